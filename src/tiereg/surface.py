"""The reference surface seen at arbitrary positions: bilinear heights and gradients of a grid
(:class:`SurfaceSampler`), and local planes of the reference's own points (:class:`LocalSurface`).

The one home of surface sampling for the coarse refinement, the fine stage and the quality
statistics. Positions are in the grid's (local) coordinates; cells are addressed as everywhere in
tiereg (upper-left corner, rows southwards).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from .grid import Grid, fill_normalized


@dataclass(frozen=True)
class SurfaceSampler:
    """Bilinear heights of a grid surface at arbitrary positions, with a validity mask."""

    grid: Grid
    values: np.ndarray
    valid: np.ndarray
    _inner: dict = field(default_factory=dict, repr=False, compare=False)
    _half_range: list = field(default_factory=list, repr=False, compare=False)

    @classmethod
    def from_grid(cls, grid: Grid, *, stat: str = "mean") -> SurfaceSampler:
        filled, support = fill_normalized(grid[stat], grid.mask, sigma_cells=0.7)
        valid = ndimage.binary_erosion(support, iterations=1)
        return cls(grid, filled, valid, {})

    def inner(self, margin_cells: int) -> np.ndarray:
        """The valid cells at least ``margin_cells`` inside the surface (all valid cells when the
        surface is too small to keep any)."""
        if margin_cells not in self._inner:
            inner = ndimage.binary_erosion(self.valid, iterations=margin_cells)
            self._inner[margin_cells] = inner if inner.any() else self.valid
        return self._inner[margin_cells]

    def roughness(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Half the range of the surface's heights over the 3 x 3 cells around each position's
        nearest cell: how far the surface rises or falls within about a cell, the part of a
        height residual that a sub-cell shift or the grid's own blur explains (edges clamped)."""
        if not self._half_range:
            v = self.values
            self._half_range.append(0.5 * (ndimage.maximum_filter(v, size=3, mode="nearest")
                                           - ndimage.minimum_filter(v, size=3, mode="nearest")))
        rn, cn = self._nearest(*self.grid.spec.rowcol(x, y))
        return self._half_range[0][rn, cn]

    def _nearest(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The nearest cell of each position (edges clamped)."""
        h, w = self.values.shape
        return (np.clip(np.rint(rows), 0, h - 1).astype(np.intp),
                np.clip(np.rint(cols), 0, w - 1).astype(np.intp))

    def _cell(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, ...]:
        """The bilinear cell of each position: corner indices and fractions (edges clamped)."""
        h, w = self.values.shape
        r0 = np.clip(np.floor(rows), 0, max(h - 2, 0)).astype(np.intp)
        c0 = np.clip(np.floor(cols), 0, max(w - 2, 0)).astype(np.intp)
        fr = np.clip(rows - r0, 0.0, 1.0) if h > 1 else np.zeros_like(rows)
        fc = np.clip(cols - c0, 0.0, 1.0) if w > 1 else np.zeros_like(cols)
        r1, c1 = np.minimum(r0 + 1, h - 1), np.minimum(c0 + 1, w - 1)
        return r0, c0, r1, c1, fr, fc

    def sample(self, x: np.ndarray, y: np.ndarray, *,
               within: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Heights ``Z`` at the positions (bilinear, edges clamped) and whether each lies on valid
        surface (the nearest cell is valid, or is set in ``within``, a mask of the grid's shape).
        """
        rows, cols = self.grid.spec.rowcol(x, y)
        h, w = self.values.shape
        inside = (rows >= 0) & (rows <= h - 1) & (cols >= 0) & (cols <= w - 1)
        r0, c0, r1, c1, fr, fc = self._cell(rows, cols)
        # flat indices: one gather per corner (the fits sample thousands of times)
        v = self.values.ravel()
        top, bottom = r0 * w, r1 * w
        z = ((v.take(top + c0) * (1 - fc) + v.take(top + c1) * fc) * (1 - fr)
             + (v.take(bottom + c0) * (1 - fc) + v.take(bottom + c1) * fc) * fr)
        rn, cn = self._nearest(rows, cols)
        mask = self.valid if within is None else within
        return z, inside & mask.ravel().take(rn * w + cn)

    def gradient(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(dZ/dx, dZ/dy)`` of the bilinear surface at the positions (per cell, constant)."""
        spec = self.grid.spec
        rows, cols = spec.rowcol(x, y)
        r0, c0, r1, c1, fr, fc = self._cell(rows, cols)
        v = self.values
        dz_dcol = (v[r0, c1] - v[r0, c0]) * (1 - fr) + (v[r1, c1] - v[r1, c0]) * fr
        dz_drow = (v[r1, c0] - v[r0, c0]) * (1 - fc) + (v[r1, c1] - v[r0, c1]) * fc
        return dz_dcol / spec.cell_size, -dz_drow / spec.cell_size


STEEP_NZ = 0.5  # planes steeper than 60 degrees give the nearest point's height instead


def fit_planes(patches: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Planes through patches of points ``(m, k, 3)`` by principal axes: centroids ``(m, 3)``,
    upward unit normals ``(m, 3)`` and the standard deviation of the points off each plane
    (``sqrt`` of the smallest eigenvalue of the patch covariance)."""
    c = patches.mean(axis=1)
    d = patches - c[:, None, :]
    evals, vecs = np.linalg.eigh(np.einsum("mki,mkj->mij", d, d) / patches.shape[1])
    n = vecs[:, :, 0]
    n = n * np.where(n[:, 2] < 0, -1.0, 1.0)[:, None]
    return c, n, np.sqrt(np.maximum(evals[:, 0], 0.0))


def plane_heights(centroid: np.ndarray, normal: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``z = c_z - (n_x (x - c_x) + n_y (y - c_y)) / n_z`` of each plane at its position
    (``inf``/NaN for vertical planes)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return centroid[:, 2] - (normal[:, 0] * (xy[:, 0] - centroid[:, 0])
                                 + normal[:, 1] * (xy[:, 1] - centroid[:, 1])) / normal[:, 2]


@dataclass(frozen=True, eq=False)
class LocalSurface:
    """Heights of the reference's own points: at a position, the plane through its
    ``neighbours`` nearest points in plan (principal axes), where they lie within ``radius``.

    Finer than any grid: a tie point beside a wall or in a canopy gap is compared with the lidar
    right there, not with a cell's mean.
    """

    points: np.ndarray = field(repr=False)  # (N, 3), local coordinates
    radius: float
    neighbours: int = 8
    _tree: object = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        from scipy.spatial import cKDTree

        object.__setattr__(self, "_tree", cKDTree(self.points[:, :2]))

    def heights(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """``Z`` at each position (NaN where the neighbourhood is not full)."""
        xy = np.column_stack([x, y])
        k = min(self.neighbours, len(self.points))
        dist, idx = self._tree.query(xy, k=k, distance_upper_bound=self.radius)
        dist = dist.reshape(len(xy), -1)
        idx = idx.reshape(len(xy), -1)
        z = np.full(len(xy), np.nan)
        full = np.isfinite(dist).all(axis=1)
        if not full.any():
            return z
        nb = self.points[idx[full]]
        c, n, _ = fit_planes(nb)
        zp = plane_heights(c, n, xy[full])
        # a steep plane (a wall, the step at a roof's edge) has no height to speak of: there the
        # nearest point's, the highest of several as near (the visible surface, which a tie
        # point lies on)
        dd = dist[full]
        nearest = np.where(dd <= dd[:, :1] + 1e-9, nb[:, :, 2], -np.inf).max(axis=1)
        z[full] = np.where(np.abs(n[:, 2]) >= STEEP_NZ, zp, nearest)
        return z
