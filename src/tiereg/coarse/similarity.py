"""Coarse registration with unknown heading and scale: search, refine, judge.

1. :func:`~tiereg.coarse.search.search` sweeps heading and scale (space domain, masked NCC).
2. The winner is refined continuously: heading, log-scale and shift by a robust fit of the tie
   points' heights to the finest reference surface (:func:`~tiereg.coarse.refine.fit_to_surface`);
   heights scale with the horizontal scale.
3. Confidence rests on evidence that a wrong answer rarely has all at once: a correlation peak
   that stands above every genuinely different hypothesis (another heading, scale or place), a
   high correlation at the refined pose, enough overlap, and a refinement that converged near
   where the search ended.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..reference import Reference
from ..robust import nmad
from ..transform import Transform
from .refine import SurfaceSampler, fit_to_surface
from .result import Candidate, CoarseResult
from .search import MIN_OVERLAP, Hypothesis, _NoOverlap, search

MIN_RIVAL_RATIO = 1.2  # best sweep score over the best genuinely different one
MIN_NCC = 0.45
# a second route to confidence: the refined pose explains the heights almost entirely
# (residual spread below a quarter of the surface's own spread; right answers on the simulated
# scenes: 0.08-0.16, near misses 0.53 or more, tie points from elsewhere 0.88 or more)
MAX_RESIDUAL_RATIO, MIN_NCC_EXPLAINED, MIN_RIVAL_RATIO_EXPLAINED = 0.25, 0.6, 1.05


def _place(xyz: np.ndarray):
    xy, z = xyz[:, :2], xyz[:, 2]

    def place(p: np.ndarray) -> np.ndarray:
        kappa, log_sigma, tx, ty = p
        sigma = math.exp(log_sigma)
        c, s = math.cos(kappa), math.sin(kappa)
        q = sigma * (xy @ np.array([[c, s], [-s, c]]))
        return np.column_stack([q[:, 0] + tx, q[:, 1] + ty, sigma * z])

    return place


def register_similarity(
    moving_xyz: np.ndarray,
    reference: Reference,
    *,
    tie_cell: float,
    sigma_range: tuple[float, float] = (0.25, 4.0),
    method: str = "search",
) -> CoarseResult:
    """Heading, scale, shift and height offset of centred tie points against a reference."""
    t0 = time.perf_counter()
    try:
        # level, unscaled data are common: the identity is always among the hypotheses
        found = search(moving_xyz, reference, tie_cell=tie_cell, sigma_range=sigma_range,
                       seeds=[(0.0, 1.0)] if sigma_range[0] <= 1.0 <= sigma_range[1] else None)
    except _NoOverlap:
        return CoarseResult(Transform.identity(), method, False, 0.0, tie_cell, 0.0, 1.0, 0.0,
                            0.0, (), ("no heading and scale in the searched range makes the tie "
                                      f"points overlap the reference by {MIN_OVERLAP:.0%}",),
                            time.perf_counter() - t0)
    best = found.best
    sampler = SurfaceSampler.from_grid(reference.base)
    cell = tie_cell * best.sigma
    fit = fit_to_surface(_place(moving_xyz), sampler,
                         np.array([best.kappa, math.log(best.sigma), best.tx, best.ty]),
                         np.array([math.radians(1.0), math.log(1.01), cell / 2, cell / 2]))
    kappa, log_sigma, tx, ty = fit.params
    moved = math.hypot(tx - best.tx, ty - best.ty) / cell
    turned = abs(math.degrees(kappa - best.kappa))
    rescaled = abs(log_sigma - math.log(best.sigma))
    reasons: list[str] = []
    # the fit descends from the search's pose; grid scores can drift a few per cent in scale
    # through lattice aliasing, which the point-based fit corrects: only runaways are refused
    if fit.converged and moved <= 5.0 and turned <= 10.0 and rescaled <= math.log(1.15):
        T = Transform.from_parameters(scale=math.exp(log_sigma), kappa=kappa,
                                      translation=(tx, ty, fit.tz))
    else:
        T = best.transform(tz=fit.tz if np.isfinite(fit.tz) else 0.0)
        reasons.append("the continuous refinement did not settle near the search's answer")

    # how much of the height variation the pose explains: residual spread over surface spread
    placed = _place(moving_xyz)(np.array([kappa, log_sigma, tx, ty]))
    z_surf, _, _, ok = sampler.sample(placed[:, 0], placed[:, 1])
    spread = nmad(z_surf[ok]) if ok.sum() > 10 else float("nan")
    residual_ratio = fit.sigma0 / spread if spread and np.isfinite(spread) else float("inf")

    rival = found.runner_up.score if found.runner_up is not None else 0.0
    ratio = found.sweep_best.score / rival if rival > 0 else float("inf")
    explained = (residual_ratio <= MAX_RESIDUAL_RATIO and best.ncc >= MIN_NCC_EXPLAINED
                 and ratio >= MIN_RIVAL_RATIO_EXPLAINED)
    if ratio < MIN_RIVAL_RATIO and not explained:
        reasons.append(f"another heading, scale or position fits almost as well (best/rival "
                       f"{ratio:.2f} < {MIN_RIVAL_RATIO})")
    if best.ncc < MIN_NCC:
        reasons.append(f"weak correlation at the best pose (NCC {best.ncc:.2f} < {MIN_NCC})")
    if best.overlap < MIN_OVERLAP:
        reasons.append(f"small overlap ({best.overlap:.0%} of the tie points)")
    confident = not reasons
    # the stronger of the two kinds of evidence: a distinct peak, or heights explained
    distinct = np.clip((ratio - 1) / 0.5, 0, 1)
    fit_quality = np.clip(1 - residual_ratio / (2 * MAX_RESIDUAL_RATIO), 0, 1)
    confidence = float(np.clip(best.ncc, 0, 1) * max(distinct, fit_quality))
    if not confident:
        confidence = min(confidence, 0.49)

    def candidate(h: Hypothesis) -> Candidate:
        return Candidate(h.tx, h.ty, h.score, h.ncc, h.overlap, f"search level {h.level}")

    return CoarseResult(
        T_ref_mov=T, method=method, confident=confident, confidence=confidence,
        cell_size=cell, ncc=best.ncc, peak_ratio=float(min(ratio, 1e6)), overlap=best.overlap,
        psr=0.0, candidates=tuple(candidate(h) for level in found.levels for h in level),
        reasons=tuple(reasons), seconds=time.perf_counter() - t0,
        details={
            "hypotheses": found.n_hypotheses,
            "search_best": {"kappa_deg": math.degrees(best.kappa), "scale": best.sigma,
                            "score": best.score},
            "rival": None if found.runner_up is None else {
                "kappa_deg": math.degrees(found.runner_up.kappa),
                "scale": found.runner_up.sigma, "score": found.runner_up.score},
            "refinement": {"iterations": fit.iterations, "converged": fit.converged,
                           "sigma0": fit.sigma0, "n_used": fit.n_used},
            "residual_ratio": residual_ratio,
        },
    )
