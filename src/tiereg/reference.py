"""The prepared reference: the lidar (or a DSM) gridded once, then seen at any coarser cell.

One streaming pass puts the reference into a fine *base* grid (per-cell count and mean, in local
coordinates: file coordinates minus ``origin``). Coarser grids are exact aggregations of the base
grid (sums and counts of blocks of cells), so the coarse stage can try cell sizes, and a benchmark
can register many tie-point sets, without reading the lidar again. The base grid itself is the
surface for sub-cell refinement.

Tie points lie on the visible surface (roofs, canopy), so lidar is gridded from first returns
when the file records returns; points classed as noise or withheld are left out.
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError
from .grid import Grid, GridAccumulator, GridSpec
from .io import PointSource
from .io.las import LasSource
from .progress import ProgressFactory, no_progress
from .surface import SurfaceSampler

# the base grid: about this many reference points per cell on average (most cells hold one), and
# at most MAX_BASE_SIDE cells along its longer side (1 M cells, 16 MB), whatever the lidar:
# memory follows this bound, never the point count. The coarse stage's grids are at most 320
# cells a side, so a base of 1,024 still divides them in three or more; its surface is then the
# tie cell over 8 or finer (5 m for 40 m cells: what the coarse and fine benchmarks measured)
BASE_SPACINGS = 1.25
MAX_BASE_SIDE = 1024
# ASPRS classes of points that are not the surface: low point (noise) and high noise; a few
# birds or multipath returns hundreds of metres off would pull whole cells of the grids
NOISE_CLASSES = (7, 18)
# ASPRS low, medium and high vegetation: lidar that enters the canopy, where its first returns lie
# anywhere down the crowns while an image's tie points sit on their tops
VEGETATION_CLASSES = (3, 4, 5)


@dataclass(frozen=True, eq=False)
class Reference:
    """A reference surface ready for registration (see the module docstring)."""

    source: PointSource
    origin: np.ndarray = field(repr=False)
    _base: Grid | None = field(repr=False)  # None until first use (:meth:`open`)
    _first_returns_only: bool
    _cache: dict[int, Grid] = field(default_factory=dict, repr=False, compare=False)
    _surface: list[SurfaceSampler] = field(default_factory=list, repr=False, compare=False)
    # the coarse stage's threads ask for grids side by side; reentrant: a grid asks for the base
    _lock: threading.RLock = field(default_factory=threading.RLock, repr=False, compare=False)
    source_args: tuple[str, ...] = ()  # the paths it was read from, when known
    _pending: tuple | None = field(default=None, repr=False, compare=False)  # (spec, progress)
    _made: list = field(default_factory=list, repr=False, compare=False)  # [base, first only]
    # pickled before its base grid is made, the receiver grids it (a mosaic's judged window, in
    # the task that uses it); otherwise the base grid is made first and sent, made once
    _grid_where_used: bool = field(default=False, repr=False, compare=False)

    @classmethod
    def open(cls, paths: str | os.PathLike[str] | Sequence[str | os.PathLike[str]], *,
             format: str | None = None, base_cell: float | None = None,
             progress: ProgressFactory | None = None) -> Reference:
        """The reference at ``paths`` (a LAS/LAZ/COPC file, several tiles, a folder or a glob
        of them, or a GeoTIFF DSM): its headers read now, its points gridded on first use
        (as :func:`prepare_reference` grids them), once. Given to :func:`tiereg.register`,
        :func:`tiereg.evaluate` or ``check_overlap`` in place of the paths, it serves many blocks
        without reading the lidar again."""
        from .io import open_points

        source = open_points(paths, format=format)
        lo, hi = _checked_bounds(source)
        origin, spec = reference_spec(lo, hi, base_cell or base_cell_for(source))
        given = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
        return cls(source, origin, None, True,
                   source_args=tuple(os.path.abspath(os.fspath(p)) for p in given),
                   _pending=(spec, progress or no_progress))

    @property
    def base(self) -> Grid:
        """The base grid (made on first use where :meth:`open` made the reference)."""
        if self._base is not None:
            return self._base
        with self._lock:
            if not self._made:
                spec, progress = self._pending
                self._made.extend(_grid_first_returns(self.source, spec, self.origin,
                                                      self._first_returns_only, progress))
            return self._made[0]

    @property
    def knows_open_ground(self) -> bool:
        """Whether the points carry classes and return numbers (LAS/LAZ/COPC), so that
        ``open_ground`` can leave out vegetation; XYZ text and PLY cannot tell."""
        return isinstance(self.source, LasSource)

    @property
    def first_returns_only(self) -> bool:
        """Whether the base grid holds first returns only (the file records returns)."""
        if self._base is not None:
            return self._first_returns_only
        _ = self.base  # decided when the points are gridded
        return self._made[1]

    @property
    def base_cell(self) -> float:
        return self.base.spec.cell_size

    @property
    def spacing(self) -> float:
        """Mean point spacing of the reference (square root of area per point)."""
        return point_spacing(self.source)

    def grid(self, cell_size: float, *, stats: tuple[str, ...] = ("mean",)) -> Grid:
        """The grid at ``k`` base cells, ``k = max(1, round(cell_size / base_cell))``, with the
        ``mean`` and the other ``stats`` asked for (``max``, :func:`aggregate`).

        The returned grid's ``spec.cell_size`` is the cell actually used; its corner is snapped to
        a multiple of that cell, like :meth:`GridSpec.from_bounds`.
        """
        k = max(1, int(round(cell_size / self.base_cell)))
        with self._lock:
            cached = self._cache.get(k)
            if cached is None or not set(stats) <= set(cached.stats):
                wanted = tuple({*stats, *(cached.stats if cached else ())})
                self._cache[k] = aggregate(self.base, k, stats=wanted)
            return self._cache[k]

    def surface(self) -> SurfaceSampler:
        """The finest surface, the base grid's, bilinear: what the continuous fits, the fine
        stage's vertical model and the height statistics sample (made once, then shared)."""
        with self._lock:
            if not self._surface:
                self._surface.append(SurfaceSampler.from_grid(self.base))
            return self._surface[0]

    def points_near(self, xy: np.ndarray, radius: float, *,
                    open_ground: bool = False) -> np.ndarray:
        """The reference points (local coordinates) within about ``radius`` of any of ``xy``
        (local), those the base grid was made from; with ``open_ground`` only those on a solid
        surface (:func:`open_ground_mask`).

        One streaming pass; a mask of cells of size ``radius`` marks the neighbourhoods, so memory
        follows the number of positions, not the lidar.
        """
        box, select = _near_cells(xy, radius, self.origin)
        kept = [c[sel] for c in self.local_chunks(box=box, open_ground=open_ground)
                if len(sel := select(c))]
        return np.concatenate(kept) if kept else np.empty((0, 3))

    def solid_near(self, xy: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`points_near` and whether each of them lies on a solid surface
        (:func:`open_ground_mask`; all do where the points carry no classes or returns), in
        the same one pass."""
        box, select = _near_cells(xy, radius, self.origin)
        kept, flags = [], []
        for chunk, solid in _solid_chunks(self.source, self.first_returns_only, box):
            chunk = chunk - self.origin
            if len(sel := select(chunk)):
                kept.append(chunk[sel])
                flags.append(solid[sel])
        if not kept:
            return np.empty((0, 3)), np.empty(0, bool)
        return np.concatenate(kept), np.concatenate(flags)

    def local_chunks(self, *, box: tuple[float, float, float, float] | None = None,
                     open_ground: bool = False) -> Iterator[np.ndarray]:
        """The reference points again, chunk by chunk, in local coordinates: those the base grid
        was made from (:func:`_chunks`); with ``box`` (file coordinates) at least those inside
        it, from the tiles that meet it only; with ``open_ground`` those on a solid surface."""
        for chunk in _chunks(self.source, self.first_returns_only, box, open_ground=open_ground):
            yield chunk - self.origin

    def __reduce__(self):
        """Pickled (to another process) without its lock and its caches, which each process
        makes anew; with ``_grid_where_used`` a base grid not made yet is made where it is
        first used."""
        if self._grid_where_used and self._base is None and not self._made:
            spec, _ = self._pending
            return (_rebuilt_pending, (self.source, self.origin, self._first_returns_only,
                                       self.source_args, spec))
        return (_rebuilt, (self.source, self.origin, self.base, self.first_returns_only,
                           self.source_args))


def _rebuilt(source, origin, base, first_returns_only, source_args) -> Reference:
    return Reference(source, origin, base, first_returns_only, source_args=source_args)


def _rebuilt_pending(source, origin, first_returns, source_args, spec) -> Reference:
    return Reference(source, origin, None, first_returns, source_args=source_args,
                     _pending=(spec, no_progress), _grid_where_used=True)


def _near_cells(xy: np.ndarray, radius: float, origin: np.ndarray):
    """The box (file coordinates) to read and a function that picks, from a chunk of points
    (local), the indices of those within about ``radius`` of any of ``xy`` (local): a mask of
    cells of size ``radius`` marks the neighbourhoods (:meth:`Reference.points_near`)."""
    lo = xy.min(axis=0) - 2 * radius
    shape = (np.ceil((xy.max(axis=0) + 2 * radius - lo) / radius)).astype(int) + 1
    near = np.zeros((shape[1], shape[0]), bool)  # rows: y, cols: x
    ix = ((xy - lo) / radius).astype(int)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            near[ix[:, 1] + dy, ix[:, 0] + dx] = True
    box = (*(lo + origin[:2]), *(lo + radius * shape + origin[:2]))

    def select(chunk: np.ndarray) -> np.ndarray:
        jx = np.floor((chunk[:, 0] - lo[0]) / radius).astype(np.int64)
        jy = np.floor((chunk[:, 1] - lo[1]) / radius).astype(np.int64)
        inside = (jx >= 0) & (jx < shape[0]) & (jy >= 0) & (jy < shape[1])
        sel = np.flatnonzero(inside)
        return sel[near[jy[sel], jx[sel]]]

    return box, select


def surface_mask(records, first_only: bool) -> np.ndarray:
    """The points of a laspy record chunk that describe the surface: not classed as noise
    (:data:`NOISE_CLASSES`), not withheld, and with ``first_only`` first returns only."""
    noise = np.isin(np.asarray(records.classification), NOISE_CLASSES)
    ok = ~noise & ~np.asarray(records.withheld, dtype=bool)
    return ok & (np.asarray(records.return_number) <= 1) if first_only else ok


def open_ground_mask(records) -> np.ndarray:
    """The points of a laspy record chunk on a solid surface (ground, roofs, roads): neither
    classed as vegetation (:data:`VEGETATION_CLASSES`) nor of a pulse that split into several
    returns (it went through something: a canopy, a wire, a roof's edge)."""
    vegetation = np.isin(np.asarray(records.classification), VEGETATION_CLASSES)
    return ~vegetation & (np.asarray(records.number_of_returns) <= 1)


def _chunks(source: PointSource, first_only: bool,
            box: tuple[float, float, float, float] | None = None, *,
            open_ground: bool = False) -> Iterator[np.ndarray]:
    """The points that describe the surface (:func:`surface_mask` for LAS/LAZ), with
    ``open_ground`` only those on a solid surface (:func:`open_ground_mask`; points without
    classes or returns, as in XYZ text or PLY, are all kept); with ``box`` (file coordinates),
    at least those inside it, read from the tiles whose header bounds meet it only."""
    if not isinstance(source, LasSource):
        return source.chunks()

    def keep(records) -> np.ndarray:
        mask = surface_mask(records, first_only)
        return mask & open_ground_mask(records) if open_ground else mask

    return source.chunks(keep=keep, box=box)  # type: ignore[call-arg]


def _solid_chunks(source: PointSource, first_only: bool,
                  box: tuple[float, float, float, float] | None = None
                  ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """:func:`_chunks`' points (file coordinates), each chunk with whether each point lies on
    a solid surface (:func:`open_ground_mask`; all do without classes or returns)."""
    if not isinstance(source, LasSource):
        for chunk in source.chunks():
            yield chunk, np.ones(len(chunk), bool)
        return
    flags: list[np.ndarray] = []

    def keep(records) -> np.ndarray:  # called once for each chunk, before it is given
        mask = surface_mask(records, first_only)
        flags.append(open_ground_mask(records)[mask])
        return mask

    for chunk in source.chunks(keep=keep, box=box):  # type: ignore[call-arg]
        yield chunk, flags.pop()


def reference_spec(lo: np.ndarray, hi: np.ndarray,
                   base_cell: float) -> tuple[np.ndarray, GridSpec]:
    """The origin (rounded centre) and the base grid (local coordinates) of a reference whose
    bounds are ``lo``, ``hi`` (file coordinates): cells of ``base_cell``, or coarser where that
    would exceed :data:`MAX_BASE_SIDE` cells a side."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    origin = np.round((lo + hi) / 2)
    lo, hi = lo - origin, hi - origin
    side = max(hi[0] - lo[0], hi[1] - lo[1]) / base_cell + 2
    if side > MAX_BASE_SIDE:  # a finer base was asked for than memory allows: still one pass
        base_cell *= math.ceil(side / MAX_BASE_SIDE)
    return origin, GridSpec.from_bounds(lo[0], lo[1], hi[0], hi[1], base_cell)


def aggregate(grid: Grid, k: int, *, stats: tuple[str, ...] = ("mean",)) -> Grid:
    """Exact mean grid over blocks of ``k x k`` cells (sums and counts), corner snapped to ``k``.

    ``"max"`` in ``stats`` adds the highest base-cell mean of each block: the top of whatever
    stands in the cell (a tree, a farmstead), which the mean of a coarse cell averages away.
    """
    if k == 1:
        if "max" not in stats or "max" in grid.stats:
            return grid
        return Grid(grid.spec, grid.count, {**grid.stats, "max": grid["mean"]}, grid.crs_wkt)
    spec = grid.spec
    c = spec.cell_size
    big = k * c
    x0 = math.floor(spec.x0 / big + 1e-9) * big
    y0 = math.ceil(spec.y0 / big - 1e-9) * big
    pad_c = int(round((spec.x0 - x0) / c))
    pad_r = int(round((y0 - spec.y0) / c))
    rows = -(-(spec.shape[0] + pad_r) // k)
    cols = -(-(spec.shape[1] + pad_c) // k)
    count = np.zeros((rows * k, cols * k), np.int64)
    total = np.zeros((rows * k, cols * k))
    sl = (slice(pad_r, pad_r + spec.shape[0]), slice(pad_c, pad_c + spec.shape[1]))
    count[sl] = grid.count
    total[sl] = np.where(grid.count > 0, grid["mean"] * grid.count, 0.0)
    count = count.reshape(rows, k, cols, k).sum(axis=(1, 3))
    total = total.reshape(rows, k, cols, k).sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = {"mean": np.where(count > 0, total / count, np.nan)}
    if "max" in stats:
        top = np.full((rows * k, cols * k), -np.inf)
        top[sl] = np.where(grid.count > 0, grid["mean"], -np.inf)
        top = top.reshape(rows, k, cols, k).max(axis=(1, 3))
        out["max"] = np.where(count > 0, top, np.nan)
    return Grid(GridSpec(x0, y0, big, (rows, cols)), count, out, grid.crs_wkt)


def point_spacing(source: PointSource) -> float:
    """Mean point spacing: the square root of the bounding-box area per point."""
    assert source.info.bounds is not None
    (x0, y0, _), (x1, y1, _) = source.info.bounds
    area = max((x1 - x0) * (y1 - y0), 1e-12)
    return math.sqrt(area / max(source.info.count, 1))


def base_cell_for(source: PointSource) -> float:
    """The base cell of a reference, from the reference alone: :data:`BASE_SPACINGS` point
    spacings, or coarser where that would make more than :data:`MAX_BASE_SIDE` cells along the
    longer side. The moving points do not enter: their units are unknown until registered."""
    assert source.info.bounds is not None
    (x0, y0, _), (x1, y1, _) = source.info.bounds
    extent = max(x1 - x0, y1 - y0, 0.0)
    cell = max(BASE_SPACINGS * point_spacing(source), extent / MAX_BASE_SIDE)
    return cell if cell > 0 and math.isfinite(cell) else 1.0


def prepare_reference(
    source: PointSource,
    *,
    base_cell: float | None = None,
    first_returns: bool = True,
    progress: ProgressFactory | None = None,
) -> Reference:
    """Grid ``source`` once at ``base_cell`` (default :func:`base_cell_for`; one streaming pass,
    memory follows the grid, at most :data:`MAX_BASE_SIDE` cells a side)."""
    lo, hi = _checked_bounds(source)
    origin, spec = reference_spec(lo, hi, base_cell or base_cell_for(source))
    grid, use_first = _grid_first_returns(source, spec, origin, first_returns,
                                         progress or no_progress)
    return Reference(source, origin, grid, use_first)


def _checked_bounds(source: PointSource) -> tuple[np.ndarray, np.ndarray]:
    """The reference's bounds from its header(s), refused where it is empty or corrupt."""
    info = source.info
    if info.count == 0:
        raise InputError(f"{info.path}: the reference point set is empty; "
                         "give a file with points in it")
    assert info.bounds is not None
    lo, hi = np.asarray(info.bounds[0], dtype=np.float64), np.asarray(info.bounds[1])
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise InputError(f"{info.path}: the reference bounds are not finite; the file is "
                         "corrupt - re-export it")
    return lo, hi


def _grid_first_returns(source: PointSource, spec: GridSpec, origin: np.ndarray,
                        first_returns: bool, progress: ProgressFactory) -> tuple[Grid, bool]:
    """The base grid of first returns where the file records returns, else of all points."""
    use_first = first_returns and isinstance(source, LasSource)
    grid = _grid(source, spec, origin, use_first, progress)
    if use_first and not grid.mask.any():  # no return numbers recorded: use all points
        use_first = False
        grid = _grid(source, spec, origin, False, progress)
    if not grid.mask.any():
        raise InputError(f"{source.info.path}: no reference point falls inside its own header "
                         "bounds; the header is wrong - re-export the file")
    return grid, use_first


def _grid(source: PointSource, spec: GridSpec, origin: np.ndarray, first_only: bool,
          progress: ProgressFactory) -> Grid:
    acc = GridAccumulator(spec, stats=("mean",))
    bar = progress(f"gridding {source.info.path.rsplit('/', 1)[-1]}", source.info.count)
    try:
        for chunk in _chunks(source, first_only):
            acc.add(chunk - origin)
            bar.update(len(chunk))
    finally:
        bar.close()
    return acc.result(crs_wkt=source.info.crs_wkt)
