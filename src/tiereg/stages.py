"""The stages of a registration as :func:`tiereg.pipeline.register` runs them.

Each stage takes the tie points in the local (centred) frames and a starting pose, and returns a
frozen result: the coarse stage with its verdict (:func:`coarse_stage`), the fine stage
(:func:`fine_stage`) and the heights after registration (:func:`heights_after`). Poses here are
``T_local``: the moving points' local frame (centred at ``Frames.o_mov``) into the reference's
(centred at ``Frames.o_ref``).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace

import numpy as np

from .coarse import CoarseResult, register_translation
from .coarse.scoring import MAX_REFERENCE_CELLS, MAX_TIE_SIDE, ScaleRange
from .coarse.similarity import register_similarity
from .errors import InputError
from .evaluate import MIN_LIDAR_POINTS, SURFACE_RADIUS_SPACINGS, height_differences
from .fine import FineResult, register_fine
from .quality import HeightStats, PointResiduals
from .reference import Reference
from .surface import LocalSurface, SurfaceSampler
from .transform import Transform
from .verdict import Verdict, imprecision, judge_refined

log = logging.getLogger(__name__)

MIN_TIE_SIDE = 32  # a coarser tie cell is tried only while the block spans this many cells


@dataclass(frozen=True)
class Frames:
    """The local frames of a registration: ``o_ref`` and ``o_mov`` are their origins in file
    coordinates (the moving points after ``T_start``, the caller's starting pose)."""

    o_ref: np.ndarray
    o_mov: np.ndarray
    T_start: Transform

    def to_world(self, T_local: Transform) -> Transform:
        """``T_ref_mov`` in file coordinates, the starting pose included."""
        return (Transform.from_translation(self.o_ref) @ T_local
                @ Transform.from_translation(-self.o_mov) @ self.T_start)

    @property
    def T_start_local(self) -> Transform:
        """The starting pose between the local frames (the moving points are already placed by
        ``T_start``)."""
        return Transform.from_translation(self.o_ref).inverse @ Transform.from_translation(
            self.o_mov)


def height_stats(xyz_ref: np.ndarray, sampler: SurfaceSampler) -> HeightStats:
    return HeightStats.from_dz(height_differences(xyz_ref, sampler), len(xyz_ref))


# --- coarse ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class CoarseStage:
    """The coarse stage and its verdict: the pose the fine stage starts from."""

    T_local: Transform
    cell_size: float  # the registration's cell, reference units
    before: HeightStats  # the heights at the starting pose
    confident: bool
    confidence: float
    reasons: tuple[str, ...]
    result: CoarseResult | None = None  # its T_ref_mov in file coordinates
    verdict: Verdict | None = None

    @property
    def hopeless(self) -> bool:
        """No pose found explains the tie points' heights: the fine stage cannot help."""
        if self.verdict is not None:
            return not self.verdict.best.explains_heights
        return self.result is not None and not self.confident


def translation_grid(ref: Reference, moving: np.ndarray, *, cell_size: float | None,
                     tie_cell: float):
    """The reference grid a translation-only search correlates, at ``cell_size`` (reference
    units) where given, else at the tie cell, coarsened where either would exceed
    :data:`~tiereg.coarse.scoring.MAX_REFERENCE_CELLS` or
    :data:`~tiereg.coarse.scoring.MAX_TIE_SIDE` cells a side; a given ``cell_size`` that fine is
    refused."""
    (x0, y0, x1, y1) = ref.base.spec.bounds
    extent = np.ptp(moving[:, :2], axis=0).max()
    least = max(max(x1 - x0, y1 - y0) / MAX_REFERENCE_CELLS, extent / MAX_TIE_SIDE)
    if cell_size is not None and cell_size < least:
        raise InputError(f"cell_size {cell_size:g} is too fine for a translation-only search of "
                         f"this reference and block; give cell_size of at least {least:.3g} "
                         "(reference units), or let the coarse stage find the scale too")
    if cell_size is None and tie_cell < least:  # a whole number of base cells, not below
        least = ref.base_cell * math.ceil(least / ref.base_cell - 1e-9)
        log.info("translation search: tie cell %.4g -> %.4g (grid size bound)", tie_cell, least)
        cell_size = least
    return ref.grid(cell_size if cell_size is not None else tie_cell)


def coarser_tie_cell(scale: float, moving: np.ndarray, ref: Reference,
                     tie_cell: float) -> float | None:
    """Twice ``tie_cell`` when an answer at ``scale`` (reference units per model unit) lies
    within a sweep step of the smallest scale the search could reach with ``tie_cell`` and the
    block still spans :data:`MIN_TIE_SIDE` doubled cells (a dense model gridded as if
    thinned), else None."""
    extent = float(np.max(moving[:, :2].max(axis=0) - moving[:, :2].min(axis=0)))
    if (not ScaleRange.of(moving, ref, tie_cell).at_lowest(scale)
            or extent / (2 * tie_cell) < MIN_TIE_SIDE):
        return None
    return 2 * tie_cell


def similarity_search(moving: np.ndarray, ref: Reference, *, tie_cell: float, method: str,
                      free_tilt: bool, scale_range: tuple[float, float] | None = None
                      ) -> tuple[CoarseResult, float]:
    """:func:`~tiereg.coarse.similarity.register_similarity`, searched again with a coarser tie
    cell while its answer lies at the smallest scale the tie cell lets the reference be searched
    at (the block may be smaller still); the result and the tie cell it was found with.
    ``scale_range``: where the scale is known to lie (:func:`searched_scales`)."""
    def once(cell: float) -> CoarseResult:
        return register_similarity(moving, ref, tie_cell=cell, method=method,
                                   free_tilt=free_tilt,
                                   scales=searched_scales(moving, ref, cell, scale_range))

    result = once(tie_cell)
    while (coarser := coarser_tie_cell(result.T_ref_mov.scale, moving, ref,
                                       tie_cell)) is not None:
        log.info("answer at the smallest scale searched: tie cell %.4g -> %.4g", tie_cell,
                 coarser)
        tie_cell = coarser
        result = once(tie_cell)
    return result, tie_cell


def searched_scales(moving: np.ndarray, ref: Reference, tie_cell: float,
                    scale_range: tuple[float, float] | None) -> ScaleRange | None:
    """The scales the similarity search looks at: where the block can be found at all
    (:meth:`ScaleRange.of`), within ``scale_range`` where the caller knows it (None: the
    default, all of them)."""
    if scale_range is None:
        return None
    found = ScaleRange.of(moving, ref, tie_cell)
    return ScaleRange(max(found.lowest, scale_range[0]), min(found.highest, scale_range[1]))


def no_coarse_stage(mov_local: np.ndarray, ref: Reference, frames: Frames, *,
                    cell_size: float) -> CoarseStage:
    """The starting pose kept (``coarse="none"``): the moving points are in the reference frame
    already; confident of nothing, but the fine stage runs where they overlap the lidar."""
    T_local = frames.T_start_local
    before = height_stats(T_local.apply(mov_local), ref.surface())
    return CoarseStage(T_local, cell_size, before, before.overlap_fraction > 0.3, 0.0,
                       ("no coarse registration was asked for (`coarse` none)",))


def coarse_stage(mov_local: np.ndarray, keep: np.ndarray, ref: Reference, frames: Frames, *,
                 method: str, tie_cell: float, cell_size: float | None,
                 free_tilt: bool, scale_range: tuple[float, float] | None = None
                 ) -> CoarseStage:
    """The coarse registration by ``method`` (``"pomf"``: translation only, judged by its own
    peaks; else a similarity, judged by the refined fits of the answer and its rivals,
    :func:`~tiereg.verdict.judge_refined`)."""
    if method == "pomf":  # level data at the reference's scale: a cell in its units
        grid = translation_grid(ref, mov_local[keep], cell_size=cell_size, tie_cell=tie_cell)
        result = register_translation(mov_local[keep], grid, reference_fine=ref.base)
    else:  # search, auto and the Fourier-Mellin forms
        result, tie_cell = similarity_search(mov_local[keep], ref, tie_cell=tie_cell,
                                             method=method, free_tilt=free_tilt,
                                             scale_range=scale_range)
    T_local = result.T_ref_mov
    log.info("coarse (%s): scale %.6g, heading %.2f deg, %s (%.1f s)", method,
             T_local.scale, math.degrees(T_local.parameters().kappa) % 360.0,
             "confident" if result.confident else "not confident", result.seconds)
    # the registration's cell, in reference units: the tie cell at the scale found
    cell_size = cell_size or result.cell_size
    before = height_stats(frames.T_start_local.apply(mov_local), ref.surface())
    verdict = None
    if method == "pomf":
        confident, confidence = result.confident, result.confidence
        reasons = tuple(result.reasons)
    else:  # the refined fits of the answer and its rivals decide
        t0 = time.perf_counter()
        verdict = judge_refined(mov_local[keep], ref, result, tie_cell=tie_cell, cell=cell_size)
        T_local = verdict.best.T
        confident = verdict.confident and not result.limits
        confidence = verdict.confidence if confident else min(verdict.confidence, 0.49)
        reasons = tuple(verdict.reasons + result.limits)
        log.info("verdict: pose %d of %d (0: the coarse answer), %s (%.1f s)", verdict.chosen,
                 len(verdict.poses), "confident" if confident else "not confident",
                 time.perf_counter() - t0)
    world = replace(result, T_ref_mov=frames.to_world(result.T_ref_mov))
    return CoarseStage(T_local, cell_size, before, confident, confidence, reasons, world,
                       verdict)


# --- fine -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class FineStage:
    """The fine stage's outcome: the final pose and what it changed in the verdict."""

    T_local: Transform
    result: FineResult | None
    confident: bool
    confidence: float  # the coarse stage's, at most 0.49 once the fine stage withdraws it
    reasons: tuple[str, ...] = ()  # added to the coarse stage's
    warnings: tuple[str, ...] = ()
    note: str = ""  # why it did not run


def fine_stage(mov_local: np.ndarray, keep: np.ndarray, ref: Reference, start: CoarseStage, *,
               method: str, coarse_method: str) -> FineStage:
    """The fine registration from ``start``'s pose (:func:`~tiereg.fine.register_fine`), unless
    ``method`` is ``"none"`` or no pose explains the heights; a refusal costs the confidence
    unless the verdict's refined fit vouches for the coarse pose (never when the fine stage
    did not converge), and so does an answer less precise than the verdict's noise allows
    (:func:`~tiereg.verdict.imprecision`)."""
    if method == "none":
        return FineStage(start.T_local, None, start.confident, start.confidence,
                         note="not asked for (`fine` none)")
    if start.hopeless:
        return FineStage(start.T_local, None, start.confident, start.confidence,
                         note="skipped: no pose found explains the tie points' heights")
    result = register_fine(start.T_local.apply(mov_local[keep]), ref, cell_size=start.cell_size,
                           method="lsm" if method == "auto" else method)
    log.info("fine (%s): %s (%.1f s)", result.method,
             f"refused: {result.refused}" if result.refused else "accepted", result.seconds)
    T_local, confident = start.T_local, start.confident
    reasons: list[str] = []
    warnings: list[str] = []
    # a fine stage that does not settle near the coarse pose says the tie points' heights do
    # not pin it there: the verdict's cheaper fit cannot vouch for it then (upside-down mountain
    # blocks matched at a tenth of their scale were confident so)
    vouched = (start.verdict is not None and not result.contradicts_coarse
               and result.fit.converged)
    if result.refused and vouched:
        # the verdict's refined fit already placed the tie points on the surface; a fine
        # stage that finds nothing better leaves that pose as the answer
        warnings.append(f"the fine stage kept the coarse answer: {result.refused}")
    elif result.refused:
        # nothing vouches for the pose to the tie points' precision, and a fine answer that
        # moves far contradicts it
        confident = False
        reasons.append(_refusal_reason(result, coarse_method))
    else:
        T_local = result.T_increment @ T_local
        imprecise = (imprecision(start.verdict, result.fit.sigma[4:7])
                     if start.verdict is not None else None)
        if imprecise and confident:
            confident = False
            reasons.append(imprecise)
    if result.held and not result.refused:
        warnings.append(f"the data do not determine {', '.join(result.held)} (flat or "
                        "featureless ground): held at the coarse answer")
    confidence = start.confidence if confident else min(start.confidence, 0.49)
    return FineStage(T_local, result, confident, confidence, tuple(reasons), tuple(warnings))


def _refusal_reason(result: FineResult, coarse_method: str) -> str:
    start = "starting pose" if coarse_method == "none" else "coarse answer"
    advice = ("check the inputs (noise points in the lidar not classed as noise, a wrong "
              "unit or CRS)" if result.contradicts_coarse else
              "give a closer starting pose (`initial`), or let the coarse stage find it"
              if coarse_method == "none" else "check the inputs")
    verb = "contradicts" if result.contradicts_coarse else "could not confirm"
    return f"the fine stage {verb} the {start}: {result.refused}; {advice}"


# --- the heights after registration ---------------------------------------------------------

def _scatter(values: np.ndarray, where: np.ndarray) -> np.ndarray:
    """``values`` of the points set in ``where``, NaN for the others: a value per point."""
    out = np.full(len(where), np.nan)
    out[where] = values
    return out


def heights_after(mov_local: np.ndarray, keep: np.ndarray, ref: Reference, start: CoarseStage,
                  fine: FineStage) -> tuple[HeightStats, PointResiduals]:
    """The tie points' heights against the lidar after registration, and per point before and
    after the fine stage: against the lidar's own points where the fine stage read them (a grid
    cell's mean is metres off beside walls and in canopy gaps), else against the grid."""
    placed = fine.T_local.apply(mov_local)
    surface: SurfaceSampler | LocalSurface = ref.surface()
    result = fine.result
    if (result is not None and result.lidar is not None
            and len(result.lidar) >= MIN_LIDAR_POINTS):
        surface = LocalSurface(result.lidar, radius=SURFACE_RADIUS_SPACINGS * ref.spacing)
    dz_after = height_differences(placed, surface)
    after = HeightStats.from_dz(dz_after, len(placed))
    accepted = result is not None and not result.refused
    weights = (_scatter(np.where(np.isfinite(result.fit.residuals), result.fit.weights, np.nan),
                        keep) if accepted else None)
    residuals = PointResiduals.from_dz(
        placed + ref.origin, height_differences(start.T_local.apply(mov_local), surface),
        dz_after, weights)
    return after, residuals
