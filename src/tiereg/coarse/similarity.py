"""Coarse registration with unknown heading and scale: search, refine, judge.

1. :func:`~tiereg.coarse.search.search` sweeps heading and scale (space domain, masked NCC).
2. The winner is refined continuously: heading, log-scale and shift by a robust fit of the tie
   points' heights to the finest reference surface (:func:`~tiereg.coarse.refine.fit_to_surface`);
   heights scale with the horizontal scale.
3. Confidence rests on evidence that a wrong answer rarely has all at once: a correlation peak
   that stands above every genuinely different hypothesis (another heading, scale or place), a
   high correlation at the refined pose, enough overlap, and a refinement that converged near
   where the search ended.
4. When the heights do not decide (flat farmland), the search is run again on what stands on the
   ground (:data:`~tiereg.coarse.scoring.OBJECTS`), judged by thresholds of its own
   (:data:`TRUST`). Where the checks that need no fit already rule out the heights' answer
   (:func:`may_be_confident`), it is judged only if the objects' answer is not confident
   (:func:`_judged_by_turns`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..grid import GridSpec, rasterize
from ..parallel import map_threads
from ..reference import Reference
from ..robust import nmad
from ..surface import SurfaceSampler
from ..transform import Transform, rotation_matrix
from .fourier_mellin import rotation_scale_candidates
from .moments import moments_search
from .preprocess import prepare
from .refine import SurfaceFit, fit_to_surface, fit_to_surface_many, height_offset
from .result import Candidate, CoarseResult
from .scoring import (
    HEIGHTS,
    MAX_REFERENCE_CELLS,
    MIN_OVERLAP,
    OBJECTS,
    Channel,
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

FREQUENCY_METHODS = ("fmt", "afmt", "qafmt", "fmt-classic", "afmt-classic", "qafmt-classic")
# methods that try a few candidates, not every hypothesis: confident only when the heights are
# explained (a rival ratio among a few candidates says nothing about those never tried)
CANDIDATE_METHODS = (*FREQUENCY_METHODS, "moments")



@dataclass(frozen=True)
class Trust:
    """When the answer of a search on one channel is confident (module docstring, 3)."""

    min_rival_ratio: float  # best sweep score over the best genuinely different one
    min_ncc: float  # the correlation at the best pose
    # a second route to confidence: the refined pose explains the heights, with a lower bar on
    # the rival ratio; over a small part of the block that proves little on smooth ground
    max_residual_ratio: float  # residual spread over the surface's own spread
    min_ncc_explained: float
    min_rival_ratio_explained: float
    min_overlap_explained: float = 0.5
    max_residual_ratio_any: float = 1.2  # heights worse than this: never confident


TRUST = {
    # heights explained: right answers on the simulated scenes 0.08-0.16, near misses 0.53 or
    # more, tie points from elsewhere 0.88 or more on the benchmark's scenes but 0.20 once on
    # the tests' smooth terrain, with a rival ratio of 1.065 (and 0.07 over 30 % of the block)
    HEIGHTS.name: Trust(1.25, 0.45, 0.2, 0.6, 1.08),
    # clipped values correlate less: NCC 0.26-0.41 at right answers on the simulated farmland.
    # Residual ratios there: right 0.11-0.59 (tie points on crowns and roofs the fit down-weights),
    # wrong 0.66 or more, tie points from elsewhere 0.42 or more with rival ratios of at most
    # 1.18 (all 8 negative cases of the benchmark). What stands on the ground can agree where
    # the heights do not (a partly covered urban block, rival ratio 1.27, 6 % off in scale after
    # the heights' fit, residual ratio 1.01): the heights must still broadly agree
    OBJECTS.name: Trust(1.25, 0.25, 0.35, 0.25, 1.15, max_residual_ratio_any=0.8),
}


def _place(xyz: np.ndarray):
    """Parameters ``(kappa, ln sigma, tx, ty, omega, phi)`` -> placed points (no height offset).

    The tilts are small corrections about the block centre (the local origin): a block that is
    not quite level must not bend the heading, scale and shift to fit the heights.
    """

    def place(p: np.ndarray) -> np.ndarray:
        kappa, log_sigma, tx, ty, omega, phi = p
        R = math.exp(log_sigma) * rotation_matrix(omega, phi, kappa)
        q = xyz @ R.T
        q[:, 0] += tx
        q[:, 1] += ty
        return q

    return place


SCALE_STARTS = (0.0, -0.05, 0.05, -0.10, 0.10, -0.15, 0.15)  # log-scale offsets of the starts
# a fit that moves the scale further than this from the grid's answer, and then does not
# explain the heights, disagrees with it: a levelled farmland model was 6 % off after the search
# and 8.5 % off (the other way) after the fit, residual ratio 0.63, confident with a rival ratio
# of 1.39; where the fit explains the heights it corrects the grid (a smooth test surface: 14 %
# off on the grid, right after the fit, residual ratio 0.01)
MAX_FIT_RESCALE = math.log(1.08)
START_POINTS = 1000  # about this many tie points take part in the starts
# a hypothesis this close to one already fitted starts the same fit (the starts span +-15 % in
# scale and the fit moves cells): its fit is reused (auto's sweep often ends where qafmt did)
SAME_START_DEG, SAME_START_SCALE, SAME_START_CELLS = 0.5, 1.01, 0.5


@dataclass
class FitCache:
    """The finest reference surface of a run, and the continuous fits of hypotheses against it,
    shared by the judgements of the run."""

    sampler: SurfaceSampler
    fits: list[tuple[Hypothesis, SurfaceFit]] = field(default_factory=list)

    @classmethod
    def of(cls, reference: Reference) -> FitCache:
        return cls(reference.surface())

    def fit(self, moving: np.ndarray, h: Hypothesis, cell: float) -> tuple[SurfaceFit, bool]:
        """:func:`refine_pose` of ``h``, or the fit of a hypothesis that starts the same; and
        whether it was such a reused fit."""
        for done, fit in self.fits:
            if starts_same(h, done, cell):
                return fit, True
        fit = refine_pose(moving, self.sampler, h, cell)
        self.fits.append((h, fit))
        return fit, False


def starts_same(h: Hypothesis, done: Hypothesis, cell: float) -> bool:
    """Whether the fit of ``h`` starts where that of ``done`` did: within
    :data:`SAME_START_DEG`, :data:`SAME_START_SCALE` and :data:`SAME_START_CELLS` cells of
    ``cell`` (that of the judgement of ``h``)."""
    return not h.distinct_from(done, kappa_deg=SAME_START_DEG,
                               log_sigma=math.log(SAME_START_SCALE),
                               shift=SAME_START_CELLS * cell)


def refine_pose(moving: np.ndarray, sampler: SurfaceSampler, h: Hypothesis,
                cell: float) -> SurfaceFit:
    """The continuous fit of a search hypothesis, from several scales around it.

    Grid scores locate the scale only to within several per cent on smooth or small surfaces,
    and the fit from a single start can settle in a neighbouring minimum there; each start is
    fitted and the one whose residuals are smallest is polished by a second fit.
    """
    steps = np.array([math.radians(1.0), math.log(1.01), cell / 2, cell / 2,
                      math.radians(0.2), math.radians(0.2)])
    thin = _place(moving[:: max(1, len(moving) // START_POINTS)])  # the starts see a sample
    # in lock-step, not on threads: a fit is many small array operations that hold the
    # interpreter's lock, and side by side on two threads the starts took twice as long
    fits = fit_to_surface_many(
        thin, sampler, [np.array([h.kappa, math.log(h.sigma) + d, h.tx, h.ty, 0.0, 0.0])
                        for d in SCALE_STARTS], steps, tol_fraction=1 / 16)
    good = [f for f in fits if f.converged and np.isfinite(f.sigma0)] or fits
    start = min(good, key=lambda f: f.sigma0)
    place = _place(moving)
    return fit_to_surface(place, sampler, start.params, steps)


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
    heights = HeightCheck(fits.sampler, free_tilt=free_tilt)
    if method == "auto" and not small_block(moving_xyz, tie_cell):
        # a large block goes straight to the sweep: on the coarse benchmark's large blocks
        # (3,150 tie points) qafmt was confident in 4 of 95 cases, which the sweep also found,
        # its seeds changed no answer, and it cost about 0.9 s a case
        auto = register_similarity(moving_xyz, reference, tie_cell=tie_cell,
                                   scales=scales, method="search", fits=fits,
                                   free_tilt=free_tilt)
        return replace(auto, method="auto", details={**auto.details, "decided_by": "search"})
    if method == "auto":  # frequency domain first; the exhaustive sweep when that is not enough
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
                               details={**judged.details, "decided_by": "qafmt",
                                        "timings_s": _rounded(timings)})
        seeds = [] if quick is None else [(h.kappa, h.sigma) for lv in quick.levels for h in lv]
        full = register_similarity(moving_xyz, reference, tie_cell=tie_cell,
                                   scales=scales, method="search", seeds=seeds,
                                   fits=fits, free_tilt=free_tilt)
        return replace(full, method="auto", seconds=time.perf_counter() - t0,
                       hypotheses=full.hypotheses + considered(quick),
                       details={**full.details, "decided_by": "search", "timings_s": _rounded(
                           {**timings, **full.details.get("timings_s", {})})})
    extra: dict = {}
    timings: dict[str, float] = {}
    try:
        if method in FREQUENCY_METHODS:
            found = frequency_search(moving_xyz, reference, tie_cell=tie_cell, method=method,
                                     scales=scales, heights=heights)
        elif method == "moments":
            found, extra = moments_search(moving_xyz, reference, tie_cell=tie_cell,
                                          scales=scales, heights=heights)
        else:
            # level, unscaled data are common: the identity is always among the hypotheses
            found = search(moving_xyz, reference, tie_cell=tie_cell, scales=scales,
                           seeds=[(0.0, 1.0), *seeds], heights=heights)
    except NoOverlap:
        return CoarseResult(Transform.identity(), method, False, 0.0, tie_cell, 0.0, 1.0, 0.0,
                            0.0, (), (no_overlap_reason(scales),), time.perf_counter() - t0)
    timings[method] = time.perf_counter() - t0
    options = {"method": method, "tie_cell": tie_cell, "extra": extra, "fits": fits}
    # where the checks that need no fit already rule out a confident answer from the heights,
    # what stands on the ground is searched first, and the heights' answer is judged only if
    # it is still needed (:func:`_judged_by_turns`): on the 95 large blocks of the coarse
    # benchmark's timing, all 37 whose heights were not confident were ruled out so
    heights_decide = method != "search" or may_be_confident(found, TRUST[HEIGHTS.name])
    result = judge_choice(moving_xyz, found, **options) if heights_decide else None
    timings["judge"] = result.seconds if result is not None else 0.0
    if method == "search" and (result is None or not result.confident):
        t_objects = time.perf_counter()
        # the heights did not decide: what stands on the ground may (flat farmland)
        try:
            objects = search(moving_xyz, reference, tie_cell=tie_cell, scales=scales,
                             seeds=[(0.0, 1.0), *seeds], channel=OBJECTS, heights=heights)
        except NoOverlap:
            objects = None
        t_searched = time.perf_counter()
        result, second = _judged_by_turns(moving_xyz, found, objects, result, options)
        timings["judge"] = result.seconds
        if second is not None:
            # neither confident: the answer whose fit explains the heights better (taking the
            # more distinct of the two peaks lost two right answers on the benchmark and gained
            # none; on the simulated farmland what stands on the ground often finds the truth
            # without a peak distinct enough to be sure)
            timings["objects"] = t_searched - t_objects + second.seconds
            take = second.confident or (not result.confident and _explains_better(second, result))
            result, other = (second, result) if take else (result, second)
            result = replace(result, hypotheses=result.hypotheses + other.hypotheses, details={
                **result.details, "other_channel": {**other.details, "confident": other.confident,
                                                    "reasons": list(other.reasons)}})
    return replace(result, seconds=time.perf_counter() - t0,
                   details={**result.details, "timings_s": _rounded(timings)})


def edge_reason(scales: ScaleRange, scale: float) -> str:
    """Why an answer at the edge of the scales searched is not trusted, and what to do."""
    if scales.at_lowest(scale):
        return (f"the scale found ({scale:.4g} reference units per model unit) is the smallest "
                "at which this block can be told apart in this reference: the block may be "
                "smaller still; crop the reference to the block's surroundings")
    return (f"the scale found ({scale:.4g} reference units per model unit) is the largest at "
            f"which {MIN_OVERLAP:.0%} of the block still lies on the reference: the block may "
            "overlap it less than that")


def no_overlap_reason(scales: ScaleRange) -> str:
    """Why no hypothesis could be scored, and what to do."""
    if scales.lowest > scales.highest:
        return ("the reference is too wide for this block: at every scale at which the block "
                "could overlap it, its grid would need more than "
                f"{MAX_REFERENCE_CELLS} cells a side; crop the reference to the block's "
                "surroundings")
    return (f"no heading and scale ({scales.lowest:.3g}-{scales.highest:.3g} reference units "
            f"per model unit) makes the tie points overlap the reference by {MIN_OVERLAP:.0%}")


def _judged_by_turns(
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


def considered(*found: SearchResult | None) -> tuple[Hypothesis, ...]:
    """The poses searches considered, best first: each one's answer, rival and refined
    candidates (and its alternative's)."""
    out: list[Hypothesis] = []
    for f in found:
        while f is not None:
            out += [f.best, *([f.runner_up] if f.runner_up else []), *f.levels[-1], f.sweep_best]
            f = f.alternative
    return tuple(out)


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
        details={"channel": HEIGHTS.name, "judged": False, "hypotheses": found.n_hypotheses,
                 "search_best": {"kappa_deg": math.degrees(best.kappa), "scale": best.sigma,
                                 "score": best.score}})


