"""Coarse registration: from no initial guess to within a cell or two.

- ``auto`` (the default): on a small block ``qafmt``, then the ``search`` sweep seeded with its
  candidates unless its answer is confident and explains the heights; on a larger block the
  sweep alone (:mod:`~tiereg.coarse.similarity`).
- ``search``: heading x scale x shift by a coarse-to-fine space-domain sweep scored by masked NCC
  (:mod:`~tiereg.coarse.search`; each hypothesis scored by :mod:`~tiereg.coarse.scoring`),
  refined continuously against the lidar surface.
- ``moments``: a quick initialiser, the heading from the spectra's principal axes and a scale
  scan (:mod:`~tiereg.coarse.moments`).
- ``fmt``, ``afmt``, ``qafmt`` and their ``-classic`` forms: Fourier-Mellin candidates
  (:mod:`~tiereg.coarse.fourier_mellin`), each verified against the lidar.
- ``pomf``: translation only (phase-only matched filter candidates verified by masked NCC), then
  sub-cell refinement and the height offset (:mod:`~tiereg.coarse.translation`).
"""

from __future__ import annotations

from .result import Candidate, CoarseResult
from .translation import register_translation

METHODS = ("auto", "search", "moments", "fmt", "afmt", "qafmt", "fmt-classic", "afmt-classic",
           "qafmt-classic", "pomf", "none")

__all__ = ["METHODS", "Candidate", "CoarseResult", "register_translation"]
