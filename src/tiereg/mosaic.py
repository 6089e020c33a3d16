"""Finding a block anywhere in a lidar much wider than the coarse stage's search grid.

The coarse sweep grids the reference at most :data:`~tiereg.coarse.scoring.MAX_REFERENCE_CELLS`
cells a side, so on a wide mosaic a small block's true scale is too fine to be scored. Here the
mosaic is searched in overlapping *screening windows*, each as wide as the sweep can search at
the block's coarsest cell (level 2: two tie cells), and overlapping by the block's diagonal so
that the block lies whole in one of them. The windows are cut from one overview grid of the
prepared reference (its base grid aggregated to the tie cell: the overview pyramid is the
reference's own, built once per archive) and swept side by side on the cluster
(:func:`~tiereg.coarse.search.search`, heights). The best distinct places are then *judged*:
each is registered (:func:`tiereg.register`, the usual coarse and fine stages and verdict) on a
window of the reference around it, one search grid wide at the finest level, whose source reads
only the tiles there, gridded at their own spacing (:func:`window_reference`), at the scales
within an octave of the screening's (:func:`judge_scales`). The answer is confident only when a
judged window's answer is confident and no other judged window is confidently somewhere else.

A scale range wider than an octave is searched as octaves, each with windows of its own size.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .archive import ArchiveSource, Box
from .coarse.scoring import HEIGHTS, MAX_REFERENCE_CELLS, Scorer
from .errors import InputError
from .grid import Grid, GridSpec, cell_size_from_density
from .io import PointSource
from .parallel import map_threads
from .pipeline import RegistrationResult, register
from .points import gross_outliers, validate_points
from .progress import no_progress
from .reference import BASE_SPACINGS, MAX_BASE_SIDE, Reference, point_spacing

TOP = 3  # distinct places judged
SCREEN_LEVEL = 3  # tie cells a screening cell (the sweep: 2): chosen on the dev blocks
KAPPA_STEP_DEG, SIGMA_RATIO = 7.5, 2 ** (1 / 5)  # the sweep's steps
JUDGE_MARGIN = 0.85  # judged windows: this share of one search grid at the candidate's scale
MIN_OVERLAP = 0.3


@dataclass(frozen=True)
class Candidate:
    """A screening window's best hypothesis: where the block's centre lands (reference local
    frame), at which heading and scale, and its correlation score."""

    box: Box
    centre: tuple[float, float]
    kappa_deg: float
    sigma: float
    score: float


@dataclass(frozen=True)
class MosaicResult:
    """The verdict of a mosaic search and what it rests on."""

    result: RegistrationResult  # the chosen window's registration, with the mosaic's verdict
    windows: int  # screening windows swept
    candidates: tuple[Candidate, ...]  # the judged places, best score first
    judged_confident: tuple[bool, ...]
    screen_seconds: float
    judge_seconds: float


def crop(grid: Grid, box: Box) -> Grid:
    """The cells of ``grid`` that meet ``box`` (the grid's frame)."""
    spec, c = grid.spec, grid.spec.cell_size
    c0 = max(0, math.floor((box[0] - spec.x0) / c))
    c1 = min(spec.shape[1], math.ceil((box[2] - spec.x0) / c))
    r0 = max(0, math.floor((spec.y0 - box[3]) / c))
    r1 = min(spec.shape[0], math.ceil((spec.y0 - box[1]) / c))
    if r1 <= r0 or c1 <= c0:
        raise InputError("the window lies outside the reference grid")
    sub = GridSpec(spec.x0 + c0 * c, spec.y0 - r0 * c, c, (r1 - r0, c1 - c0))
    sl = (slice(r0, r1), slice(c0, c1))
    return Grid(sub, grid.count[sl], {k: v[sl] for k, v in grid.stats.items()}, grid.crs_wkt)


def window_reference(ref: Reference, box: Box, *, regrid: bool = True) -> Reference:
    """``ref`` seen through ``box`` (its local frame). Of an archive only the tiles that meet
    the window are read, and with ``regrid`` gridded anew at their own spacing
    (:func:`window_cell`) where the archive's base grid is coarser: a base capped at
    :data:`~tiereg.reference.MAX_BASE_SIDE` cells over a wide mosaic is tens of metres, too
    coarse for the fits that judge a small block (gridded in the task that registers the
    window, on first use). Otherwise the base grid is cut."""
    source = ref.source
    if isinstance(source, ArchiveSource):
        o = ref.origin
        source = source.index.source((box[0] + o[0], box[1] + o[1], box[2] + o[0],
                                      box[3] + o[1]))
        cell = window_cell(source, box)
        if regrid and cell < ref.base_cell:
            spec = GridSpec.from_bounds(*box, cell)
            return Reference(source, ref.origin, None, ref.first_returns_only,
                             source_args=ref.source_args, _pending=(spec, no_progress),
                             _grid_where_used=True)
    return Reference(source, ref.origin, crop(ref.base, box), ref.first_returns_only,
                     source_args=ref.source_args)


def window_cell(source: PointSource, box: Box) -> float:
    """The base cell of a window's own grid: that of a reference of the window's tiles alone
    (:func:`~tiereg.reference.base_cell_for`, :data:`~tiereg.reference.BASE_SPACINGS` point
    spacings), coarser where the window would be more than
    :data:`~tiereg.reference.MAX_BASE_SIDE` cells a side."""
    return max(BASE_SPACINGS * point_spacing(source),
               max(box[2] - box[0], box[3] - box[1]) / (MAX_BASE_SIDE - 2))


def windows(extent: Box, size: float, step: float) -> list[Box]:
    """Squares of ``size`` covering ``extent``, ``step`` apart (the last flush with the end)."""
    def starts(lo: float, hi: float) -> list[float]:
        if hi - lo <= size:
            return [(lo + hi - size) / 2]
        n = math.ceil((hi - lo - size) / step) + 1
        return list(np.linspace(lo, hi - size, n))
    return [(x, y, x + size, y + size) for y in starts(extent[1], extent[3])
            for x in starts(extent[0], extent[2])]


def octaves(sigma_range: tuple[float, float]) -> list[tuple[float, float]]:
    lo, hi = sigma_range
    if not (0 < lo <= hi and math.isfinite(hi)):
        raise InputError(f"the scale range must be two positive numbers, low first; got "
                         f"{sigma_range}")
    n = max(1, math.ceil(math.log2(hi / lo) - 1e-9))
    return [(lo * (hi / lo) ** (i / n), lo * (hi / lo) ** ((i + 1) / n)) for i in range(n)]


def screen_window(overview: Reference, box: Box, moving: np.ndarray, *, tie_cell: float,
                  sigma_range: tuple[float, float], level: int = SCREEN_LEVEL
                  ) -> Candidate | None:
    """The best-correlated heading, scale and shift of ``moving`` (centred) in one window, from
    the sweep alone (every :data:`KAPPA_STEP_DEG`, scales :data:`SIGMA_RATIO` apart, at
    ``level`` tie cells a search cell; a task)."""
    try:
        wref = window_reference(overview, box, regrid=False)  # the overview's cells
    except InputError:
        return None
    scorer = Scorer(moving, wref, tie_cell, level,
                    channel=replace(HEIGHTS, tie_stat=HEIGHTS.sweep_tie_stat))
    lo, hi = sigma_range
    n = max(0, math.ceil(math.log(hi / lo) / math.log(SIGMA_RATIO) - 1e-9))
    sigmas = [float(lo * SIGMA_RATIO**i) for i in range(n + 1)]
    kappas = list(np.radians(np.arange(0.0, 360.0, KAPPA_STEP_DEG)))
    scorer.prepare_for(sigmas)
    scored = map_threads(lambda sg: scorer.score_many(kappas, sg), sigmas)
    hyps = [h for hs in scored for h in hs if h is not None]
    if not hyps:
        return None
    h = max(hyps, key=lambda h: h.score)
    return Candidate(box, (h.tx, h.ty), math.degrees(h.kappa), h.sigma, h.score)


def _distinct(cands: list[Candidate], k: int, diag: float) -> list[Candidate]:
    """The ``k`` best-scored places at least half the block's diagonal apart."""
    out: list[Candidate] = []
    for c in sorted(cands, key=lambda c: -c.score):
        if all(math.dist(c.centre, o.centre) > diag * o.sigma / 2 for o in out):
            out.append(c)
        if len(out) == k:
            break
    return out


def _judge_box(cand: Candidate, side: float) -> Box:
    x, y = cand.centre
    return (x - side / 2, y - side / 2, x + side / 2, y + side / 2)


def find_in_mosaic(moving: Any, ref: Reference, *, client: Any = None,
                   sigma_range: tuple[float, float] = (0.25, 4.0), top: int = TOP,
                   overviews: Overviews | None = None, **options: Any) -> MosaicResult:
    """Register ``moving`` (a path, or what :func:`tiereg.register` takes) anywhere in the
    prepared ``ref`` (see the module docstring); windows and judgements are tasks on
    ``client`` (here without one). ``sigma_range``: reference units per model unit.
    ``overviews``: the overview grids sent to the workers, to share between blocks.
    ``options`` go to :func:`tiereg.register`."""
    from .distributed import submit_all
    from .io import read_points

    t0 = time.perf_counter()
    pts = moving if isinstance(moving, np.ndarray) else read_points(moving).xyz
    validate_points_xyz(pts)
    xyz = pts[~gross_outliers(pts)]
    local = xyz - np.round(xyz.mean(axis=0))
    tie_cell = cell_size_from_density(local)
    diag = float(np.hypot(*(local[:, :2].max(axis=0) - local[:, :2].min(axis=0))))
    (x0, y0, x1, y1) = ref.base.spec.bounds
    width = max(x1 - x0, y1 - y0)
    if MAX_REFERENCE_CELLS * tie_cell * sigma_range[0] >= width:
        # the whole reference is one search grid at the finest level: register searches it all
        result = submit_all(client, _register, [(ref, sigma_range)], moving=moving,
                            options=options)[0]
        return MosaicResult(result, 1, (), (result.confident,), 0.0, time.perf_counter() - t0)
    cands: list[Candidate] = []
    n_windows = 0
    for lo, hi in octaves(sigma_range):
        side = SCREEN_LEVEL * MAX_REFERENCE_CELLS * tie_cell * lo  # one search grid at ``lo``
        if side >= width:
            boxes = [(x0, y0, x1, y1)]
        else:
            boxes = windows((x0, y0, x1, y1), side, max(side - diag * hi, side / 4))
        k = max(1, int(round(tie_cell * lo / ref.base_cell)))
        overview = (overviews or Overviews(ref, client)).get(k)
        found = submit_all(client, _screen_box, boxes, overview=overview, moving=local,
                           tie_cell=tie_cell, sigma_range=(lo, hi))
        cands += [c for c in found if c is not None]
        n_windows += len(boxes)
    t_screen = time.perf_counter() - t0
    if not cands:
        raise InputError("no window of the reference overlaps the block at any heading and "
                         f"scale in {sigma_range}; check that the block lies in the lidar")
    best = _distinct(cands, top, diag)
    sides = [JUDGE_MARGIN * MAX_REFERENCE_CELLS * tie_cell * c.sigma for c in best]
    judged = [(window_reference(ref, _judge_box(c, side)), judge_scales(c, sigma_range))
              for c, side in zip(best, sides)]
    results = submit_all(client, _register, judged, moving=moving, options=options)
    verdict = _verdict(results, np.median(xyz, axis=0))
    return MosaicResult(verdict, n_windows, tuple(best), tuple(r.confident for r in results),
                        t_screen, time.perf_counter() - t0 - t_screen)


def _screen_box(box: Box, *, overview: Reference, moving: np.ndarray, tie_cell: float,
                sigma_range: tuple[float, float]) -> Candidate | None:
    return screen_window(overview, box, moving, tie_cell=tie_cell, sigma_range=sigma_range)


def judge_scales(cand: Candidate, sigma_range: tuple[float, float]) -> tuple[float, float]:
    """The scales a judged window is searched at: an octave either way of the screening's
    (good to a sweep step, :data:`SIGMA_RATIO`), inside the range given."""
    return max(sigma_range[0], cand.sigma / 2), min(sigma_range[1], cand.sigma * 2)


def _register(job: tuple[Reference, tuple[float, float]], *, moving: Any,
              options: dict) -> RegistrationResult:
    window, scales = job
    return register(moving, window, **{"scale_range": scales, **options})


class Overviews:
    """The reference's base grid aggregated ``k`` base cells a side, made once and, with a
    client, sent once to every worker (a future); shared by the blocks of a batch."""

    def __init__(self, ref: Reference, client: Any = None):
        self.ref, self.client = ref, client
        self._made: dict[int, Any] = {}
        self._lock = threading.Lock()

    def get(self, k: int) -> Any:
        with self._lock:
            if k not in self._made:
                ref = self.ref
                overview = Reference(ref.source, ref.origin, ref.grid(k * ref.base_cell),
                                     ref.first_returns_only, source_args=ref.source_args)
                self._made[k] = overview if self.client is None else self.client.scatter(
                    overview, broadcast=True)
            return self._made[k]


def validate_points_xyz(xyz: np.ndarray) -> None:
    from .points import PointSet

    validate_points(PointSet(xyz, source="moving"), min_count=30, role="moving")


def _verdict(results: list[RegistrationResult], centre_mov: np.ndarray) -> RegistrationResult:
    """The judged windows' answers as one: confident when one is and no confident answer
    places the block elsewhere (further apart than two cells)."""
    confident = [r for r in results if r.confident]
    pool = confident or results
    best = max(pool, key=lambda r: r.confidence)
    place = best.T_ref_mov.apply(centre_mov[None])[0]
    rivals = [r for r in confident if r is not best and np.linalg.norm(
        r.T_ref_mov.apply(centre_mov[None])[0][:2] - place[:2]) > 2 * max(r.cell_size,
                                                                           best.cell_size)]
    if not rivals:
        return best
    far = max(float(np.linalg.norm(r.T_ref_mov.apply(centre_mov[None])[0][:2] - place[:2]))
              for r in rivals)
    reasons = (*best.reasons, f"another window of the mosaic registers the block confidently "
               f"{far:.0f} units away: the answer is ambiguous")
    return replace(best, confident=False, confidence=min(best.confidence, 0.49),
                   reasons=reasons)
