"""Coarse registration: from no initial guess to within a cell or two.

``search`` (and ``auto``, which is ``search`` in this version): heading x scale x shift by a
coarse-to-fine space-domain search scored by masked NCC, refined continuously (module
:mod:`~tiereg.coarse.similarity`). ``pomf``: translation only (phase-only matched filter
candidates verified by masked NCC), then sub-cell refinement and the height offset.
"""

from __future__ import annotations

from .result import Candidate, CoarseResult
from .translation import register_translation

METHODS = ("auto", "search", "fmt", "afmt", "qafmt", "fmt-classic", "afmt-classic",
           "qafmt-classic", "pomf", "none")

__all__ = ["METHODS", "Candidate", "CoarseResult", "register_translation"]
