"""What a coarse registration returns: the answer, and the typed evidence it rests on."""

from __future__ import annotations

import math
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
class Peak:
    """A hypothesis of the sweep: heading, scale (reference units per model unit) and score,
    with the height check's residual ratio where it was measured (else NaN)."""

    kappa_deg: float
    scale: float
    score: float
    residual_ratio: float = math.nan

    def to_dict(self) -> dict[str, float]:
        out = {"kappa_deg": self.kappa_deg, "scale": self.scale, "score": self.score}
        if math.isfinite(self.residual_ratio):
            out["residual_ratio"] = self.residual_ratio
        return out


@dataclass(frozen=True)
class Refinement:
    """The continuous fit of a coarse answer against the finest reference surface; the fields
    after ``n_used`` are the similarity fit's (None for a translation)."""

    iterations: int
    converged: bool
    sigma0: float
    n_used: int
    scale_change: float | None = None  # relative, against the sweep's scale
    turn_deg: float | None = None  # against the sweep's heading
    shift_cells: float | None = None  # how far the fit moved the block, in cells
    reused: bool | None = None  # an earlier fit from the same start served
    settled: bool | None = None  # converged and stayed near its start
    taken: bool | None = None  # the pose returned is the fit's

    def to_dict(self) -> dict[str, Any]:
        return {k: v for k, v in asdict(self).items() if v is not None}


@dataclass(frozen=True)
class Moments:
    """What the spectra's orientations said (``moments``): the heading they imply (modulo 180
    degrees) and how elongated each spectrum is (0: no direction)."""

    heading_from_moments_deg: float
    anisotropy_moving: float
    anisotropy_reference: float


@dataclass(frozen=True)
class ModelCheck:
    """A translation's check for a rotation or scale it ignores: the residual spread (NMAD,
    reference units) of the shifted block, and of slightly turned or scaled copies each after
    its own shift fit, as ``(kappa_deg, scale, sigma0)``."""

    translation_only: float
    turned: tuple[tuple[float, float, float], ...]

    def to_dict(self) -> dict[str, float]:
        out = {"translation_only": self.translation_only}
        out.update({f"kappa{k:+.0f}_scale{s:.3f}": v for k, s, v in self.turned})
        return out


@dataclass(frozen=True)
class Evidence:
    """What a coarse answer rests on beyond its peak; each field is None (or empty) where the
    method has no such evidence. RESULT.json's coarse stage writes it under the names of
    ``docs/result-json.md``."""

    channel: str | None = None  # "heights", or "objects": what stands on the ground
    judged: bool = True  # False: the heights' answer was not needed, so not fitted
    hypotheses: int | None = None  # how many hypotheses were scored
    search_best: Peak | None = None
    rival: Peak | None = None  # the best genuinely different hypothesis
    refinement: Refinement | None = None
    residual_ratio: float | None = None  # of the fit, taken or not
    pose_residual_ratio: float | None = None  # of the pose returned
    verified: tuple[Peak, ...] = ()
    moments: Moments | None = None
    model_check: ModelCheck | None = None
    moving_occupancy: float | None = None  # share of the tie grid's cells holding points
    decided_by: str | None = None  # with auto: "qafmt" or "search"
    timings_s: tuple[tuple[str, float], ...] = ()  # seconds per part of the stage
    other_channel: CoarseResult | None = None  # the other channel's judged answer

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        if self.channel is not None:
            out["channel"] = self.channel
        if not self.judged:
            out["judged"] = False
        if self.hypotheses is not None:
            out["hypotheses"] = self.hypotheses
        if self.search_best is not None:
            out["search_best"] = self.search_best.to_dict()
            if self.judged:
                out["rival"] = None if self.rival is None else self.rival.to_dict()
        if self.refinement is not None:
            out["refinement"] = self.refinement.to_dict()
        for name in ("residual_ratio", "pose_residual_ratio"):
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        if self.search_best is not None and self.judged:
            out["verified"] = [p.to_dict() for p in self.verified]
        if self.moments is not None:
            out.update(asdict(self.moments))
        if self.model_check is not None:
            out["model_check"] = self.model_check.to_dict()
        if self.moving_occupancy is not None:
            out["moving_occupancy"] = round(self.moving_occupancy, 4)
        if self.decided_by is not None:
            out["decided_by"] = self.decided_by
        if self.timings_s:
            out["timings_s"] = dict(self.timings_s)
        if self.other_channel is not None:
            other = self.other_channel
            out["other_channel"] = {**other.evidence.to_dict(), "confident": other.confident,
                                    "reasons": list(other.reasons)}
        return out


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
    evidence: Evidence = field(default_factory=Evidence)
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
            **self.evidence.to_dict(),
        }
