"""Sub-cell refinement of a horizontal shift and height offset against a reference surface.

Vertical distances of the points to the surface (least z-difference, Rosenholm & Torlegard 1988),
``r_i = Z(x_i + tx, y_i + ty) - (z_i + tz)``, restricted to a translation and minimised robustly.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..robust import nmad, tukey_loss
from ..surface import SurfaceSampler


@dataclass(frozen=True)
class TranslationFit:
    translation: tuple[float, float, float]
    iterations: int
    converged: bool
    n_used: int
    sigma0: float


def height_offset(xyz: np.ndarray, sampler: SurfaceSampler, shift_xy: np.ndarray) -> float:
    """Median of ``Z_ref(x + t) - z`` over the points that land on valid reference cells."""
    z, ok = sampler.sample(xyz[:, 0] + shift_xy[0], xyz[:, 1] + shift_xy[1])
    if not ok.any():
        return float("nan")
    return float(np.median(z[ok] - xyz[ok, 2]))


EDGE_MARGIN_CELLS = 8  # of the surface grid (an eighth of a tie cell each: one tie cell)
MIN_KEPT = 0.7  # a pose must keep this share of the starting points on the surface


@dataclass(frozen=True)
class SurfaceFit:
    params: np.ndarray
    tz: float  # profiled height offset
    sigma0: float  # NMAD of the residuals at the optimum
    n_used: int
    iterations: int
    converged: bool


def fit_to_surface(
    place: Callable[[np.ndarray], np.ndarray],
    sampler: SurfaceSampler,
    initial: np.ndarray,
    steps: np.ndarray,
    *,
    tol_fraction: float = 1 / 256,
    max_iterations: int = 600,
) -> SurfaceFit:
    """Minimise a robust loss of vertical distances of placed points to the surface.

    ``place(params)`` returns the points ``(N, 3)`` in surface coordinates without the height
    offset; the offset is profiled out as ``tz = median(Z(x, y) - z)`` and the loss is
    the mean of ``rho((Z - z - tz) / s)`` with Tukey's bounded ``rho`` and a fixed scale ``s``
    (NMAD at the start), so canopy points and blunders cannot pull the answer. A compass (pattern) search
    minimises it: derivative-free, hence indifferent to the noisy gradients of a gridded surface.
    It starts with ``steps`` per parameter, halves them when no move helps, and stops when they
    are below ``tol_fraction`` of the start. Points count at a pose when they lie at least
    :data:`EDGE_MARGIN_CELLS` inside the surface there; a pose that loses more than
    ``1 - MIN_KEPT`` of the starting points is refused.
    """
    p0 = np.asarray(initial, dtype=np.float64)
    steps = np.asarray(steps, dtype=np.float64).copy()
    stop = steps * tol_fraction

    # only points well inside the surface count, judged at each evaluated pose: a fixed set
    # would penalise moves that push points out but not moves that pull others in, which biases
    # scale and shift (a shrinking block keeps all its points); the loss is a mean over the
    # points that count, so neither direction gains by changing how many there are
    inner = sampler.inner(EDGE_MARGIN_CELLS)

    def residuals(params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pts = place(params)
        z, deep = sampler.sample(pts[:, 0], pts[:, 1], within=inner)
        return z - pts[:, 2], deep

    r0, use = residuals(p0)
    n0 = int(use.sum())
    if n0 < 10:
        return SurfaceFit(p0, float("nan"), float("nan"), n0, 0, False)
    scale = max(nmad(r0[use]), 1e-6 * max(1.0, float(np.abs(r0[use]).max())))

    def loss(params: np.ndarray) -> float:
        r, good = residuals(params)
        if good.sum() < max(10, MIN_KEPT * n0):
            return np.inf
        d = r[good] - np.median(r[good])
        return float(tukey_loss(d, scale).mean())

    p, best = p0.copy(), loss(p0)
    it = 0
    while np.any(steps >= stop) and it < max_iterations:
        it += 1
        moved = False
        for i in np.flatnonzero(steps >= stop):
            for sign in (1.0, -1.0):
                trial = p.copy()
                trial[i] += sign * steps[i]
                value = loss(trial)
                if value < best:
                    p, best, moved = trial, value, True
                    break
        if not moved:
            steps = steps / 2
    r, good = residuals(p)
    tz = float(np.median(r[good]))
    return SurfaceFit(p, tz, nmad(r[good] - tz), int(good.sum()), it, not np.any(steps >= stop))


def refine_translation(
    xyz: np.ndarray,
    sampler: SurfaceSampler,
    initial: np.ndarray,
    *,
    search_radius: float | None = None,
) -> TranslationFit:
    """Refine a horizontal shift (and the height offset) of points against the surface.

    Steps start at half the ``search_radius`` (default one cell of the surface); a result that
    ends on that radius is reported as not converged.
    """
    t0 = np.asarray(initial, dtype=np.float64)[:2]
    radius = sampler.grid.spec.cell_size if search_radius is None else search_radius
    fit = fit_to_surface(lambda t: xyz + [t[0], t[1], 0.0], sampler, t0,
                         np.array([radius / 2, radius / 2]), tol_fraction=1 / 256)
    inside = np.hypot(*(fit.params - t0)) <= radius
    return TranslationFit((float(fit.params[0]), float(fit.params[1]), fit.tz), fit.iterations,
                          fit.converged and inside, fit.n_used, fit.sigma0)