def judge_choice(moving_xyz: np.ndarray, found: SearchResult, **options) -> CoarseResult:
    """:func:`judge` of a search's answer, and of its ``alternative`` where it has one (the
    best correlation, where the heights chose another): a confident one, else the one whose
    continuous fit explains the heights better."""
    result = judge(moving_xyz, found, **options)
    if found.alternative is None:
        return result
    other = judge(moving_xyz, found.alternative, **options)
    if (other.confident, _explains_better(other, result)) > (result.confident, False):
        return other
    return result


def _explains_better(a: CoarseResult, b: CoarseResult) -> bool:
    """Whether the pose ``a`` returns leaves smaller height residuals than the pose ``b`` returns
    (``pose_residual_ratio``: its continuous fit's where the fit was taken, else the search's).

    Counting a fit that was not taken lost a levelled city block's right answer (residual ratio
    0.658) to a wrong one whose fit, 19 % off its search's scale and not taken, had 0.653; not
    counting the pose at all then lost a farmland answer that was right on the grid."""
    return a.details["pose_residual_ratio"] < b.details["pose_residual_ratio"]


def _rounded(timings: dict[str, float]) -> dict[str, float]:
    return {k: round(v, 3) for k, v in timings.items()}


def rival_ratio(found: SearchResult) -> float:
    """The sweep's best score over that of the best genuinely different hypothesis."""
    rival = found.runner_up.score if found.runner_up is not None else 0.0
    return found.sweep_best.score / rival if rival > 0 else float("inf")


