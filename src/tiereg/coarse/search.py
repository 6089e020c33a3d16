"""Exhaustive heading x scale search, coarse to fine, scored by masked NCC (space domain).

Every hypothesis ``(kappa, sigma)`` is scored at every shift at once by a
:class:`~tiereg.coarse.scoring.Scorer`. Levels (tie cells per search cell): 2, a full sweep of
heading and scale; 1, local refinement of the best distinct candidates. Small blocks (fewer than
:data:`SWEEP_MIN_CELLS` cells at level 2) are swept at level 1 too: over a few hundred cells a
wrong hypothesis correlates by chance as well as the right one does. Coarser sweeps than level 2
would smooth away what tells the right hypothesis from a wrong one (the band-pass keeps its
width on the ground at every level).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from ..parallel import map_threads
from ..reference import Reference
from ..robust import nmad
from ..surface import SurfaceSampler
from .scoring import HEIGHTS, MIN_OVERLAP, SCALE_STEP, Channel, Hypothesis, ScaleRange, Scorer

SWEEP_MIN_CELLS = 1000  # the block's cells at the sweep's level 2, else the sweep is at level 1
KEEP = 6  # distinct candidates refined: the best correlations (and on small blocks as many of
# the poses that best explain the heights, :func:`choose`)
RIVAL_KAPPA_DEG, RIVAL_SCALE, RIVAL_SHIFT_TIE_CELLS = 20.0, 1.25, 6.0  # a different answer


@dataclass(frozen=True)
class SearchResult:
    best: Hypothesis
    runner_up: Hypothesis | None  # best hypothesis distinct from ``sweep_best``, at sweep level
    sweep_best: Hypothesis  # the sweep's hypothesis that ``best`` was refined from
    levels: tuple[tuple[Hypothesis, ...], ...]  # kept candidates per level, coarse to fine
    n_hypotheses: int
    # the best correlation's answer, where the heights chose another (:func:`choose`)
    alternative: SearchResult | None = None
    scales: ScaleRange | None = None  # the scales searched


def small_block(moving: np.ndarray, tie_cell: float) -> bool:
    """Whether the block has fewer than :data:`SWEEP_MIN_CELLS` cells at the sweep's level 2.

    Over so few cells a wrong pose correlates by chance about as well as the right one, and the
    sweep runs at level 1; the tie points' own heights then choose better (:func:`choose`).
    Over a large block the correlation is the better judge: a sweep pose's heights on a
    built-up surface tell nothing (measured on the simulated city: 7 of 18 right when chosen by
    the heights, 16 by the correlation).
    """
    lo, hi = moving[:, :2].min(axis=0), moving[:, :2].max(axis=0)
    return float(np.prod(hi - lo)) / (2 * tie_cell) ** 2 < SWEEP_MIN_CELLS


def residual_ratio(residuals: np.ndarray, surface_z: np.ndarray) -> float:
    """The NMAD of height residuals over the NMAD of the surface heights under the points: near
    0 when a pose explains the heights, about sqrt(2) when they are unrelated (inf with fewer
    than 10 points)."""
    spread = nmad(surface_z) if len(surface_z) >= 10 else 0.0
    return nmad(residuals) / spread if spread > 0 else float("inf")


@dataclass(frozen=True, eq=False)
class HeightCheck:
    """How well a pose explains the tie points' own heights on the finest reference surface."""

    surface: SurfaceSampler
    # a model levelled from its own points may lean by a degree: then the residuals are
    # compared after a fitted plane (over a level block a plane absorbs a wrong pose's regional
    # slope too: on the small real blocks of the benchmark, right answers fell from 33 to 24 of
    # 36 with it)
    free_tilt: bool = False

    def residual_ratio(self, moving: np.ndarray, h: Hypothesis) -> float:
        """:func:`residual_ratio` of the tie points placed by ``h`` (heights scaled by its
        sigma) against the surface, after a height offset (and a tilt); inf where fewer than
        :data:`~tiereg.coarse.scoring.MIN_OVERLAP` of them land on it (a few points agree by
        chance)."""
        q = h.transform().apply(moving)
        z, ok = self.surface.sample(q[:, 0], q[:, 1])
        if ok.mean() < MIN_OVERLAP or ok.sum() < 10:
            return float("inf")
        r = z[ok] - q[ok, 2]
        if self.free_tilt:
            A = np.column_stack([np.ones(len(r)), q[ok, 0] - q[ok, 0].mean(),
                                 q[ok, 1] - q[ok, 1].mean()])
            keep = np.ones(len(r), bool)
            for _ in range(2):  # least squares, then again without the blunders it exposed
                coef = np.linalg.lstsq(A[keep], r[keep], rcond=None)[0]
                r_plane = r - A @ coef
                keep = np.abs(r_plane - np.median(r_plane)) <= 3.0 * max(nmad(r_plane), 1e-12)
            r = r_plane
        return residual_ratio(r, z[ok])


