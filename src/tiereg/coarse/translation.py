"""Translation-only coarse registration of a sparse point set to a reference grid.

1. Grid the moving points on the reference lattice (same cell size, snapped corners), so the two
   grids differ by an integer number of cells plus the sub-cell remainder.
2. Prepare both grids (detrend, normalized-convolution fill, band-pass; ``preprocess``).
3. Candidates: the top peaks of the phase-only matched filter (POMF) surface and of the masked
   NCC surface (Padfield 2012); every candidate is scored by masked NCC weighted by the square
   root of its overlap fraction.
4. The best candidate is refined below a cell (parabola on the NCC peak, then least squares of
   the points against the reference surface); the height offset is the median difference.
5. Confidence: NCC at the peak, distinctness (best over second-best distinct peak), overlap, and
   a model check: if a small rotation or scale change correlates better than none, a
   translation-only answer cannot be trusted.
"""

from __future__ import annotations

import time

import numpy as np

from ..grid import Grid, GridSpec, rasterize
from ..surface import SurfaceSampler
from ..transform import Transform
from .correlation import (
    cross_power_correlation,
    local_maxima,
    masked_ncc,
    peak_to_sidelobe,
    second_peak,
    shift_of_index,
    subpixel_peak,
)
from .preprocess import Prepared, prepare
from .refine import height_offset, refine_translation
from .result import Candidate, CoarseResult, Evidence, ModelCheck, Refinement

MIN_OVERLAP = 0.3  # of the moving grid's support
MIN_NCC = 0.5
MIN_PEAK_RATIO = 1.6  # true matches >= 1.9, spurious <= 1.51 in the tests' synthetic scenes
# perturbations (kappa, scale) tried about the block centre by the model check
MODEL_CHECK = ((np.radians(2.0), 1.0), (np.radians(-2.0), 1.0), (np.radians(6.0), 1.0),
               (np.radians(-6.0), 1.0), (0.0, 1.03), (0.0, 1 / 1.03), (0.0, 1.1), (0.0, 1 / 1.1))
MODEL_CHECK_GAIN = 0.85  # a perturbation whose residual NMAD is below 85 % of ours wins


def _grid_moving(xyz: np.ndarray, ref_spec: GridSpec) -> Grid:
    c = ref_spec.cell_size
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    spec = GridSpec.from_bounds(lo[0], lo[1], hi[0], hi[1], c)
    return rasterize(xyz, spec, stats=("median",))


def _best_shift(ref: Prepared, mov: Prepared) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ncc, n = masked_ncc(ref.image, ref.support, mov.image, mov.support)
    overlap = n / max(float(mov.support.sum()), 1.0)
    score = np.where(overlap >= MIN_OVERLAP, ncc * np.sqrt(np.clip(overlap, 0, 1)), -np.inf)
    return ncc, overlap, score


def _model_check(
    xyz: np.ndarray, sampler: SurfaceSampler, translation: np.ndarray, sigma: float, cell: float
) -> ModelCheck:
    """Residual NMAD after re-fitting the shift for slightly rotated or scaled copies of the block.

    If a rotated or scaled block fits the reference clearly better than the shifted one, the
    data hold a rotation or scale that a translation-only answer ignores. Scores are residual
    spreads of the points against the reference surface, each after its own sub-cell shift fit,
    so grid alignment noise does not enter.
    """
    centre = xyz.mean(axis=0)
    turned = []
    for kappa, s in MODEL_CHECK:
        T_try = Transform.about(centre, Transform.from_parameters(scale=s, kappa=kappa))
        fit = refine_translation(T_try.apply(xyz), sampler, translation, search_radius=2 * cell)
        turned.append((float(np.degrees(kappa)), s, fit.sigma0))
    return ModelCheck(sigma, tuple(turned))