def may_explain(found: SearchResult, trust: Trust) -> bool:
    """Whether the answer could pass :func:`judge` as explaining the heights, by the checks that
    need no fit (correlation, overlap, rival ratio)."""
    best = found.best
    return (best.ncc >= max(trust.min_ncc, trust.min_ncc_explained)
            and best.overlap >= trust.min_overlap_explained
            and rival_ratio(found) >= trust.min_rival_ratio_explained)


def may_be_confident(found: SearchResult, trust: Trust) -> bool:
    """Whether :func:`judge_choice` could find the answer (or its alternative) confident, by
    the checks of :func:`judge` that need no fit: the correlation, the overlap, and a rival
    ratio that is high enough or may be explained (:func:`may_explain`)."""
    def one(f: SearchResult) -> bool:
        return (f.best.ncc >= trust.min_ncc and f.best.overlap >= MIN_OVERLAP
                and (rival_ratio(f) >= trust.min_rival_ratio or may_explain(f, trust)))

    return one(found) or (found.alternative is not None and one(found.alternative))


def judge(
    moving_xyz: np.ndarray,
    found: SearchResult,
    *,
    method: str,
    tie_cell: float,
    fits: FitCache,
    extra: dict | None = None,
    channel: Channel = HEIGHTS,
) -> CoarseResult:
    """The refined pose of a search's answer against the finest reference surface (that of
    ``fits``, whose earlier fits are reused for a hypothesis that starts the same), and whether
    to trust it (module docstring, 2-3)."""
    t0 = time.perf_counter()
    extra = extra or {}
    trust = TRUST[channel.name]
    best = found.best
    cell = tie_cell * best.sigma
    sampler = fits.sampler
    fit, reused = fits.fit(moving_xyz, best, cell)
    kappa, log_sigma, tx, ty, omega, phi = fit.params
    moved = math.hypot(tx - best.tx, ty - best.ty) / cell
    turned = abs(math.degrees(kappa - best.kappa))
    rescaled = abs(log_sigma - math.log(best.sigma))
    reasons: list[str] = []
    # how much of the height variation the pose explains: residual spread over surface spread
    placed = _place(moving_xyz)(fit.params)
    z_surf, ok = sampler.sample(placed[:, 0], placed[:, 1])
    spread = nmad(z_surf[ok]) if ok.sum() > 10 else float("nan")
    residual_ratio = fit.sigma0 / spread if spread and np.isfinite(spread) else float("inf")

    # the fit descends from the search's pose (and scales around it); grid scores can miss the scale
    # by several per cent through lattice aliasing, which the point-based fit corrects: only
    # runaways are refused. A fit that explains the heights may have come further (a small
    # block's sweep left the heading 13.5 deg off, and the fit found the truth with a residual
    # ratio of 0.10: Muscatatuck)
    max_moved, max_turned = (10.0, 20.0) if residual_ratio <= trust.max_residual_ratio else (
        5.0, 10.0)
    settled = bool(fit.converged and moved <= max_moved and turned <= max_turned
                   and rescaled <= max(SCALE_STARTS) + 0.1)
    # a fit that moves the scale far from the grid's answer and then does not explain the
    # heights disagrees with it (MAX_FIT_RESCALE): the grid's pose is the better guess (flat
    # farmland: the grid right to 1 %, the fit 19 % off with a residual ratio of 0.68)
    disagrees = rescaled > MAX_FIT_RESCALE and residual_ratio > trust.max_residual_ratio
    fit_taken = settled and not disagrees
    if fit_taken:
        T = Transform.from_parameters(scale=math.exp(log_sigma), kappa=kappa, omega=omega,
                                      phi=phi, translation=(tx, ty, fit.tz))
        pose_residual_ratio = residual_ratio
    else:
        placed_grid = best.transform().apply(moving_xyz)
        tz = height_offset(placed_grid, sampler, np.zeros(2))
        T = best.transform(tz=tz if np.isfinite(tz) else 0.0)
        pose_residual_ratio = HeightCheck(sampler).residual_ratio(moving_xyz, best)
    if not settled:
        reasons.append("the continuous refinement did not settle near the search's answer")

    ratio = rival_ratio(found)
    explained = (residual_ratio <= trust.max_residual_ratio
                 and best.ncc >= trust.min_ncc_explained
                 and ratio >= trust.min_rival_ratio_explained
                 and best.overlap >= trust.min_overlap_explained)
    if method in CANDIDATE_METHODS and not explained:
        # a few candidates say nothing about the hypotheses never tried: the heights must be
        # explained, a rival ratio among candidates is not evidence
        reasons.append(f"the {'moments' if method == 'moments' else 'frequency-domain'} "
                       "candidates do not explain the heights (residual ratio "
                       f"{residual_ratio:.2f} > {trust.max_residual_ratio})")
    elif ratio < trust.min_rival_ratio and not explained:
        reasons.append(f"another heading, scale or position fits almost as well (best/rival "
                       f"{ratio:.2f} < {trust.min_rival_ratio})")
    if best.ncc < trust.min_ncc:
        reasons.append(f"weak correlation at the best pose (NCC {best.ncc:.2f} < "
                       f"{trust.min_ncc})")
    if residual_ratio > trust.max_residual_ratio_any:
        reasons.append("the tie points' heights disagree with the reference surface at the "
                       f"found pose (residual spread {residual_ratio:.2f} x the surface's own)")
    if best.overlap < MIN_OVERLAP:
        reasons.append(f"small overlap ({best.overlap:.0%} of the tie points)")
    scale = math.exp(log_sigma) if fit_taken else best.sigma
    limits = ((edge_reason(found.scales, scale),)
              if found.scales is not None and found.scales.at_edge(scale) else ())
    reasons.extend(limits)
    if disagrees:
        reasons.append(f"the continuous fit moved the scale by {math.expm1(rescaled):.0%} from "
                       "the search's answer: the two disagree")
    confident = not reasons
    # the stronger of the two kinds of evidence: a distinct peak, or heights explained
    distinct = np.clip((ratio - 1) / 0.5, 0, 1)
    fit_quality = np.clip(1 - residual_ratio / (2 * trust.max_residual_ratio), 0, 1)
    confidence = float(np.clip(best.ncc, 0, 1) * max(distinct, fit_quality))
    if not confident:
        confidence = min(confidence, 0.49)

    def candidate(h: Hypothesis) -> Candidate:
        return Candidate(h.tx, h.ty, h.score, h.ncc, h.overlap, f"search level {h.level}")

    return CoarseResult(
        hypotheses=considered(found), limits=limits,
        T_ref_mov=T, method=method, confident=confident, confidence=confidence,
        cell_size=cell, ncc=best.ncc, peak_ratio=float(min(ratio, 1e6)), overlap=best.overlap,
        psr=0.0, candidates=tuple(candidate(h) for level in found.levels for h in level),
        reasons=tuple(reasons), seconds=time.perf_counter() - t0,
        details={
            "channel": channel.name,
            "hypotheses": found.n_hypotheses,
            "search_best": {"kappa_deg": math.degrees(best.kappa), "scale": best.sigma,
                            "score": best.score},
            "rival": None if found.runner_up is None else {
                "kappa_deg": math.degrees(found.runner_up.kappa),
                "scale": found.runner_up.sigma, "score": found.runner_up.score},
            "refinement": {"iterations": fit.iterations, "converged": fit.converged,
                           "sigma0": fit.sigma0, "n_used": fit.n_used,
                           "scale_change": math.expm1(log_sigma - math.log(best.sigma)),
                           "turn_deg": math.degrees(kappa - best.kappa), "shift_cells": moved,
                           "reused": reused, "settled": settled, "taken": fit_taken},
            "residual_ratio": residual_ratio,  # of the fit, taken or not
            "pose_residual_ratio": pose_residual_ratio,  # of the pose returned
            "verified": [{"kappa_deg": math.degrees(h.kappa), "scale": h.sigma, "score": h.score,
                          **({"residual_ratio": h.residual_ratio}
                             if np.isfinite(h.residual_ratio) else {})}
                         for level in found.levels for h in level],
            **extra,
        },
    )
