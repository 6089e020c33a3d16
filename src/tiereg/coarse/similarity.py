"""Coarse registration with unknown heading and scale: search, refine, judge.

1. :func:`~tiereg.coarse.search.search` sweeps heading and scale (space domain, masked NCC).
2. The winner is refined continuously: heading, log-scale and shift by a robust fit of the tie
   points' heights to the finest reference surface (:func:`~tiereg.coarse.refine.fit_to_surface`);
   heights scale with the horizontal scale (:mod:`~tiereg.coarse.judge`).
3. Confidence rests on evidence that a wrong answer rarely has all at once: a correlation peak
   that stands above every genuinely different hypothesis (another heading, scale or place), a
   high correlation at the refined pose, enough overlap, and a refinement that converged near
   where the search ended.
4. When the heights do not decide (flat farmland), the search is run again on what stands on the
   ground (:data:`~tiereg.coarse.scoring.OBJECTS`), judged by thresholds of its own
   (:data:`~tiereg.coarse.judge.TRUST`). Where the checks that need no fit already rule out the
   heights' answer (:func:`~tiereg.coarse.judge.may_be_confident`), it is judged only if the
   objects' answer is not confident (:func:`judged_by_turns`).
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np

from ..grid import GridSpec, rasterize
from ..parallel import map_threads
from ..reference import Reference
from ..transform import Transform
from .fourier_mellin import rotation_scale_candidates
from .judge import (
    FREQUENCY_METHODS,
    TRUST,
    FitCache,
    considered,
    judge,
    may_be_confident,
    may_explain,
    peak,
    rival_ratio,
    starts_same,
)
from .moments import moments_search
from .preprocess import prepare
from .result import CoarseResult, Evidence, Moments
from .scoring import (
    HEIGHTS,
    MAX_REFERENCE_CELLS,
    MIN_OVERLAP,
    OBJECTS,
    Hypothesis,
    ScaleRange,
    Scorer,
)
from .search import (
    HeightCheck,
    NoOverlap,
    SearchResult,
    search,
    small_block,
    verify_candidates,
)


def frequency_search(
    moving: np.ndarray,
    ref: Reference,
    *,
    tie_cell: float,
    method: str,
    scales: ScaleRange | None = None,
    heights: HeightCheck | None = None,
) -> SearchResult:
    """Candidates from a Fourier-Mellin method on a 2x pyramid of reference cells, verified
    (``heights``: as in :func:`~tiereg.coarse.search.verify_candidates`).

    At each level ``s`` (the powers of two in ``scales``, default
    :class:`~tiereg.coarse.scoring.ScaleRange`) the reference is gridded at ``tie_cell * s`` and
    the tie points at ``tie_cell`` (model units), so the method only has to find the residual
    scale within the level's octave. Each candidate is scored by masked NCC, the best distinct
    ones refined. Levels that would grid the reference finer than
    :data:`~tiereg.coarse.scoring.MAX_REFERENCE_CELLS` a side are not tried: no transform is
    larger than twice that (and the tie grid's :data:`~tiereg.coarse.scoring.MAX_TIE_SIDE`).
    """
    name, robust = method.removesuffix("-classic"), not method.endswith("-classic")
    scales = scales or ScaleRange.of(moving, ref, tie_cell)
    scorer = Scorer(moving, ref, tie_cell, 2)
    lo, hi = moving[:, :2].min(axis=0), moving[:, :2].max(axis=0)
    spec = GridSpec.from_bounds(lo[0], lo[1], hi[0], hi[1], tie_cell)
    mgrid = rasterize(moving, spec, stats=("median",))
    mov = prepare(mgrid["median"], mgrid.mask,
                  bandpass_sigma_cells=6.0 if robust else 0.0)

    def level_candidates(s_level: float) -> list[tuple[float, float]]:
        if scorer.too_fine(s_level / 2):  # the grid at the level's cell: too many cells
            return []
        grid = ref.grid(tie_cell * s_level)
        s_eff = grid.spec.cell_size / tie_cell  # the quantized cell's own scale
        rgrid = prepare(grid["mean"], grid.mask, bandpass_sigma_cells=6.0 if robust else 0.0)
        if rgrid.support.sum() < 12:
            return []
        found = ((c.theta, c.scale * s_eff)
                 for c in rotation_scale_candidates(rgrid, mov, method=name, robust=robust))
        return [(theta, sigma) for theta, sigma in found
                if scales.lowest / 1.5 <= sigma <= scales.highest * 1.5]

    # the powers of two from the one at or below the lowest scale to the one at or above the
    # highest: each level's octave holds the candidates around it
    levels = [2.0**k for k in range(math.floor(math.log2(scales.lowest)),
                                    math.ceil(math.log2(scales.highest)) + 1)]
    tried = [c for level in map_threads(level_candidates, levels, workers=None) for c in level]
    scorer.prepare_for(sigma for _, sigma in tried)
    scored = map_threads(lambda kappa_sigma: scorer.score(*kappa_sigma), tried, workers=None)
    hyps = [h for h in scored if h is not None]
    return verify_candidates(moving, ref, hyps, tie_cell=tie_cell, keep=6,
                             log_sigma=math.log(1.1), n_tried=len(tried), scales=scales,
                             heights=heights)


def register_similarity(
    moving_xyz: np.ndarray,
    reference: Reference,
    *,
    tie_cell: float,
    scales: ScaleRange | None = None,
    method: str = "search",
    seeds: list[tuple[float, float]] | None = None,
    fits: FitCache | None = None,
    free_tilt: bool = False,
) -> CoarseResult:
    """Heading, scale, shift and height offset of centred tie points against a reference.

    ``method``: ``"search"`` (exhaustive sweep), ``"moments"`` (heading from the spectra's
    orientations, :mod:`~tiereg.coarse.moments`), a Fourier-Mellin method (``fmt``, ``afmt``,
    ``qafmt``, robust; ``*-classic``: as published), or ``"auto"`` (on a
    :func:`~tiereg.coarse.search.small_block`, ``qafmt``, then the sweep seeded with its
    candidates unless its answer is confident and explains the heights; on a larger block the
    sweep).
    ``scales``: the scales searched (reference units per model unit; default: every scale at
    which the block can be found in the reference, :class:`~tiereg.coarse.scoring.ScaleRange`).
    ``free_tilt``: the block may lean by a degree or more (a model levelled from its own
    points), so its heights are compared after a fitted plane
    (:class:`~tiereg.coarse.search.HeightCheck`).
    """
    seeds = list(seeds or [])
    t0 = time.perf_counter()
    scales = scales or ScaleRange.of(moving_xyz, reference, tie_cell)
    fits = FitCache.of(reference) if fits is None else fits  # the finest surface, for all
    if method == "auto":
        return _register_auto(moving_xyz, reference, tie_cell=tie_cell, scales=scales, fits=fits,
                              free_tilt=free_tilt, t0=t0)
    heights = HeightCheck(fits.sampler, free_tilt=free_tilt)
    moments: Moments | None = None
    timings: dict[str, float] = {}
    try:
        if method in FREQUENCY_METHODS:
            found = frequency_search(moving_xyz, reference, tie_cell=tie_cell, method=method,
                                     scales=scales, heights=heights)
        elif method == "moments":
            found, moments = moments_search(moving_xyz, reference, tie_cell=tie_cell,
                                            scales=scales, heights=heights)
        else:
            # level, unscaled data are common: the identity is always among the hypotheses
            found = search(moving_xyz, reference, tie_cell=tie_cell, scales=scales,
                           seeds=[(0.0, 1.0), *seeds], heights=heights)
    except NoOverlap:
        return CoarseResult(Transform.identity(), method, False, 0.0, tie_cell, 0.0, 1.0, 0.0,
                            0.0, (), (no_overlap_reason(scales),), time.perf_counter() - t0)
    timings[method] = time.perf_counter() - t0
    options = {"method": method, "tie_cell": tie_cell, "moments": moments, "fits": fits}
    # where the checks that need no fit already rule out a confident answer from the heights,
    # what stands on the ground is searched first, and the heights' answer is judged only if
    # it is still needed (:func:`judged_by_turns`): on the 95 large blocks of the coarse
    # benchmark's timing, all 37 whose heights were not confident were ruled out so
    heights_decide = method != "search" or may_be_confident(found, TRUST[HEIGHTS.name])
    result = judge_choice(moving_xyz, found, **options) if heights_decide else None
    timings["judge"] = result.seconds if result is not None else 0.0
    if method == "search" and (result is None or not result.confident):
        result = _objects_too(moving_xyz, reference, found, result, options, seeds=seeds,
                              scales=scales, heights=heights, timings=timings)
    return replace(result, seconds=time.perf_counter() - t0,
                   evidence=replace(result.evidence, timings_s=_rounded(timings)))


def _register_auto(moving_xyz: np.ndarray, reference: Reference, *, tie_cell: float,
                   scales: ScaleRange, fits: FitCache, free_tilt: bool,
                   t0: float) -> CoarseResult:
    """``method="auto"`` of :func:`register_similarity`."""
    if not small_block(moving_xyz, tie_cell):
        # a large block goes straight to the sweep: on the coarse benchmark's large blocks
        # (3,150 tie points) qafmt was confident in 4 of 95 cases, which the sweep also found,
        # its seeds changed no answer, and it cost about 0.9 s a case
        auto = register_similarity(moving_xyz, reference, tie_cell=tie_cell,
                                   scales=scales, method="search", fits=fits,
                                   free_tilt=free_tilt)
        return replace(auto, method="auto",
                       evidence=replace(auto.evidence, decided_by="search"))
    # frequency domain first; the exhaustive sweep when that is not enough
    heights = HeightCheck(fits.sampler, free_tilt=free_tilt)
    try:
        quick = frequency_search(moving_xyz, reference, tie_cell=tie_cell, method="qafmt",
                                 scales=scales, heights=heights)
    except NoOverlap:
        quick = None
    # the continuous fit is the dear part of judging: spared when the candidates' own
    # scores already rule out a confident answer (the same verdict, judge's rules)
    timings = {"qafmt": time.perf_counter() - t0}
    if quick is not None and may_explain(quick, TRUST[HEIGHTS.name]):
        judged = judge_choice(moving_xyz, quick, method="qafmt", tie_cell=tie_cell, fits=fits)
        timings["qafmt_judge"] = judged.seconds
        if judged.confident:
            return replace(judged, method="auto", seconds=time.perf_counter() - t0,
                           evidence=replace(judged.evidence, decided_by="qafmt",
                                            timings_s=_rounded(timings)))
    seeds = [] if quick is None else [(h.kappa, h.sigma) for lv in quick.levels for h in lv]
    full = register_similarity(moving_xyz, reference, tie_cell=tie_cell,
                               scales=scales, method="search", seeds=seeds,
                               fits=fits, free_tilt=free_tilt)
    return replace(full, method="auto", seconds=time.perf_counter() - t0,
                   hypotheses=full.hypotheses + considered(quick),
                   evidence=replace(full.evidence, decided_by="search", timings_s=_rounded(
                       {**timings, **dict(full.evidence.timings_s)})))


def _objects_too(moving_xyz: np.ndarray, reference: Reference, found: SearchResult,
                 result: CoarseResult | None, options: dict, *, seeds: list,
                 scales: ScaleRange, heights: HeightCheck,
                 timings: dict[str, float]) -> CoarseResult:
    """The heights did not decide: what stands on the ground may (flat farmland). The sweep
    searched again on the objects channel and the two judged in turns; ``timings`` gains
    ``judge`` and ``objects``."""
    t_objects = time.perf_counter()
    try:
        objects = search(moving_xyz, reference, tie_cell=options["tie_cell"], scales=scales,
                         seeds=[(0.0, 1.0), *seeds], channel=OBJECTS, heights=heights)
    except NoOverlap:
        objects = None
    t_searched = time.perf_counter()
    result, second = judged_by_turns(moving_xyz, found, objects, result, options)
    timings["judge"] = result.seconds
    if second is None:
        return result
    # neither confident: the answer whose fit explains the heights better (taking the
    # more distinct of the two peaks lost two right answers on the benchmark and gained
    # none; on the simulated farmland what stands on the ground often finds the truth
    # without a peak distinct enough to be sure)
    timings["objects"] = t_searched - t_objects + second.seconds
    take = second.confident or (not result.confident and explains_better(second, result))
    result, other = (second, result) if take else (result, second)
    return replace(result, hypotheses=result.hypotheses + other.hypotheses,
                   evidence=replace(result.evidence, other_channel=other))


def no_overlap_reason(scales: ScaleRange) -> str:
    """Why no hypothesis could be scored, and what to do."""
    if scales.lowest > scales.highest:
        return ("the reference is too wide for this block: at every scale at which the block "
                "could overlap it, its grid would need more than "
                f"{MAX_REFERENCE_CELLS} cells a side; crop the reference to the block's "
                "surroundings")
    return (f"no heading and scale ({scales.lowest:.3g}-{scales.highest:.3g} reference units "
            f"per model unit) makes the tie points overlap the reference by {MIN_OVERLAP:.0%}")


def judged_by_turns(
    moving_xyz: np.ndarray,
    heights: SearchResult,
    objects: SearchResult | None,
    judged: CoarseResult | None,
    options: dict,
) -> tuple[CoarseResult, CoarseResult | None]:
    """The verdicts on the heights' answer and on the objects' (``None`` without one), with the
    heights' judged only where needed: unless ``judged`` already, when the objects are not
    confident, or first when the two answers start their fits at the same pose (the heights'
    fit then serves both, as it would have had the heights been judged first). A heights'
    answer not judged is reported as such, not confident.

    The verdicts are those of judging the heights and then the objects: a fit is reused only
    for a hypothesis that starts the same (:meth:`FitCache.fit`), and one that does not start
    where any of the other channel's fits did is made afresh in either order.
    """
    def shared(a: SearchResult, b: SearchResult) -> bool:
        cell = options["tie_cell"]  # a pose is judged at the tie cell times its scale
        return any(starts_same(h, g, cell * h.sigma) or starts_same(g, h, cell * g.sigma)
                   for h in _judged_poses(a) for g in _judged_poses(b))

    if judged is None and (objects is None or shared(heights, objects)):
        judged = judge_choice(moving_xyz, heights, **options)
    if objects is None:
        return judged, None
    second = judge_choice(moving_xyz, objects, channel=OBJECTS, **options)
    if judged is None and not second.confident:
        judged = judge_choice(moving_xyz, heights, **options)
    if judged is None:
        judged = _not_judged(heights, method=options["method"], tie_cell=options["tie_cell"])
    return judged, second


def _judged_poses(found: SearchResult) -> list[Hypothesis]:
    """The hypotheses :func:`judge_choice` fits: the answer, and its alternative's."""
    return [found.best] + ([found.alternative.best] if found.alternative is not None else [])


NOT_JUDGED = ("not judged: its correlation alone rules out a confident answer, and what stands "
              "on the ground decided")


def _not_judged(found: SearchResult, *, method: str, tie_cell: float) -> CoarseResult:
    """The heights' answer where it was not judged: not confident by the checks that need no
    fit (:func:`may_be_confident`), and not needed, what stands on the ground having decided."""
    best = found.best
    return CoarseResult(
        best.transform(), method, False, 0.0, tie_cell * best.sigma, best.ncc,
        float(min(rival_ratio(found), 1e6)), best.overlap, 0.0, (),
        (NOT_JUDGED,), 0.0, hypotheses=considered(found),
        evidence=Evidence(channel=HEIGHTS.name, judged=False, hypotheses=found.n_hypotheses,
                          search_best=peak(best)))


def judge_choice(moving_xyz: np.ndarray, found: SearchResult, **options) -> CoarseResult:
    """:func:`judge` of a search's answer, and of its ``alternative`` where it has one (the
    best correlation, where the heights chose another): a confident one, else the one whose
    continuous fit explains the heights better."""
    result = judge(moving_xyz, found, **options)
    if found.alternative is None:
        return result
    other = judge(moving_xyz, found.alternative, **options)
    if (other.confident, explains_better(other, result)) > (result.confident, False):
        return other
    return result


def explains_better(a: CoarseResult, b: CoarseResult) -> bool:
    """Whether the pose ``a`` returns leaves smaller height residuals than the pose ``b`` returns
    (``pose_residual_ratio``: its continuous fit's where the fit was taken, else the search's).

    Counting a fit that was not taken lost a levelled city block's right answer (residual ratio
    0.658) to a wrong one whose fit, 19 % off its search's scale and not taken, had 0.653; not
    counting the pose at all then lost a farmland answer that was right on the grid."""
    return a.evidence.pose_residual_ratio < b.evidence.pose_residual_ratio


def _rounded(timings: dict[str, float]) -> tuple[tuple[str, float], ...]:
    return tuple((k, round(v, 3)) for k, v in timings.items())
