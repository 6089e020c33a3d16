"""Grids: a spec with an explicit pixel convention, and chunked rasterization of points.

Convention (as GeoTIFF, north up): ``(x0, y0)`` is the *upper-left corner* of the grid; row
``r`` and column ``c`` cover ``[x0 + c*cell, x0 + (c+1)*cell) x (y0 - (r+1)*cell, y0 - r*cell]``
and their centre is ``(x0 + (c + 0.5)*cell, y0 - (r + 0.5)*cell)``. Rows grow southwards.

Rasterization accumulates per-cell statistics chunk by chunk; memory depends on the grid, never
on the number of points.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from .errors import InputError

STATS = ("count", "min", "max", "mean", "median")
MEDIAN_SAMPLE = 15
MERGE_BLOCK = 65_536  # cells merged at once by the median sketch


@dataclass(frozen=True)
class GridSpec:
    """A north-up grid: upper-left corner ``(x0, y0)``, square cells, ``shape = (rows, cols)``."""

    x0: float
    y0: float
    cell_size: float
    shape: tuple[int, int]

    def __post_init__(self) -> None:
        if not (self.cell_size > 0 and math.isfinite(self.cell_size)):
            raise InputError(f"the cell size must be a positive number, got {self.cell_size}")
        if self.shape[0] < 1 or self.shape[1] < 1:
            raise InputError(f"a grid needs at least one row and column, got {self.shape}")

    @classmethod
    def from_bounds(
        cls,
        xmin: float,
        ymin: float,
        xmax: float,
        ymax: float,
        cell_size: float,
        *,
        pad_cells: int = 0,
        max_cells: int = 400_000_000,
    ) -> GridSpec:
        """The grid covering a box, its corner snapped to a multiple of the cell size.

        Snapping makes grids of the same cell size line up cell for cell across data sets.
        """
        if not (cell_size > 0 and math.isfinite(cell_size)):
            raise InputError(f"the cell size must be a positive number, got {cell_size}")
        if not all(map(math.isfinite, (xmin, ymin, xmax, ymax))):
            raise InputError(f"the extent to grid ({xmin}, {ymin}) - ({xmax}, {ymax}) is not "
                             "finite: some coordinates are NaN or infinite; remove them")
        x0 = (math.floor(xmin / cell_size) - pad_cells) * cell_size
        y0 = (math.floor(ymax / cell_size) + 1 + pad_cells) * cell_size
        cols = int(math.floor((xmax - x0) / cell_size)) + 1 + pad_cells
        rows = int(math.floor((y0 - ymin) / cell_size)) + 1 + pad_cells
        if rows * cols > max_cells:
            raise InputError(
                f"a {cell_size:g}-unit grid over this extent would have {rows}x{cols} cells; "
                "choose a larger `cell_size`"
            )
        return cls(float(x0), float(y0), float(cell_size), (rows, cols))

    @property
    def size(self) -> int:
        return self.shape[0] * self.shape[1]

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of the outer cell edges."""
        rows, cols = self.shape
        c = self.cell_size
        return (self.x0, self.y0 - rows * c, self.x0 + cols * c, self.y0)

    def xy(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre coordinates of (fractional) row and column indices."""
        c = self.cell_size
        return self.x0 + (np.asarray(cols) + 0.5) * c, self.y0 - (np.asarray(rows) + 0.5) * c

    def rowcol(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fractional (row, col) of positions, cell centres at integers."""
        c = self.cell_size
        return (self.y0 - np.asarray(y)) / c - 0.5, (np.asarray(x) - self.x0) / c - 0.5

    def cell_coordinates(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) of positions in cells from the grid's corner, fractional: a position
        lies in the cell ``(floor(row), floor(col))`` (the arithmetic every gridding shares)."""
        inv = 1.0 / self.cell_size
        return (self.y0 - np.asarray(y)) * inv, (np.asarray(x) - self.x0) * inv

    def cell_index(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat cell index of each position and whether it falls inside the grid."""
        row, col = self.cell_coordinates(x, y)
        inside = (row >= 0) & (row < self.shape[0]) & (col >= 0) & (col < self.shape[1])
        # truncation equals floor for the non-negative values inside; outside cells get 0
        idx = row.astype(np.int64) * self.shape[1] + col.astype(np.int64)
        idx[~inside] = 0
        return idx, inside


@dataclass(frozen=True, eq=False)
class Grid:
    """Per-cell statistics of points on a :class:`GridSpec`; NaN where a cell has no point."""

    spec: GridSpec
    count: np.ndarray = field(repr=False)
    stats: dict[str, np.ndarray] = field(repr=False)
    crs_wkt: str | None = field(default=None, repr=False)

    def __getitem__(self, stat: str) -> np.ndarray:
        if stat == "count":
            return self.count
        if stat not in self.stats:
            raise InputError(
                f"statistic {stat!r} was not computed for this grid; have {sorted(self.stats)}"
            )
        return self.stats[stat]

    @property
    def mask(self) -> np.ndarray:
        return self.count > 0

    @property
    def occupancy(self) -> float:
        return float(self.mask.mean())

    def cell_points(self, *, max_cells: int | None = None) -> np.ndarray:
        """The filled cells as ``(N, 3)`` points: their centres and mean heights, in the grid's
        frame; at most about ``max_cells`` of them (evenly strided) when given."""
        rows, cols = np.nonzero(self.mask)
        step = max(1, len(rows) // max_cells) if max_cells else 1
        rows, cols = rows[::step], cols[::step]
        x, y = self.spec.xy(rows, cols)
        return np.column_stack([x, y, self["mean"][rows, cols]])


class GridAccumulator:
    """Accumulate per-cell statistics of point chunks on a fixed grid.

    ``count``, ``min``, ``max`` and ``mean`` are exact. ``median`` is exact for cells with at most
    ``median_sample`` points; in fuller cells it is the median of a uniform random sample of
    ``median_sample`` of the cell's points (a bottom-k sketch over random keys), so memory stays
    ``O(cells * median_sample)`` however many points arrive.
    """

    def __init__(
        self,
        spec: GridSpec,
        *,
        stats: Sequence[str] = ("mean",),
        median_sample: int = MEDIAN_SAMPLE,
        seed: int = 0,
    ):
        unknown = set(stats) - set(STATS)
        if unknown:
            raise InputError(f"unknown grid statistic {sorted(unknown)}; choose from {STATS}")
        self.spec = spec
        self.stats = tuple(dict.fromkeys(s for s in stats if s != "count"))
        n = spec.size
        self._count = np.zeros(n, np.int64)
        self._sum = np.zeros(n) if "mean" in self.stats else None
        self._min = np.full(n, np.inf) if "min" in self.stats else None
        self._max = np.full(n, -np.inf) if "max" in self.stats else None
        self._k = int(median_sample)
        if "median" in self.stats:
            self._rng = np.random.default_rng(seed)
            self._keys = np.full((n, self._k), np.inf, np.float32)
            self._vals = np.full((n, self._k), np.nan)
        self.points_seen = 0

    def add(self, xyz: np.ndarray) -> None:
        """Add a chunk of ``(n, 3)`` points; points outside the grid or not finite are ignored."""
        xyz = np.asarray(xyz, dtype=np.float64)
        self.points_seen += len(xyz)
        idx, inside = self.spec.cell_index(xyz[:, 0], xyz[:, 1])
        inside &= np.isfinite(xyz[:, 2])
        if not inside.all():
            idx, z = idx[inside], xyz[inside, 2]
        else:
            z = xyz[:, 2]
        self._add_cells(idx, z)

    def add_cells(self, idx: np.ndarray, z: np.ndarray) -> None:
        """Add heights ``z`` at flat cell indices ``idx`` found by the caller (each inside the
        grid, each ``z`` finite)."""
        self.points_seen += len(z)
        self._add_cells(np.asarray(idx, dtype=np.int64), np.asarray(z, dtype=np.float64))

    def _add_cells(self, idx: np.ndarray, z: np.ndarray) -> None:
        if len(idx) == 0:
            return
        # count over the chunk's own index range: a chunk of strip-ordered lidar touches a
        # fraction of a large grid, and full-grid bincounts would cost the grid's size per chunk
        lo, hi = int(idx.min()), int(idx.max()) + 1
        local = idx - lo
        self._count[lo:hi] += np.bincount(local, minlength=hi - lo)
        if self._sum is not None:
            self._sum[lo:hi] += np.bincount(local, weights=z, minlength=hi - lo)
        if self._min is not None:
            np.minimum.at(self._min, idx, z)
        if self._max is not None:
            np.maximum.at(self._max, idx, z)
        if "median" in self.stats:
            self._add_median(idx, z)

    def _add_median(self, idx: np.ndarray, z: np.ndarray) -> None:
        k = self._k
        u = self._rng.random(len(idx), dtype=np.float32)
        cand = u < self._keys[idx, k - 1]  # beats the k-th smallest key of its cell
        idx, u, z = idx[cand], u[cand], z[cand]
        if len(idx) == 0:
            return
        order = np.argsort(idx.astype(np.float64) + u.astype(np.float64) * 0.999, kind="stable")
        idx, u, z = idx[order], u[order], z[order]
        first = np.r_[True, idx[1:] != idx[:-1]]
        pos = np.arange(len(idx))
        rank = pos - np.maximum.accumulate(np.where(first, pos, 0))
        keep = rank < k
        idx, u, z, rank, first = idx[keep], u[keep], z[keep], rank[keep], first[keep]
        group = np.cumsum(first) - 1
        cells = idx[first]
        # merge with the cells' current samples, a block of cells at a time so that the
        # temporaries stay small whatever the chunk size
        for lo in range(0, len(cells), MERGE_BLOCK):
            hi = min(lo + MERGE_BLOCK, len(cells))
            sel = slice(*np.searchsorted(group, [lo, hi]))  # candidates sorted by cell
            block = cells[lo:hi]
            new_keys = np.full((hi - lo, k), np.inf, np.float32)
            new_vals = np.full((hi - lo, k), np.nan)
            new_keys[group[sel] - lo, rank[sel]] = u[sel]
            new_vals[group[sel] - lo, rank[sel]] = z[sel]
            keys = np.concatenate([self._keys[block], new_keys], axis=1)
            vals = np.concatenate([self._vals[block], new_vals], axis=1)
            best = np.argsort(keys, axis=1, kind="stable")[:, :k]
            self._keys[block] = np.take_along_axis(keys, best, axis=1)
            self._vals[block] = np.take_along_axis(vals, best, axis=1)

    def result(self, *, crs_wkt: str | None = None) -> Grid:
        shape = self.spec.shape
        count = self._count.reshape(shape)
        empty = self._count == 0
        out: dict[str, np.ndarray] = {}
        with np.errstate(invalid="ignore", divide="ignore"):
            if self._sum is not None:
                out["mean"] = np.where(empty, np.nan, self._sum / self._count).reshape(shape)
        if self._min is not None:
            out["min"] = np.where(empty, np.nan, self._min).reshape(shape)
        if self._max is not None:
            out["max"] = np.where(empty, np.nan, self._max).reshape(shape)
        if "median" in self.stats:
            out["median"] = _row_medians(self._vals, self._count).reshape(shape)
        return Grid(self.spec, count, out, crs_wkt)


def _row_medians(vals: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Median of the first ``min(count, k)`` finite values of each row; NaN for empty rows.

    Vectorized and blockwise (``np.nanmedian`` loops in Python over short rows).
    """
    out = np.full(len(vals), np.nan)
    k = vals.shape[1]
    for lo in range(0, len(vals), MERGE_BLOCK * 4):
        block = np.sort(vals[lo : lo + MERGE_BLOCK * 4], axis=1)  # NaN (unused slots) sort last
        n = np.minimum(count[lo : lo + MERGE_BLOCK * 4], k)
        has = n > 0
        rows = np.flatnonzero(has)
        a = block[rows, (n[has] - 1) // 2]
        b = block[rows, n[has] // 2]
        out[lo + rows] = 0.5 * (a + b)
    return out


def median_sample_for(points_per_cell: float) -> int:
    """Sketch size for an expected number of points per cell: exact below it, bounded above.

    Four times the expected count (odd), between 7 and 31: a 1 m grid of 2 pts/m^2 lidar keeps
    7 values a cell (84 bytes), a 40 m grid 31.
    """
    k = int(np.clip(np.ceil(4 * points_per_cell), 7, 31))
    return k if k % 2 else k + 1


def rasterize(
    points: np.ndarray | Iterable[np.ndarray],
    spec: GridSpec,
    *,
    stats: Sequence[str] = ("mean",),
    median_sample: int = MEDIAN_SAMPLE,
    seed: int = 0,
    crs_wkt: str | None = None,
    progress: Callable[[int], None] | None = None,
) -> Grid:
    """Grid an ``(N, 3)`` array, or an iterable of such chunks (e.g. ``source.chunks()``)."""
    acc = GridAccumulator(spec, stats=stats, median_sample=median_sample, seed=seed)
    chunks = [points] if isinstance(points, np.ndarray) else points
    for chunk in chunks:
        acc.add(chunk)
        if progress is not None:
            progress(len(chunk))
    return acc.result(crs_wkt=crs_wkt)


def nice_size(value: float) -> float:
    """Round to 1, 1.5, 2, 2.5, 3, 4, 5, 6 or 8 times a power of ten."""
    if value <= 0 or not math.isfinite(value):
        raise InputError(f"cannot derive a cell size from a spacing of {value}")
    exp = math.floor(math.log10(value))
    base = value / 10**exp
    steps = (1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0)
    best = min(steps, key=lambda s: abs(math.log(s / base)))
    return best * 10**exp


def cell_size_from_density(xy: np.ndarray, *, points_per_cell: float = 0.64) -> float:
    """A cell size for a sparse point set: ``sqrt(points_per_cell * area / n)``, rounded nicely.

    ``area`` is the convex hull of the points in plan view. The default of 0.64 points per cell
    (about 47 % of cells occupied for uniform points) keeps enough cells for correlation while
    most occupied cells hold a single point.
    """
    from scipy.spatial import ConvexHull, QhullError

    xy = np.asarray(xy, dtype=np.float64)[:, :2]
    n = len(xy)
    if n < 3:
        raise InputError("need at least 3 points to derive a cell size; give `cell_size`")
    centred = xy - xy.mean(axis=0)
    try:
        area = ConvexHull(centred).volume  # in 2-D, 'volume' is the area
    except QhullError:
        raise InputError(
            "the points lie on a line in plan view, so no cell size can be derived from them"
        ) from None
    return nice_size(math.sqrt(points_per_cell * area / n))


def mask_bounds(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """``(row0, row1, col0, col1)``, ends exclusive: the bounding box of a 2-D mask's true cells;
    ``None`` where there are none."""
    rows, cols = np.flatnonzero(np.any(mask, axis=1)), np.flatnonzero(np.any(mask, axis=0))
    if len(rows) == 0:
        return None
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def fill_normalized(
    values: np.ndarray,
    mask: np.ndarray,
    *,
    sigma_cells: float = 1.0,
    min_support: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """Mask-aware gap filling by normalized convolution (Knutsson & Westin 1993).

    ``f = (G * (g m)) / (G * m)`` with a Gaussian ``G`` of ``sigma_cells``; cells where the
    smoothed mask ``G * m`` is below ``min_support`` stay unsupported. Returns ``(filled,
    support)``; ``filled`` is 0 outside the support. A stack ``(..., rows, cols)`` is filled
    image by image.
    """
    mask = np.asarray(mask, bool)
    m = mask.astype(np.float64)
    g = np.where(mask, np.nan_to_num(np.asarray(values, dtype=np.float64)), 0.0)
    sigma = (0.0,) * (g.ndim - 2) + (sigma_cells, sigma_cells)  # a stack: each image alone
    num = ndimage.gaussian_filter(g, sigma, mode="constant", truncate=3.0)  # g is 0 off the mask
    den = ndimage.gaussian_filter(m, sigma, mode="constant", truncate=3.0)
    support = den > min_support
    filled = np.divide(num, den, out=np.zeros_like(g), where=support)
    return filled, support
