"""Scoring a hypothesis of heading and scale at one pyramid level: masked NCC at every shift.

A hypothesis ``(kappa, sigma)`` rotates the tie points by ``kappa`` and scales them by ``sigma``
(reference units per model unit); the masked normalized cross-correlation (Padfield 2012) of
their grid with the reference grid then gives the best shift and its score for all shifts at
once. The tie points are gridded on the lattice of the reference grid, whose cell is the tie
cell times ``sigma`` times the pyramid level, so every hypothesis compares like with like. The
band-pass keeps the same width on the ground at every level (six tie cells). Cost grows with the
number of hypotheses, not with the lidar: the reference grids are exact aggregations of one
prepared base grid. The correlations run in single precision
(:func:`~tiereg.coarse.correlation.masked_ncc`): scores to about 1e-5, which ranks hypotheses
as well, at two thirds of the time. :mod:`~tiereg.coarse.search` decides which hypotheses to
score.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from ..grid import Grid, GridSpec, cell_size_from_density, mask_bounds, nice_size, rasterize
from ..reference import Reference
from ..transform import Transform, rotation_matrix
from .correlation import (
    MaskedReference,
    Mode,
    masked_ncc,
    match_score,
    overlap_trim,
    shift_of_index,
    subpixel_peak,
    surface_shape,
)
from .preprocess import Prepared, prepare

MIN_OVERLAP = 0.3
BANDPASS_TIE_CELLS = 6.0  # band-pass width on the ground, in tie cells, at every level
MAX_REFERENCE_CELLS = 320  # per side: finer hypotheses (tiny blocks) are not tried
MIN_SUPPORT_CELLS = 50  # correlations over fewer cells are high by chance too often
MAX_TIE_CELLS = 4_000_000  # a tie-point canvas larger than this is not tried
# the tie points' own grid: at most this many cells along the block's longer side (a dense
# model is gridded coarser, as if thinned; blocks of up to 20,000 tie points stay below it)
MAX_TIE_SIDE = 256
SCALE_STEP = 2 ** (1 / 5)  # the sweep's scale lattice: 2^(k/5), k integer (0.25 and 4 on it)
CANVAS_MARGIN_CELLS = 1  # room around a tie-point grid (it ends at its points' bounds)
WINDOW_CELLS = 8  # local refinement: shifts within this many cells of the candidate's
STACK_CELLS = 200_000  # correlation cells of a stack (1.6 MB an array: measured fastest, in cache)


def tie_cell_for(moving: np.ndarray) -> float:
    """The tie points' grid cell (model units): from their density
    (:func:`~tiereg.grid.cell_size_from_density`), coarser where the block would span more than
    about :data:`MAX_TIE_SIDE` cells."""
    xy = moving[:, :2]
    extent = float(np.max(xy.max(axis=0) - xy.min(axis=0)))
    cell = cell_size_from_density(xy)
    return cell if extent / cell <= MAX_TIE_SIDE else nice_size(extent / MAX_TIE_SIDE)


@dataclass(frozen=True)
class ScaleRange:
    """The scales (reference units per model unit) at which a block can be found in a reference
    at all, whatever units either is in (:meth:`of`)."""

    lowest: float  # finer, the tie cell grids the reference at over MAX_REFERENCE_CELLS a side
    highest: float  # coarser, MIN_OVERLAP of the block would be more than the whole reference

    @classmethod
    def of(cls, moving: np.ndarray, ref: Reference, tie_cell: float) -> ScaleRange:
        """From the data alone: the block's extent and tie cell (model units) against the
        reference's extent (its units). A model in any gauge (1e-3 to 1e3 reference units per
        model unit and beyond) lands inside it."""
        (x0, y0, x1, y1) = ref.base.spec.bounds
        lo, hi = moving[:, :2].min(axis=0), moving[:, :2].max(axis=0)
        block_area = max(float(np.prod(hi - lo)), 1e-300)
        return cls(max(x1 - x0, y1 - y0) / (MAX_REFERENCE_CELLS * tie_cell),
                   math.sqrt((x1 - x0) * (y1 - y0) / (MIN_OVERLAP * block_area)))

    def lattice(self, step: float, *, level: int = 1) -> np.ndarray:
        """The scales ``step^k`` (k integer) in the range; at a search ``level``, down to the
        finest that level can still score (its cells are ``level`` tie cells)."""
        lo = math.ceil(math.log(self.lowest / level) / math.log(step) - 1e-9)
        hi = math.floor(math.log(self.highest) / math.log(step) + 1e-9)
        return step ** np.arange(lo, hi + 1, dtype=np.float64)

    def at_lowest(self, sigma: float) -> bool:
        """Within a sweep step (:data:`SCALE_STEP`) of the smallest scale: the block may be
        smaller still."""
        return sigma < self.lowest * SCALE_STEP

    def at_edge(self, sigma: float) -> bool:
        """Within a sweep step (:data:`SCALE_STEP`) of either end: the truth may lie beyond."""
        return self.at_lowest(sigma) or sigma > self.highest / SCALE_STEP


@dataclass(frozen=True)
class Channel:
    """What is correlated: a reference grid statistic against a tie-point grid statistic."""

    name: str
    # of :meth:`~tiereg.reference.Reference.grid` ("mean", or "max": the top of each cell)
    reference_stat: str
    tie_stat: str  # of :func:`~tiereg.grid.rasterize`
    sweep_tie_stat: str  # the same in the sweep, where a median's sort per hypothesis is dear
    clip_nmad: float  # band-passed values clipped at this many NMADs (0: not clipped)
    sweep_level: int | None  # None: 2, or 1 for small blocks (search.SWEEP_MIN_CELLS)


# the terrain and what stands on it, as the mean heights of the cells
HEIGHTS = Channel("heights", "mean", "median", "mean", 0.0, None)
# what stands on flat ground: farmland's few metres of relief carry no shape that survives the
# band-pass, but its trees and farmsteads do, as the highest point of a cell on either side,
# each counted alike (clipped); measured on the simulated farmland at the finest level, the
# truth's score over the best different hypothesis rose from 0.79-1.07 (heights) to 1.10-1.70
# (at the sweep's usual level 2: 0.71-1.02, so this channel is swept at level 1). Nor does level
# 2 pick the hypotheses worth sweeping at level 1: over the 95 large blocks of the coarse
# benchmark's timing cases, level 1 for the best 30 % at level 2 lost the level-1 best in 4 and
# raised a rival ratio by up to 19 % (confidence unearned); with their lattice neighbours that
# is 75 % of the hypotheses, and level 2 alone costs half of level 1
OBJECTS = Channel("objects", "max", "max", "max", 1.0, 1)


@dataclass(frozen=True, eq=False)
class Surface:
    """The scores of one hypothesis at every shift, with the grids that locate them."""

    score: np.ndarray  # :func:`~tiereg.coarse.correlation.match_score`; -inf where not valid
    ncc: np.ndarray
    overlap: np.ndarray  # share of the tie points' support that overlaps the reference
    spec: GridSpec  # the tie points' grid (its shape: the stack's, padded below and right)
    window: GridSpec  # the part of the reference grid correlated (all of it in full mode)
    mode: Mode

    def translation(self, index: tuple[float, float]) -> tuple[float, float]:
        """``(tx, ty)`` of the hypothesis at a (fractional) surface index."""
        dr, dc = shift_of_index(index, self.spec.shape, mode=self.mode)
        c = self.window.cell_size
        return (self.window.x0 - self.spec.x0 + dc * c, self.window.y0 - self.spec.y0 - dr * c)

    def index_of(self, tx: float, ty: float) -> tuple[float, float]:
        """The surface index of a translation (the inverse of :meth:`translation`)."""
        c = self.window.cell_size
        dc = (tx - self.window.x0 + self.spec.x0) / c
        dr = (self.window.y0 - self.spec.y0 - ty) / c
        zero = shift_of_index((0.0, 0.0), self.spec.shape, mode=self.mode)
        return (dr - zero[0], dc - zero[1])


@dataclass(frozen=True)
class Hypothesis:
    """Moving (local, model units) -> reference (local): ``q = sigma R(kappa) p + t``."""

    kappa: float  # radians
    sigma: float  # reference units per model unit
    tx: float
    ty: float
    score: float  # :func:`~tiereg.coarse.correlation.match_score` of NCC and overlap
    ncc: float
    overlap: float
    level: int
    # where measured: :meth:`~tiereg.coarse.search.HeightCheck.residual_ratio`
    residual_ratio: float = float("nan")

    def transform(self, tz: float = 0.0) -> Transform:
        return Transform.from_parameters(scale=self.sigma, kappa=self.kappa,
                                         translation=(self.tx, self.ty, tz))

    def distinct_from(self, other: Hypothesis, *, kappa_deg: float, log_sigma: float,
                      shift: float) -> bool:
        dk = abs((math.degrees(self.kappa - other.kappa) + 180.0) % 360.0 - 180.0)
        ds = abs(math.log(self.sigma / other.sigma))
        dt = math.hypot(self.tx - other.tx, self.ty - other.ty)
        return dk > kappa_deg or ds > log_sigma or dt > shift


class Scorer:
    """Scores hypotheses at one pyramid level; caches prepared reference grids by cell."""

    def __init__(self, moving: np.ndarray, ref: Reference, tie_cell: float, level: int, *,
                 channel: Channel = HEIGHTS):
        self.xy, self.z = moving[:, :2], moving[:, 2]
        self.ref, self.tie_cell, self.level, self.channel = ref, tie_cell, level, channel
        self._refs: dict[float, tuple[Grid, MaskedReference, float]] = {}
        self._lock = threading.Lock()  # the threads of a search share the prepared grids
        (x0, y0, x1, y1) = ref.base.spec.bounds
        self.ref_extent = max(x1 - x0, y1 - y0)

    def reference(self, sigma: float) -> tuple[Grid, MaskedReference, float]:
        """The prepared reference grid for ``sigma`` and its band-pass width in cells.

        The scales whose cells round to one grid (:meth:`~tiereg.reference.Reference.grid`)
        share it, prepared once, with the band-pass of the first scale that asks. Threads that
        score side by side would ask in any order: :meth:`prepare_for` fixes the order first.
        """
        cell = max(self.level * self.tie_cell * sigma, self.ref.base_cell)
        with self._lock:
            grid = self.ref.grid(cell, stats=(self.channel.reference_stat,))
            key = grid.spec.cell_size
            if key not in self._refs:
                bandpass = BANDPASS_TIE_CELLS * self.tie_cell * sigma / key
                p = prepare(grid[self.channel.reference_stat], grid.mask,
                            bandpass_sigma_cells=bandpass, clip_nmad=self.channel.clip_nmad)
                self._refs[key] = (grid, MaskedReference(p.image, p.support), bandpass)
            return self._refs[key]

    def prepare_for(self, sigmas: Iterable[float]) -> None:
        """Prepare the reference grids of ``sigmas`` in that order (:meth:`reference`), so that
        the scores do not depend on which thread asks first."""
        for sigma in sigmas:
            if not self.too_fine(sigma):
                self.reference(sigma)

    def too_fine(self, sigma: float) -> bool:
        """Whether ``sigma``'s cell would grid the reference finer than
        :data:`MAX_REFERENCE_CELLS` a side: such hypotheses are not scored."""
        return self.level * self.tie_cell * sigma < self.ref_extent / MAX_REFERENCE_CELLS

    def surface(self, kappa: float, sigma: float) -> Surface | None:
        """The score surface of one hypothesis (:meth:`surfaces`)."""
        return self.surfaces([kappa], sigma)[0]

    def surfaces(self, kappas: Sequence[float], sigma: float, *,
                 near: tuple[float, float] | None = None) -> list[Surface | None]:
        """The score (:func:`~tiereg.coarse.correlation.match_score`, -inf where not valid),
        NCC and overlap at every shift (full-mode surfaces, :mod:`tiereg.coarse.correlation`) of
        the hypotheses ``(kappa, sigma)`` for each of ``kappas``; ``None`` where a hypothesis
        cannot be scored.

        ``near=(tx, ty)``: only the shifts within :data:`WINDOW_CELLS` of that translation, in a
        window of the reference (valid mode): the same scores there, at a fraction of the cost.

        The headings share the scale's reference grid, so their tie-point grids are made and
        correlated as one stack: the work per hypothesis is then mostly transforms, not the
        overhead of many small array operations.
        """
        out: list[Surface | None] = [None] * len(kappas)
        if self.too_fine(sigma):
            return out
        grid, mref, bandpass = self.reference(sigma)
        c = grid.spec.cell_size
        placed = self._placed(kappas, sigma, c, bandpass)
        if not placed:
            return out
        # one stack of a common shape; each grid keeps its own corner, padded below and right
        shape = (max(sp.shape[0] for _, sp, _ in placed), max(sp.shape[1] for _, sp, _ in placed))
        span = mref.shape if near is None else (shape[0] + 2 * WINDOW_CELLS,
                                                shape[1] + 2 * WINDOW_CELLS)
        per_chunk = max(1, STACK_CELLS // int(np.prod(surface_shape(span, shape))))
        items = [(i, spec) for i, spec, _ in placed]
        mov = _stacked([crop for _, _, crop in placed], shape)
        # shifts with too little overlap to score are not computed (one trim for the stack,
        # so the reference's spectra serve all of its chunks)
        trim = overlap_trim(mov.support, MIN_OVERLAP)
        for lo_i in range(0, len(items), per_chunk):
            chunk = items[lo_i : lo_i + per_chunk]
            if near is None:
                target, window, mode = mref, grid.spec, "full"
            else:
                target, window = _window(mref, grid.spec, [sp for _, sp in chunk], shape, near)
                mode = "valid"
            part = slice(lo_i, lo_i + len(chunk))
            found = self._scores(mov.image[part], mov.support[part], target, mode, trim)
            for (i, spec), one in zip(chunk, found):
                if one is not None:
                    out[i] = Surface(*one, replace(spec, shape=shape), window, mode)
        return out

    def _placed(self, kappas: Sequence[float], sigma: float, c: float,
                bandpass: float) -> list[tuple[int, GridSpec, Prepared]]:
        """The prepared tie-point grid of each hypothesis ``(kappa, sigma)`` (cell ``c``), as
        ``(index in kappas, its spec, image and support)``, cropped to its support. A grid
        ends at its points' bounding box, as if gridded over their bounds alone.

        Headings a quarter turn apart share one grid: the cells lie on the lattice of ``c``
        about the block's origin, which a quarter turn maps onto itself, and the preparation
        (detrending, filling, band-pass, opening, clipping) commutes with it. So each heading
        modulo 90 deg is gridded and prepared once, on a square canvas about the origin that
        holds all four turns, and the others are its rotations (:func:`numpy.rot90`): a sweep's
        48 headings cost 12 preparations. Equal, to round-off, to gridding and preparing each
        heading alone (tested).
        """
        quarter = math.pi / 2
        groups: dict[float, list[tuple[int, int]]] = {}
        for i, kappa in enumerate(kappas):
            turns, base = divmod(kappa, quarter)
            if quarter - base < 1e-9:  # a whole number of turns, up to round-off
                turns, base = turns + 1, 0.0
            groups.setdefault(round(base, 12), []).append((i, int(turns) % 4))
        bases = list(groups)
        # row vectors turned anticlockwise by each base heading
        placed = [sigma * (self.xy @ rotation_matrix(0.0, 0.0, kappa)[:2, :2].T)
                  for kappa in bases]
        # half a side of the common canvas, in cells: the farthest point, and a cell of room
        reach = max(float(np.abs(xy).max()) for xy in placed) / c
        half = math.ceil(reach) + CANVAS_MARGIN_CELLS
        if (2 * half) ** 2 > MAX_TIE_CELLS:
            return []
        side = 2 * half
        # canvas j occupies rows j*side .. (j+1)*side - 1 of one tall grid
        xs = np.concatenate([xy[:, 0] for xy in placed]) + half * c
        ys = np.concatenate([xy[:, 1] - j * side * c for j, xy in enumerate(placed)])
        stat = self.channel.tie_stat
        tall = rasterize(np.column_stack([xs, ys, np.tile(self.z, len(bases))]),
                         GridSpec(0.0, half * c, c, (len(bases) * side, side)), stats=(stat,))
        shape = (len(bases), side, side)
        # each grid ends at its points' bounding box, which a quarter turn maps onto the turned
        # grid's: the filling does not stretch a block past its points (which would shrink the
        # share of it that overlaps the lidar: blocks a third on it fell under the minimum)
        mask = tall.mask.reshape(shape)
        canvas = prepare(tall[stat].reshape(shape), mask, bandpass_sigma_cells=bandpass,
                         clip_nmad=self.channel.clip_nmad, within=_bounding_boxes(mask))
        out = []
        for j, base in enumerate(bases):
            if canvas.support[j].sum() < MIN_SUPPORT_CELLS:  # the same for all four turns
                continue
            for i, turns in groups[base]:
                support = np.rot90(canvas.support[j], turns)
                r0, r1, c0, c1 = mask_bounds(support)  # not empty: it has the minimum support
                spec = GridSpec((c0 - half) * c, (half - r0) * c, c, (r1 - r0, c1 - c0))
                image = np.rot90(canvas.image[j], turns)[r0:r1, c0:c1]
                out.append((i, spec, Prepared(image, support[r0:r1, c0:c1])))
        return sorted(out, key=lambda item: item[0])

    def _scores(self, image, support, mref, mode, trim=(0, 0)):
        """Score, NCC and overlap surfaces of each prepared tie grid of a stack (``None`` for
        one with too little support)."""
        n_support = support.sum(axis=(-2, -1), keepdims=True)
        ncc, n = masked_ncc(mref, None, image, support, mode=mode, single=True, trim=trim)
        overlap = n / np.maximum(n_support, 1).astype(n.dtype)
        valid = (overlap >= MIN_OVERLAP) & (n >= MIN_SUPPORT_CELLS)
        score = np.where(valid, match_score(ncc, overlap), -np.inf).astype(ncc.dtype)
        for j in range(len(image)):
            yield None if n_support[j] < MIN_SUPPORT_CELLS else (score[j], ncc[j], overlap[j])

    def score(self, kappa: float, sigma: float) -> Hypothesis | None:
        return self.score_many([kappa], sigma)[0]

    def score_many(self, kappas: Sequence[float], sigma: float, *,
                   near: tuple[float, float] | None = None) -> list[Hypothesis | None]:
        """The best shift of each hypothesis ``(kappa, sigma)`` and its score (``near``: as in
        :meth:`surfaces`)."""
        return [None if found is None else self._best(kappa, sigma, found)
                for kappa, found in zip(kappas, self.surfaces(kappas, sigma, near=near))]

    def _best(self, kappa: float, sigma: float, found: Surface) -> Hypothesis | None:
        best = np.unravel_index(int(np.argmax(found.score)), found.score.shape)
        if not np.isfinite(found.score[best]):
            return None
        tx, ty = found.translation(subpixel_peak(found.score, best) if self.level == 1 else best)
        return Hypothesis(kappa, sigma, tx, ty, float(found.score[best]), float(found.ncc[best]),
                          float(found.overlap[best]), self.level)


def _bounding_boxes(mask: np.ndarray) -> np.ndarray:
    """Each image's bounding box of ``mask`` (a stack ``(k, rows, cols)``), as a mask."""
    def between(lines: np.ndarray) -> np.ndarray:  # from the first true line to the last
        after_first = np.logical_or.accumulate(lines, axis=1)
        before_last = np.logical_or.accumulate(lines[:, ::-1], axis=1)[:, ::-1]
        return after_first & before_last

    return between(mask.any(axis=2))[:, :, None] & between(mask.any(axis=1))[:, None, :]