def choose(
    moving: np.ndarray,
    ranked: list[Hypothesis],
    top: list[Hypothesis],
    pairs: list[tuple[Hypothesis, Hypothesis]],
    *,
    tie_cell: float,
    heights: HeightCheck | None,
    n_hypotheses: int,
    scales: ScaleRange | None = None,
) -> SearchResult:
    """The answer among refined candidates ``pairs`` of ``(refined, the hypothesis it grew
    from)``, and its rival: the best of the ``ranked`` hypotheses genuinely different from it.

    With ``heights`` the pose that leaves the smallest height residuals wins
    (:meth:`HeightCheck.residual_ratio`), refined or as the sweep found it (on a small block the
    correlation alone can walk the scale 20 % off); else the best correlation. The band-passed
    grids of a small block correlate by chance about as well at a wrong pose, while the tie
    points' own heights on the finest surface tell the poses apart. Measured on the sweep of the
    real surfaces of the coarse benchmark, the truth's pose ranked first among all hypotheses in
    8 of 18 Autzen and 10 of 18 Muscatatuck cases by correlation, and in 14 and 18 of them by
    residual ratio (truth 0.14-0.63, the best elsewhere 0.39-0.91; tie points from elsewhere
    0.71 and 1.14). A rival that correlates better than the answer makes its rival ratio below 1.
    Where the two choices differ, the best correlation's answer goes along as the
    ``alternative``, for the continuous fit to decide (a suburb of 1,700 tie points: the
    correlation right, the heights at the grid's poses not).
    """
    def answer(best: Hypothesis, parent: Hypothesis,
               pairs: list[tuple[Hypothesis, Hypothesis]]) -> SearchResult:
        rival = next((h for h in ranked if h.distinct_from(
            parent, kappa_deg=RIVAL_KAPPA_DEG, log_sigma=math.log(RIVAL_SCALE),
            shift=RIVAL_SHIFT_TIE_CELLS * tie_cell * parent.sigma)), None)
        refined = tuple(sorted((r for r, _ in pairs), key=lambda h: -h.score))
        return SearchResult(best, rival, parent, (tuple(top), refined), n_hypotheses,
                            scales=scales)

    by_correlation = answer(*max(pairs, key=lambda rp: rp[0].score), pairs)
    if heights is None:
        return by_correlation

    def measured(h: Hypothesis) -> Hypothesis:
        if np.isfinite(h.residual_ratio):
            return h
        return replace(h, residual_ratio=heights.residual_ratio(moving, h))

    pairs = [(measured(r), measured(p)) for r, p in pairs]
    options = [(min((r, p), key=lambda h: h.residual_ratio), p) for r, p in pairs]
    best, parent = min(options, key=lambda bp: (bp[0].residual_ratio, -bp[0].score))
    other = by_correlation.sweep_best
    same = (parent.kappa, parent.sigma, parent.tx, parent.ty) == (other.kappa, other.sigma,
                                                                  other.tx, other.ty)
    return replace(answer(best, parent, pairs), alternative=None if same else by_correlation)


