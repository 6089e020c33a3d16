"""A gridded reference surface seen at arbitrary positions: bilinear heights and gradients.

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
        v = self.values
        z = ((v[r0, c0] * (1 - fc) + v[r0, c1] * fc) * (1 - fr)
             + (v[r1, c0] * (1 - fc) + v[r1, c1] * fc) * fr)
        rn = np.clip(np.rint(rows), 0, h - 1).astype(np.intp)
        cn = np.clip(np.rint(cols), 0, w - 1).astype(np.intp)
        mask = self.valid if within is None else within
        return z, inside & mask[rn, cn]

    def gradient(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(dZ/dx, dZ/dy)`` of the bilinear surface at the positions (per cell, constant)."""
        spec = self.grid.spec
        rows, cols = spec.rowcol(x, y)
        r0, c0, r1, c1, fr, fc = self._cell(rows, cols)
        v = self.values
        dz_dcol = (v[r0, c1] - v[r0, c0]) * (1 - fr) + (v[r1, c1] - v[r1, c0]) * fr
        dz_drow = (v[r1, c0] - v[r0, c0]) * (1 - fc) + (v[r1, c1] - v[r0, c1]) * fc
        return dz_dcol / spec.cell_size, -dz_drow / spec.cell_size
