"""Coarse registration: from no initial guess to within a cell or two.

Today: ``pomf``, a translation-only search (phase-only matched filter candidates verified by
masked normalized cross-correlation), followed by sub-cell refinement and the height offset.
"""

from __future__ import annotations

from .result import Candidate, CoarseResult
from .translation import register_translation

METHODS = ("auto", "pomf", "none")

__all__ = ["METHODS", "Candidate", "CoarseResult", "register_translation"]