def distinct_top(hyps: list[Hypothesis], k: int, *, kappa_deg: float, log_sigma: float,
                 shift: float, key: Callable[[Hypothesis], float] = lambda h: -h.score,
                 taken: Sequence[Hypothesis] = ()) -> list[Hypothesis]:
    """The first ``k`` hypotheses in the order of ``key`` (best score first) that are distinct
    from each other and from those ``taken`` already."""
    out: list[Hypothesis] = []
    for h in sorted(hyps, key=key):
        if all(h.distinct_from(o, kappa_deg=kappa_deg, log_sigma=log_sigma, shift=shift)
               for o in (*taken, *out)):
            out.append(h)
            if len(out) == k:
                break
    return out


def search(
    moving: np.ndarray,
    ref: Reference,
    *,
    tie_cell: float,
    scales: ScaleRange | None = None,
    kappa_step_deg: float = 7.5,
    sigma_ratio: float = SCALE_STEP,
    keep: int = KEEP,
    seeds: list[tuple[float, float]] | None = None,
    channel: Channel = HEIGHTS,
    heights: HeightCheck | None = None,
    workers: int | None = None,
) -> SearchResult:
    """Search heading and scale; ``moving`` is local (centred) model coordinates.

    ``tie_cell`` is the tie-point grid cell in model units; ``scales`` bounds the scale
    (reference units per model unit; default: all at which the block can be found,
    :class:`~tiereg.coarse.scoring.ScaleRange`), swept on the lattice ``sigma_ratio^k``.
    ``seeds`` are extra
    ``(kappa, sigma)`` hypotheses, e.g. from a frequency-domain method, refined like the sweep's
    own candidates. ``channel``: what is correlated (:data:`~tiereg.coarse.scoring.HEIGHTS`,
    :data:`~tiereg.coarse.scoring.OBJECTS`). ``keep``: the distinct best-correlated hypotheses
    refined. ``heights``: with it, on a :func:`small_block`, the
    ``keep`` distinct hypotheses whose poses best explain the tie points' heights are refined
    too, and the answer is chosen by the heights (:func:`choose`); otherwise the best
    correlation wins. ``workers``: threads that score the scales side by side (default: one per
    core).
    """
    n_hyp = 0
    small = small_block(moving, tie_cell)
    sweep_level = channel.sweep_level or (1 if small else 2)
    heights = heights if small else None
    sweep_scorer = Scorer(moving, ref, tie_cell, sweep_level,
                          channel=replace(channel, tie_stat=channel.sweep_tie_stat))
    scales = scales or ScaleRange.of(moving, ref, tie_cell)
    sigmas = scales.lattice(sigma_ratio, level=sweep_level)
    kappas = np.radians(np.arange(0.0, 360.0, kappa_step_deg))
    by_sigma: dict[float, list[float]] = {float(sg): [float(k) for k in kappas] for sg in sigmas}
    for kappa, sigma in seeds or []:
        by_sigma.setdefault(float(sigma), []).append(float(kappa))
    sweep_scorer.prepare_for(by_sigma)
    scored = map_threads(lambda item: sweep_scorer.score_many(item[1], item[0]),
                         by_sigma.items(), workers=workers)
    sweep = [h for hs in scored for h in hs if h is not None]
    n_hyp += sum(len(k) for k in by_sigma.values())
    if not sweep:
        raise NoOverlap()
    sep = dict(kappa_deg=2 * kappa_step_deg, log_sigma=2 * math.log(sigma_ratio))
    ranked = sorted(sweep, key=lambda h: -h.score)
    sep["shift"] = 3 * 2 * tie_cell * ranked[0].sigma
    top = distinct_top(ranked, keep, **sep)
    if heights is not None:  # and the poses that best explain the heights
        fitted = [replace(h, residual_ratio=heights.residual_ratio(moving, h))
                  for h in sweep]
        top += distinct_top(fitted, keep, key=lambda h: h.residual_ratio, taken=top, **sep)
    pairs, n_refine = refine_candidates(moving, ref, top, tie_cell=tie_cell, channel=channel,
                                        first_steps=(kappa_step_deg / 2, sigma_ratio ** 0.5),
                                        workers=workers)
    n_hyp += n_refine
    if not pairs:
        pairs = [(replace(top[0], level=1), top[0])]
    return choose(moving, ranked, top, pairs, tie_cell=tie_cell, heights=heights,
                  n_hypotheses=n_hyp, scales=scales)


