"""Gridding an archive tile by tile on a Dask cluster, and the reference made from it.

Each tile is a task that rasterizes its points into a *partial grid*: the window of the archive's
grid that the tile's header bounds cover. Cells are found with the archive grid's own arithmetic
(:meth:`~tiereg.grid.GridSpec.cell_index`), so a point lands in the same cell as in one
process. The partial grids are merged cell by cell on the client, in tile order: counts add,
minima and maxima take the extreme (the same grid as one process, bit for bit), means are
weighted by counts (bit for bit in cells that one tile covers, to float rounding where tiles
share a cell), medians are the one-process sketch's in cells that one tile covers and the fuller
tile's elsewhere. A worker holds one tile's points and grid window at a time, whatever the
archive's size; the client holds the merged grid.

``cluster(workers=N)`` starts a local cluster, ``cluster(scheduler=ADDRESS)`` joins a running
one, ``cluster()`` gives no client and everything runs in this process (the same code, the same
answers).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .archive import Tile, TileIndex, tile_columns
from .errors import InputError, MissingDependencyError
from .grid import Grid, GridAccumulator, GridSpec, median_sample_for, nice_size
from .progress import ProgressFactory, no_progress
from .reference import Reference, reference_spec, surface_mask

log = logging.getLogger(__name__)

IN_FLIGHT_PER_WORKER = 4  # tile tasks submitted ahead per worker: bounds the workers' memory
# a COPC tile gridded into an archive reference's base grid gives only its octree levels down to
# this many points a cell side (about 16 points a cell where the data hold that many): a wide
# archive's base cell is capped to many point spacings, and its coarse grids need no more
COPC_POINTS_PER_CELL_SIDE = 4.0


@contextlib.contextmanager
def cluster(*, workers: int | None = None, scheduler: str | None = None,
            processes: bool = True) -> Iterator[Any]:
    """A ``distributed.Client`` for ``workers`` local worker processes (``processes=False``:
    threads, for tests) or for the scheduler at ``scheduler``; ``None`` with neither."""
    if workers is not None and scheduler is not None:
        raise InputError("give `workers` or `scheduler`, not both")
    if workers is None and scheduler is None:
        yield None
        return
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise MissingDependencyError("`workers` and `scheduler` need Dask: pip install "
                                     "'tiereg[distributed]'") from None
    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as exc:
            raise InputError(f"`scheduler` {scheduler}: cannot reach a Dask scheduler there "
                             f"({exc}); start one (dask scheduler) or check the address"
                             ) from None
        with client:
            yield client
        return
    if not (isinstance(workers, int) and workers >= 1):
        raise InputError(f"`workers` must be a whole number of at least 1, got {workers}")
    with _malloc_as_glibc_sets_it(), \
            LocalCluster(n_workers=workers, threads_per_worker=1, processes=processes,
                         dashboard_address=":0", silence_logs=logging.ERROR) as local, \
            Client(local) as client:
        yield client


@contextlib.contextmanager
def _malloc_as_glibc_sets_it() -> Iterator[None]:
    """Local workers started without Dask's ``MALLOC_TRIM_THRESHOLD_``: setting it turns off
    glibc's dynamic mmap threshold, so every array of the tile tasks (tens of MB each) is mapped
    afresh and paged in again; measured on 16 tiles of 10 million points in all, decoding took
    12 % more CPU and gridding 15 % more with it. The workers' memory is bounded by the tasks in
    flight (:data:`IN_FLIGHT_PER_WORKER`), not by trimming."""
    import dask

    key = "distributed.nanny.pre-spawn-environ"
    environ = {k: v for k, v in (dask.config.get(key, default=None) or {}).items()
               if k != "MALLOC_TRIM_THRESHOLD_"}
    with dask.config.set({key: environ}):
        yield


def n_workers(client: Any) -> int:
    """The workers a client has now (1 without a client)."""
    return 1 if client is None else max(1, len(client.scheduler_info().get("workers", {})))


@dataclass(frozen=True, eq=False)
class PartialGrid:
    """One tile's share of a grid: its window (rows and columns of the whole grid) and the
    statistics of its points there."""

    row0: int
    col0: int
    grid: Grid
    points: int


def tile_window(spec: GridSpec, tile: Tile, origin: np.ndarray | None) -> tuple[int, ...] | None:
    """``(row0, row1, col0, col1)`` of the cells of ``spec`` under the tile's header bounds,
    one cell of margin around (the header rounds), clipped; ``None`` when it misses ``spec``."""
    o = np.zeros(3) if origin is None else origin
    c = spec.cell_size
    col0 = math.floor((tile.mins[0] - o[0] - spec.x0) / c) - 1
    col1 = math.floor((tile.maxs[0] - o[0] - spec.x0) / c) + 2
    row0 = math.floor((spec.y0 - (tile.maxs[1] - o[1])) / c) - 1
    row1 = math.floor((spec.y0 - (tile.mins[1] - o[1])) / c) + 2
    row0, col0 = max(row0, 0), max(col0, 0)
    row1, col1 = min(row1, spec.shape[0]), min(col1, spec.shape[1])
    return None if row1 <= row0 or col1 <= col0 else (row0, row1, col0, col1)


def grid_tile(tile: Tile, spec: GridSpec, *, stats: Sequence[str], origin: np.ndarray | None,
              surface: bool, first_only: bool, median_sample: int, seed: int,
              resolution: float | None = None) -> PartialGrid:
    """Rasterize one tile into its window of ``spec`` (a task). ``origin``: subtracted from the
    points first (the local frame of a reference); ``surface``: only the points
    :func:`~tiereg.archive.surface_mask` keeps; ``resolution``: a COPC tile's octree levels
    down to that point spacing only (:func:`~tiereg.archive.tile_columns`)."""
    window = tile_window(spec, tile, origin)
    r0, r1, c0, c1 = window or (0, 1, 0, 1)
    c, width = spec.cell_size, c1 - c0
    wspec = GridSpec(spec.x0 + c0 * c, spec.y0 - r0 * c, c, (r1 - r0, width))
    acc = GridAccumulator(wspec, stats=stats, median_sample=median_sample, seed=seed)
    keep = (lambda r: surface_mask(r, first_only)) if surface else None
    lost = 0
    for x, y, z, kept in tile_columns(tile, keep=keep, resolution=resolution):
        if origin is not None:
            x -= origin[0]
            y -= origin[1]
            z -= origin[2]
        row, col = spec.cell_coordinates(x, y)  # the whole grid's arithmetic
        # the window's edges are whole cells, so comparing the fractional coordinates with
        # them finds the cells that flooring first would
        ok = (row >= r0) & (row < r1) & (col >= c0) & (col < c1)
        if kept is not None:
            ok &= kept
        if int(np.count_nonzero(ok)) < (len(z) if kept is None else np.count_nonzero(kept)):
            lost += _inside_but_not_in(spec, row, col, ok if kept is None else ok | ~kept)
        acc.add_cells((row[ok].astype(np.int64) - r0) * width
                      + (col[ok].astype(np.int64) - c0), z[ok])
    if lost:
        raise InputError(f"{tile.path}: {lost} points lie outside the tile's header bounds; the "
                         "header is wrong - re-export the tile")
    return PartialGrid(r0, c0, acc.result(), acc.points_seen)


def _inside_but_not_in(spec: GridSpec, row: np.ndarray, col: np.ndarray,
                       taken: np.ndarray) -> int:
    """How many of the points not ``taken`` (outside their tile's window) lie inside the grid:
    outside their tile's header bounds, which the window holds (those outside the grid too
    are not gridded, as in one process)."""
    r, c = row[~taken], col[~taken]
    return int(np.count_nonzero((r >= 0) & (r < spec.shape[0]) & (c >= 0) & (c < spec.shape[1])))


class GridMerger:
    """Merges :class:`PartialGrid` windows into one grid (see the module docstring)."""

    def __init__(self, spec: GridSpec, stats: Sequence[str]):
        self.spec, self.stats = spec, tuple(s for s in stats if s != "count")
        self.count = np.zeros(spec.shape, np.int64)
        self.values = {s: np.full(spec.shape, np.nan) for s in self.stats}
        self.points = 0

    def add(self, part: PartialGrid) -> None:
        g = part.grid
        sl = (slice(part.row0, part.row0 + g.spec.shape[0]),
              slice(part.col0, part.col0 + g.spec.shape[1]))
        n0, n1 = self.count[sl], g.count
        new, old = n0 == 0, n1 == 0
        for s in self.stats:
            a, b = self.values[s][sl], g[s]
            if s == "mean":
                with np.errstate(invalid="ignore"):
                    mixed = (a * n0 + b * n1) / np.maximum(n0 + n1, 1)
                out = np.where(new, b, np.where(old, a, mixed))
            elif s == "min":
                out = np.fmin(a, b)
            elif s == "max":
                out = np.fmax(a, b)
            else:  # median: the fuller share's where tiles share a cell
                out = np.where(n1 > n0, b, a)
            self.values[s][sl] = out
        self.count[sl] = n0 + n1
        self.points += part.points

    def result(self, *, crs_wkt: str | None = None) -> Grid:
        return Grid(self.spec, self.count, dict(self.values), crs_wkt)


def grid_tiles(tiles: Sequence[Tile], spec: GridSpec, *, stats: Sequence[str] = ("mean",),
               origin: np.ndarray | None = None, surface: bool = False,
               first_only: bool = False, median_sample: int = 15, client: Any = None,
               progress: ProgressFactory | None = None, crs_wkt: str | None = None,
               resolution: float | None = None) -> Grid:
    """Grid ``tiles`` on ``spec``, a task per tile (on ``client``, else here), merged in tile
    order; ``resolution``: COPC tiles give their octree levels down to it (:func:`grid_tile`)."""
    progress = progress or no_progress
    options = dict(stats=tuple(stats), origin=origin, surface=surface, first_only=first_only,
                   median_sample=median_sample, resolution=resolution)
    merger = GridMerger(spec, stats)
    todo = [(i, t) for i, t in enumerate(tiles) if tile_window(spec, t, origin) is not None]
    bar = progress("gridding tiles", len(todo))
    try:
        for part in _ordered(todo, spec, options, client):
            merger.add(part)
            bar.update(1)
    finally:
        bar.close()
    return merger.result(crs_wkt=crs_wkt)


def _ordered(todo: list[tuple[int, Tile]], spec: GridSpec, options: dict,
             client: Any) -> Iterable[PartialGrid]:
    """The tiles' partial grids in tile order; on a cluster, a bounded number ahead."""
    if client is None:
        for i, tile in todo:
            yield grid_tile(tile, spec, seed=i, **options)
        return
    spec_f = client.scatter(spec, broadcast=True)
    ahead = IN_FLIGHT_PER_WORKER * n_workers(client)
    futures: dict[int, Any] = {}

    def submit(k: int) -> None:
        i, tile = todo[k]
        futures[k] = client.submit(grid_tile, tile, spec_f, seed=i, pure=False, **options)

    for k in range(min(ahead, len(todo))):
        submit(k)
    for k in range(len(todo)):
        part = futures.pop(k).result()
        if k + ahead < len(todo):
            submit(k + ahead)
        yield part


