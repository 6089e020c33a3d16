"""Sub-cell refinement of a horizontal shift and height offset against a reference surface.

Vertical distances of the points to the surface (least z-difference, Rosenholm & Torlegard 1988),
``r_i = Z(x_i + tx, y_i + ty) - (z_i + tz)``, restricted to a translation and minimised robustly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..grid import Grid, fill_normalized
from ..robust import nmad


@dataclass(frozen=True)
class SurfaceSampler:
    """Bilinear heights and gradients of a grid surface at arbitrary positions."""

    grid: Grid
    values: np.ndarray
    grad_row: np.ndarray
    grad_col: np.ndarray
    valid: np.ndarray

    @classmethod
    def from_grid(cls, grid: Grid, *, stat: str = "mean") -> SurfaceSampler:
        filled, support = fill_normalized(grid[stat], grid.mask, sigma_cells=0.7)
        valid = ndimage.binary_erosion(support & grid.mask | support, iterations=1)
        g_row, g_col = np.gradient(filled)
        return cls(grid, filled, g_row, g_col, valid)

    def sample(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                            np.ndarray]:
        """Heights ``Z``, gradients ``dZ/dx``, ``dZ/dy`` (per map unit) and a validity mask."""
        spec = self.grid.spec
        rows, cols = spec.rowcol(x, y)
        coords = np.vstack([rows, cols])
        z = ndimage.map_coordinates(self.values, coords, order=1, mode="nearest")
        gr = ndimage.map_coordinates(self.grad_row, coords, order=1, mode="nearest")
        gc = ndimage.map_coordinates(self.grad_col, coords, order=1, mode="nearest")
        ok = ndimage.map_coordinates(self.valid.astype(np.float64), coords, order=0,
                                     mode="constant", cval=0.0) > 0.5
        inside = (rows >= 0) & (rows <= spec.shape[0] - 1) & (cols >= 0) & (
            cols <= spec.shape[1] - 1)
        c = spec.cell_size
        return z, gc / c, -gr / c, ok & inside


@dataclass(frozen=True)
class TranslationFit:
    translation: tuple[float, float, float]
    iterations: int
    converged: bool
    n_used: int
    sigma0: float


def height_offset(xyz: np.ndarray, sampler: SurfaceSampler, shift_xy: np.ndarray) -> float:
    """Median of ``Z_ref(x + t) - z`` over the points that land on valid reference cells."""
    z, _, _, ok = sampler.sample(xyz[:, 0] + shift_xy[0], xyz[:, 1] + shift_xy[1])
    if not ok.any():
        return float("nan")
    return float(np.median(z[ok] - xyz[ok, 2]))


def _tukey_loss(r: np.ndarray, scale: float, c: float = 4.685) -> np.ndarray:
    """Tukey's biweight loss, bounded at ``c^2/6``: blunders cost a constant."""
    a = np.clip(np.abs(r) / (c * scale), 0.0, 1.0)
    return (c**2 / 6.0) * (1.0 - (1.0 - a**2) ** 3)


def refine_translation(
    xyz: np.ndarray,
    sampler: SurfaceSampler,
    initial: np.ndarray,
    *,
    search_radius: float | None = None,
    tol: float | None = None,
    max_iterations: int = 400,
) -> TranslationFit:
    """Minimise a robust loss of vertical distances over the horizontal shift.

    For a shift ``t`` the height offset is profiled out as ``tz(t) = median(Z(x+t) - z)`` and the
    loss is ``sum rho((Z(x + t) - z - tz) / s)`` with Tukey's bounded ``rho`` and a fixed scale
    ``s`` (NMAD at the start), so canopy points and blunders cannot pull the answer. The loss is
    minimised by a compass (pattern) search: derivative-free, hence indifferent to the noisy
    gradients of a gridded surface. Starts with steps of half the ``search_radius`` (default one
    cell of the surface), stops at ``tol`` (default 1/500 cell) and never leaves that radius.
    """
    t0 = np.asarray(initial, dtype=np.float64)[:2].copy()
    cell = sampler.grid.spec.cell_size
    radius = cell if search_radius is None else search_radius
    tol = cell / 500 if tol is None else tol
    z_all = xyz[:, 2]

    def residuals(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        z, _, _, ok = sampler.sample(xyz[:, 0] + t[0], xyz[:, 1] + t[1])
        return z - z_all, ok

    r0, ok0 = residuals(t0)
    if ok0.sum() < 10:
        return TranslationFit((float(t0[0]), float(t0[1]), float("nan")), 0, False,
                              int(ok0.sum()), float("nan"))
    scale = max(nmad(r0[ok0]), 1e-6 * max(1.0, float(np.abs(z_all).max())))
    # the same points throughout, so losses at different shifts compare fairly
    use = ok0

    def loss(t: np.ndarray) -> float:
        r, ok = residuals(t)
        good = use & ok
        if good.sum() < 0.9 * use.sum():
            return np.inf
        d = r[good] - np.median(r[good])
        return float(_tukey_loss(d, scale).sum() + (use.sum() - good.sum()) * 4.685**2 / 6)

    t, best = t0.copy(), loss(t0)
    step = radius / 2
    directions = np.array([[1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [1, -1], [-1, 1], [-1, -1]],
                          dtype=np.float64)
    it = 0
    while step >= tol and it < max_iterations:
        it += 1
        trials = t + step * directions
        trials = trials[np.hypot(*(trials - t0).T) <= radius]
        values = [loss(p) for p in trials]
        if values and min(values) < best:
            k = int(np.argmin(values))
            t, best = trials[k], values[k]
        else:
            step /= 2
    r, ok = residuals(t)
    good = use & ok
    tz = float(np.median(r[good]))
    sigma = nmad(r[good] - tz)
    on_edge = np.hypot(*(t - t0)) > radius - 2 * tol
    return TranslationFit((float(t[0]), float(t[1]), tz), it, step < tol and not on_edge,
                          int(good.sum()), sigma)
