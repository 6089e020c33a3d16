"""What a coarse registration returns."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

from ..transform import Transform

if TYPE_CHECKING:
    from .scoring import Hypothesis


@dataclass(frozen=True)
class Candidate:
    """One hypothesis: a horizontal shift (map units of the reference) and its evidence."""

    shift_x: float
    shift_y: float
    score: float  # the method's ranking: match_score (search), NCC x sqrt(overlap) (pomf)
    ncc: float
    overlap: float  # fraction of the moving grid's support that overlaps the reference
    source: str  # which surface proposed it: "pomf" or "ncc"


@dataclass(frozen=True)
class CoarseResult:
    """The coarse stage's answer and the evidence it rests on."""

    T_ref_mov: Transform
    method: str
    confident: bool
    confidence: float
    cell_size: float
    ncc: float
    peak_ratio: float
    overlap: float
    psr: float
    candidates: tuple[Candidate, ...]
    reasons: tuple[str, ...]
    seconds: float
    details: dict[str, Any] = field(default_factory=dict)
    # the distinct poses the searches considered (local frames, as ``T_ref_mov`` before the
    # pipeline turns it into file coordinates): the rivals the verdict refines beside the answer
    hypotheses: tuple[Hypothesis, ...] = field(default=(), repr=False, compare=False)
    # reasons no refinement can lift: the answer lies where the search could not see past it
    limits: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": "coarse",
            "method": self.method,
            "seconds": round(self.seconds, 4),
            "confident": self.confident,
            "confidence": round(self.confidence, 4),
            "cell_size": self.cell_size,
            "T_ref_mov": self.T_ref_mov.matrix.tolist(),
            "ncc": round(self.ncc, 4),
            "peak_ratio": round(self.peak_ratio, 4),
            "peak_to_sidelobe": round(self.psr, 3),
            "overlap_fraction": round(self.overlap, 4),
            "reasons": list(self.reasons),
            "candidates": [asdict(c) for c in self.candidates],
            **self.details,
        }