def register_translation(
    moving_xyz: np.ndarray,
    reference: Grid,
    *,
    reference_stat: str = "mean",
    reference_fine: Grid | None = None,
    n_candidates: int = 5,
    model_check: bool = True,
) -> CoarseResult:
    """Find the horizontal shift and height offset that put ``moving_xyz`` onto ``reference``.

    ``moving_xyz`` should be centred near the origin for precision (the pipeline does this);
    the returned ``T_ref_mov`` is a pure translation in the same coordinates.
    ``reference_fine``, a finer grid of the same reference, makes the sub-cell refinement
    sharper; without it the coarse grid serves.
    """
    t_start = time.perf_counter()
    spec = reference.spec
    c = spec.cell_size
    mgrid = _grid_moving(moving_xyz, spec)
    ref = prepare(reference[reference_stat], reference.mask)
    mov = prepare(mgrid["median"], mgrid.mask)
    ncc, overlap, score = _best_shift(ref, mov)
    valid = np.isfinite(score)

    pomf = cross_power_correlation(ref.image, mov.image, normalization="pomf")
    proposals = [(p, "pomf") for p in local_maxima(pomf, k=n_candidates, valid=valid)]
    proposals += [(p, "ncc") for p in local_maxima(score, k=n_candidates, valid=valid)]

    def to_map(index: tuple[float, float]) -> tuple[float, float]:
        dr, dc = shift_of_index(index, mgrid.spec.shape)
        return (spec.x0 - mgrid.spec.x0 + dc * c, spec.y0 - mgrid.spec.y0 - dr * c)

    candidates = _verified(proposals, score, ncc, overlap, to_map)
    if not candidates:
        return CoarseResult(Transform.identity(), "pomf", False, 0.0, c, 0.0, 1.0, 0.0, 0.0, (),
                            ("the two data sets do not overlap by at least "
                             f"{MIN_OVERLAP:.0%} of the moving block at any shift",),
                            time.perf_counter() - t_start)

    candidates.sort(key=lambda item: -item[0].score)
    best, best_idx = candidates[0]
    second = second_peak(score, best_idx)
    peak_ratio = best.score / second if second > 0 else float("inf")
    psr = peak_to_sidelobe(np.where(valid, score, 0.0), best_idx)

    # sub-cell: parabola on the NCC surface, then least squares against the reference surface
    sampler = SurfaceSampler.from_grid(reference_fine or reference, stat=reference_stat)
    shift_xy = np.array(to_map(subpixel_peak(ncc, best_idx)))
    translation, fit, reasons = _sub_cell(moving_xyz, sampler, shift_xy, c)
    reasons += _peak_reasons(best, peak_ratio)
    check: ModelCheck | None = None
    if model_check and np.isfinite(fit.sigma0):
        check = _model_check(moving_xyz, sampler, translation, fit.sigma0, c)
        reasons += _model_reasons(check, fit.sigma0)

    confident = not any(r for r in reasons if not r.startswith("sub-cell"))
    confidence = float(np.clip(best.ncc, 0, 1) * np.clip(peak_ratio - 1, 0, 1))
    if not confident:
        confidence = min(confidence, 0.49)
    return CoarseResult(
        T_ref_mov=Transform.from_translation(translation),
        method="pomf",
        confident=confident,
        confidence=confidence,
        cell_size=c,
        ncc=best.ncc,
        peak_ratio=float(min(peak_ratio, 1e6)),
        overlap=best.overlap,
        psr=psr,
        candidates=tuple(cand for cand, _ in candidates),
        reasons=tuple(reasons),
        seconds=time.perf_counter() - t_start,
        evidence=Evidence(
            refinement=Refinement(iterations=fit.iterations, converged=fit.converged,
                                  sigma0=fit.sigma0, n_used=fit.n_used),
            model_check=check, moving_occupancy=mgrid.occupancy),
    )


def _verified(proposals: list, score: np.ndarray, ncc: np.ndarray, overlap: np.ndarray,
              to_map) -> list[tuple[Candidate, tuple[int, int]]]:
    """The proposed peaks, each verified by the best masked-NCC score within one cell of it
    (a POMF peak may sit beside it), once each."""
    candidates: list[tuple[Candidate, tuple[int, int]]] = []
    seen: set[tuple[int, int]] = set()
    for (i, j), origin in proposals:
        win = score[max(0, i - 1) : i + 2, max(0, j - 1) : j + 2]
        di, dj = np.unravel_index(int(np.argmax(win)), win.shape)
        bi, bj = max(0, i - 1) + int(di), max(0, j - 1) + int(dj)
        if (bi, bj) in seen or not np.isfinite(score[bi, bj]):
            continue
        seen.add((bi, bj))
        sx, sy = to_map((bi, bj))
        candidates.append((Candidate(sx, sy, float(score[bi, bj]), float(ncc[bi, bj]),
                                     float(overlap[bi, bj]), origin), (bi, bj)))
    return candidates


def _sub_cell(moving_xyz: np.ndarray, sampler: SurfaceSampler, shift_xy: np.ndarray,
              cell: float):
    """The translation by least squares against the reference surface from the correlation
    peak ``shift_xy``, or the peak where that does not converge within a cell; the fit and the
    reasons."""
    tz0 = height_offset(moving_xyz, sampler, shift_xy)
    fit = refine_translation(moving_xyz, sampler, np.array([*shift_xy, tz0]),
                             search_radius=cell)
    moved = np.hypot(fit.translation[0] - shift_xy[0], fit.translation[1] - shift_xy[1])
    if fit.converged and moved <= 1.0 * cell:
        return np.array(fit.translation), fit, []
    return (np.array([*shift_xy, tz0]), fit,
            ["sub-cell refinement did not converge; kept the correlation peak"])


def _model_reasons(check: ModelCheck, sigma0: float) -> list[str]:
    rival = min(v for _, _, v in check.turned)
    if rival >= MODEL_CHECK_GAIN * sigma0:
        return []
    return ["a rotated or scaled moving block fits the reference better than a shifted one "
            f"(height residual NMAD {rival:.3g} vs {sigma0:.3g}): rotation or scale is "
            "present, which the translation-only search cannot recover"]


def _peak_reasons(best: Candidate, peak_ratio: float) -> list[str]:
    reasons = []
    if best.ncc < MIN_NCC:
        reasons.append(f"weak correlation at the best shift (NCC {best.ncc:.2f} < {MIN_NCC})")
    if peak_ratio < MIN_PEAK_RATIO:
        reasons.append(
            f"the correlation peak is not distinct (best/second {peak_ratio:.2f} < "
            f"{MIN_PEAK_RATIO})"
        )
    if best.overlap < MIN_OVERLAP:
        reasons.append(f"small overlap ({best.overlap:.0%} of the moving block)")
    return reasons