def verify_candidates(
    moving: np.ndarray,
    ref: Reference,
    hyps: list[Hypothesis],
    *,
    tie_cell: float,
    keep: int,
    log_sigma: float,
    n_tried: int,
    scales: ScaleRange,
    heights: HeightCheck | None = None,
    workers: int | None = None,
) -> SearchResult:
    """The answer from a few scored candidates (a frequency-domain or moments method): the
    ``keep`` best distinct ones (``log_sigma`` apart in scale, 5 deg in heading) refined on the
    finest level and chosen among as :func:`choose` does (by the ``heights`` for a
    :func:`small_block`), and the best genuinely different one as the rival."""
    if not hyps:
        raise NoOverlap()
    ranked = sorted(hyps, key=lambda h: -h.score)
    top = distinct_top(ranked, keep, kappa_deg=5.0, log_sigma=log_sigma,
                       shift=6 * tie_cell * ranked[0].sigma)
    pairs, n_refine = refine_candidates(moving, ref, top, tie_cell=tie_cell, workers=workers)
    return choose(moving, ranked, top, pairs or [(top[0], top[0])], tie_cell=tie_cell,
                  heights=heights if small_block(moving, tie_cell) else None,
                  n_hypotheses=n_tried + n_refine, scales=scales)


def refine_candidates(
    moving: np.ndarray,
    ref: Reference,
    candidates: list[Hypothesis],
    *,
    tie_cell: float,
    first_steps: tuple[float, float] = (3.75, 2 ** 0.1),
    channel: Channel = HEIGHTS,
    workers: int | None = None,
) -> tuple[list[tuple[Hypothesis, Hypothesis]], int]:
    """Refine each candidate on the finest level: a 3 x 3 (heading, scale) neighbourhood with
    ``first_steps`` (degrees, scale ratio), then 1 deg / 2 %, then 0.5 deg / 1 %. Returns pairs
    ``(refined, candidate)``, best first, and the number of hypotheses scored.

    Locally the candidates are compared by NCC alone: the overlap weight that keeps the sweep
    away from spurious small overlaps would here favour shrinking a partly covered block. Each
    step looks only at shifts near the current one (:data:`~tiereg.coarse.scoring.WINDOW_CELLS`):
    a refinement stays in its candidate's basin. ``workers``: threads refining candidates side by
    side.
    """
    fine = Scorer(moving, ref, tie_cell, 1, channel=channel)
    steps = (first_steps, (1.0, 1.02), (0.5, 1.01))

    def refine(h: Hypothesis) -> tuple[Hypothesis, int]:
        cur, n = h, 0
        for dk_deg, ratio in steps:
            local = [cur]
            for ds in (1 / ratio, 1.0, ratio):
                dks = [dk for dk in (-dk_deg, 0.0, dk_deg)
                       if not (dk == 0.0 and ds == 1.0 and cur.level == 1)]
                kappas = [cur.kappa + math.radians(dk) for dk in dks]
                local += [c for c in fine.score_many(kappas, cur.sigma * ds,
                                                      near=(cur.tx, cur.ty)) if c is not None]
                n += len(kappas)
            level1 = [c for c in local if c.level == 1]
            cur = max(level1, key=lambda c: c.ncc) if level1 else cur
        return cur, n

    reach = []  # the scales each refinement may score, candidate by candidate
    for h in candidates:
        sigmas = [h.sigma]
        for _, ratio in steps:
            sigmas = [s * ds for s in sigmas for ds in (1 / ratio, 1.0, ratio)]
            reach += sigmas
    fine.prepare_for(reach)
    done = map_threads(refine, candidates, workers=workers)
    pairs = sorted(((h, c) for (h, _), c in zip(done, candidates) if h.level == 1),
                   key=lambda hc: -hc[0].score)
    return pairs, sum(n for _, n in done)


class NoOverlap(Exception):
    """No hypothesis overlaps the reference by the minimum share of the block."""