def prepare_archive_reference(index: TileIndex, *, base_cell: float, first_returns: bool = True,
                              client: Any = None,
                              progress: ProgressFactory | None = None) -> Reference:
    """The :class:`~tiereg.reference.Reference` of an archive, gridded a tile a task: the same
    base grid as :func:`~tiereg.reference.prepare_reference` on the same tiles (noise and
    withheld points left out, first returns only where the tiles record returns), except that
    COPC tiles give only their octree levels down to :data:`COPC_POINTS_PER_CELL_SIDE` points
    a cell side (all their points where the cell is that fine)."""
    if index.count == 0:
        raise InputError("the archive's tiles hold no points; give tiles with points in them")
    lo, hi = (np.asarray(b, dtype=np.float64) for b in index.bounds)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise InputError("the archive's header bounds are not finite; a tile is corrupt - "
                         "re-export it")
    origin, spec = reference_spec(lo, hi, base_cell)
    opts = dict(stats=("mean",), origin=origin, surface=True, client=client, progress=progress,
                crs_wkt=index.crs_wkt, resolution=spec.cell_size / COPC_POINTS_PER_CELL_SIDE)
    grid = grid_tiles(index.tiles, spec, first_only=first_returns, **opts)
    use_first = first_returns
    if use_first and not grid.mask.any():  # no return numbers recorded: use all points
        use_first = False
        grid = grid_tiles(index.tiles, spec, first_only=False, **opts)
    if not grid.mask.any():
        raise InputError("no point of the archive falls inside its tiles' header bounds; the "
                         "headers are wrong - re-export the tiles")
    return Reference(index.source(), origin, grid, use_first, source_args=index.paths)