def _stacked(crops: list[Prepared], shape: tuple[int, int]) -> Prepared:
    """Prepared grids padded below and right to one ``shape``, as one stack."""
    image = np.zeros((len(crops), *shape))
    support = np.zeros((len(crops), *shape), bool)
    for k, crop in enumerate(crops):
        rows, cols = crop.image.shape
        image[k, :rows, :cols] = crop.image
        support[k, :rows, :cols] = crop.support
    return Prepared(image, support)


def _window(mref: MaskedReference, spec: GridSpec, specs: list[GridSpec],
            shape: tuple[int, int], near: tuple[float, float]) -> tuple[MaskedReference,
                                                                         GridSpec]:
    """The part of a prepared reference the tie grids ``specs`` (padded to ``shape``) cover at
    translation ``near``, widened by :data:`WINDOW_CELLS` on every side; zero (no data) where it
    leaves the reference."""
    c = spec.cell_size
    r0 = [round((spec.y0 - sp.y0 - near[1]) / c) for sp in specs]  # the tie grid's first row
    c0 = [round((sp.x0 + near[0] - spec.x0) / c) for sp in specs]
    r_lo, c_lo = min(r0) - WINDOW_CELLS, min(c0) - WINDOW_CELLS
    r_hi, c_hi = max(r0) + shape[0] + WINDOW_CELLS, max(c0) + shape[1] + WINDOW_CELLS
    image = np.zeros((r_hi - r_lo, c_hi - c_lo))
    mask = np.zeros_like(image)
    rs, re = max(r_lo, 0), min(r_hi, mref.shape[0])
    cs, ce = max(c_lo, 0), min(c_hi, mref.shape[1])
    if re > rs and ce > cs:
        image[rs - r_lo : re - r_lo, cs - c_lo : ce - c_lo] = mref.image[rs:re, cs:ce]
        mask[rs - r_lo : re - r_lo, cs - c_lo : ce - c_lo] = mref.mask[rs:re, cs:ce]
    window = GridSpec(spec.x0 + c_lo * c, spec.y0 - r_lo * c, c, image.shape)
    return MaskedReference(image, mask), window


def score_around(placed: np.ndarray, ref: Reference, cell_size: float, *,
                 cells: int) -> np.ndarray | None:
    """The match score (:func:`~tiereg.coarse.correlation.match_score`) of tie points already
    placed in the reference's local frame, at every shift of up to ``cells`` cells of
    ``cell_size`` each way: a ``(2 cells + 1)`` square with zero shift at its centre, -inf where
    a shift cannot be scored; ``None`` where none near zero can (a registration that failed)."""
    found = Scorer(placed, ref, cell_size, 1).surface(0.0, 1.0)
    if found is None:
        return None
    score = found.score
    i0 = np.rint(found.index_of(0.0, 0.0)).astype(int)  # the index of zero shift
    out = np.full((2 * cells + 1, 2 * cells + 1), -np.inf)
    r0, c0 = i0[0] - cells, i0[1] - cells
    rs, cs = max(r0, 0), max(c0, 0)
    re, ce = min(i0[0] + cells + 1, score.shape[0]), min(i0[1] + cells + 1, score.shape[1])
    if re <= rs or ce <= cs:
        return None
    out[rs - r0:re - r0, cs - c0:ce - c0] = score[rs:re, cs:ce]
    return out if np.isfinite(out).any() else None