def grid_archive(paths: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
                 out_path: str | os.PathLike[str], *, cell_size: float | None = None,
                 stat: str = "mean", client: Any = None, cache: str | None = None,
                 progress: ProgressFactory | None = None) -> GridSpec:
    """``tiereg grid`` a tile a task: the GeoTIFF :func:`~tiereg.files.grid_to_geotiff` writes
    (the same spec, every point), from tiles indexed by their headers."""
    from .io import check_not_input
    from .io.raster import write_geotiff

    check_not_input(out_path, paths)
    index = TileIndex.build(paths, cache=cache)
    if index.count == 0:
        raise InputError("the tiles hold no points; nothing to grid")
    (x0, y0, _), (x1, y1, _) = index.bounds
    if cell_size is None:
        area = max((x1 - x0) * (y1 - y0), 1e-12)
        cell_size = nice_size(math.sqrt(4.0 * area / index.count))
    spec = GridSpec.from_bounds(x0, y0, x1, y1, cell_size)
    grid = grid_tiles(index.tiles, spec, stats=(stat,), client=client, progress=progress,
                      median_sample=median_sample_for(index.count / max(spec.size, 1)),
                      crs_wkt=index.crs_wkt)
    values = grid.count.astype(np.float64) if stat == "count" else grid[stat]
    write_geotiff(out_path, values, spec, crs_wkt=index.crs_wkt)
    return spec


def index_cache_beside(out: str | os.PathLike[str]) -> str:
    """Where the tile index of a run writing ``out`` is cached: ``tile-index.json`` in its
    folder (a run's results folder, or beside its output file)."""
    p = Path(out)
    return str((p if p.is_dir() else p.parent) / "tile-index.json")


def submit_all(client: Any, fn: Callable, items: Sequence, **kw: Any) -> list:
    """``[fn(x, **kw) for x in items]`` as tasks on ``client`` (here without one), in order."""
    if client is None:
        return [fn(x, **kw) for x in items]
    return client.gather([client.submit(fn, x, pure=False, **kw) for x in items])
