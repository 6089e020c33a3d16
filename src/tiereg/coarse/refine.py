"""Sub-cell refinement of a horizontal shift and height offset against a reference surface.

Vertical distances of the points to the surface (least z-difference, Rosenholm & Torlegard 1988),
``r_i = Z(x_i + tx, y_i + ty) - (z_i + tz)``, restricted to a translation and minimised robustly.
"""

from __future__ import annotations

from collections.abc import Callable, Generator
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

    ``place(params)`` takes ``K`` parameter rows ``(K, P)`` and returns the points each places,
    ``(K, N, 3)``, in surface coordinates without the height offset; the offset is profiled
    out as ``tz = median(Z(x, y) - z)`` and the loss is the mean of ``rho((Z - z - tz) / s)``
    with Tukey's bounded ``rho`` and a fixed scale ``s`` (NMAD at the start), so canopy points
    and blunders cannot pull the answer. A compass (pattern) search minimises it:
    derivative-free, hence indifferent to the noisy gradients of a gridded surface. It starts
    with ``steps`` per parameter, halves them when no move helps, and stops when they are below
    ``tol_fraction`` of the start. Points count at a pose when they lie at least
    :data:`EDGE_MARGIN_CELLS` inside the surface there; a pose that loses more than
    ``1 - MIN_KEPT`` of the starting points is refused.
    """
    return fit_to_surface_many(place, sampler, [initial], steps, tol_fraction=tol_fraction,
                               max_iterations=max_iterations)[0]


def fit_to_surface_many(
    place: Callable[[np.ndarray], np.ndarray],
    sampler: SurfaceSampler,
    initials: list[np.ndarray],
    steps: np.ndarray,
    *,
    tol_fraction: float = 1 / 256,
    max_iterations: int = 600,
) -> list[SurfaceFit]:
    """:func:`fit_to_surface` from each of several starts: the same fits as one after another,
    run in lock-step so that each round places and samples once the next trial poses of every
    unfinished start (a fit is thousands of small evaluations, whose cost is mostly the
    interpreter's per-call overhead)."""
    steps = np.asarray(steps, dtype=np.float64)
    # only points well inside the surface count, judged at each evaluated pose: a fixed set
    # would penalise moves that push points out but not moves that pull others in, which biases
    # scale and shift (a shrinking block keeps all its points); the loss is a mean over the
    # points that count, so neither direction gains by changing how many there are
    inner = sampler.inner(EDGE_MARGIN_CELLS)

    def residuals(params: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """``(K, N)`` residuals ``Z - z`` and whether each point counts, for ``K`` poses."""
        pts = place(np.stack(params))
        z, deep = sampler.sample(pts[..., 0].ravel(), pts[..., 1].ravel(), within=inner)
        return z.reshape(pts.shape[:2]) - pts[..., 2], deep.reshape(pts.shape[:2])

    p0 = [np.asarray(p, dtype=np.float64) for p in initials]
    r0, use0 = residuals(p0)
    n0 = use0.sum(axis=1)
    scale = np.array([max(nmad(r[u]), 1e-6 * max(1.0, float(np.abs(r[u]).max(initial=0.0))))
                      if k >= 10 else np.nan for r, u, k in zip(r0, use0, n0)])
    n_min = np.maximum(10, MIN_KEPT * n0)

    def losses(rows: list[int], params: list[np.ndarray]) -> np.ndarray:
        r, good = residuals(params)
        d = r - _masked_median(r, good)[:, None]
        value = np.where(good, tukey_loss(d, scale[rows, None]), 0.0).sum(axis=1)
        count = good.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(count >= n_min[rows], value / count, np.inf)

    live = [k for k in range(len(p0)) if n0[k] >= 10]
    searches, trials, ends = {}, {}, {}
    for k, value in zip(live, losses(live, [p0[k] for k in live]) if live else ()):
        searches[k] = _compass(p0[k], value, steps, steps * tol_fraction, max_iterations)
        trials[k] = _advance(searches[k], None, ends, k)
    while trials:
        rows = list(trials)
        counts = [len(trials[k]) for k in rows]
        values = losses([k for k, n in zip(rows, counts) for _ in range(n)],
                        [t for k in rows for t in trials[k]])
        for k, chunk in zip(rows, np.split(values, np.cumsum(counts)[:-1])):
            trials[k] = _advance(searches[k], chunk, ends, k)
            if trials[k] is None:
                del trials[k]

    fits: list[SurfaceFit] = [SurfaceFit(p, float("nan"), float("nan"), int(n), 0, False)
                              for p, n in zip(p0, n0)]
    if live:
        r, good = residuals([ends[k][0] for k in live])
        for k, rk, gk in zip(live, r, good):
            p, it, converged = ends[k]
            tz = float(np.median(rk[gk]))
            fits[k] = SurfaceFit(p, tz, nmad(rk[gk] - tz), int(gk.sum()), it, converged)
    return fits


def _compass(p: np.ndarray, best: float, steps: np.ndarray, stop: np.ndarray,
             max_iterations: int
             ) -> Generator[list[np.ndarray], np.ndarray, tuple[np.ndarray, int, bool]]:
    """The compass search of :func:`fit_to_surface`: yields trial poses, is sent their losses,
    and returns ``(pose, iterations, converged)``. Each parameter in turn moves by its step up,
    else down, where that lowers the loss; a round without a move halves the steps. The two
    trials of a parameter are evaluated together (the same search as one after the other)."""
    it = 0
    while np.any(steps >= stop) and it < max_iterations:
        it += 1
        moved = False
        for i in np.flatnonzero(steps >= stop):
            trials = [p.copy(), p.copy()]
            trials[0][i] += steps[i]
            trials[1][i] -= steps[i]
            values = yield trials
            for trial, value in zip(trials, values):
                if value < best:
                    p, best, moved = trial, float(value), True
                    break
        if not moved:
            steps = steps / 2
    return p, it, not np.any(steps >= stop)


def _advance(search: Generator, values: np.ndarray | None, ends: dict,
             key: int) -> list[np.ndarray] | None:
    """The next trial poses of a compass search (``None``, with its end kept in ``ends``, when
    it has finished)."""
    try:
        return next(search) if values is None else search.send(values)
    except StopIteration as end:
        ends[key] = end.value
        return None


def _masked_median(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The median of each row's values where ``mask`` is set (NaN for an empty row): the
    ``np.median`` of the row's kept values, for all rows in one sort."""
    count = mask.sum(axis=1)
    ordered = np.sort(np.where(mask, values, np.inf), axis=1)
    rows = np.arange(len(values))
    lo = ordered[rows, np.maximum((count - 1) // 2, 0)]
    hi = ordered[rows, np.maximum(count // 2, 0)]
    return np.where(count > 0, (lo + hi) / 2, np.nan)


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

    def place(t: np.ndarray) -> np.ndarray:  # (K, 2) shifts -> (K, N, 3)
        return xyz + np.column_stack([t, np.zeros(len(t))])[:, None, :]

    fit = fit_to_surface(place, sampler, t0, np.array([radius / 2, radius / 2]),
                         tol_fraction=1 / 256)
    inside = np.hypot(*(fit.params - t0)) <= radius
    return TranslationFit((float(fit.params[0]), float(fit.params[1]), fit.tz), fit.iterations,
                          fit.converged and inside, fit.n_used, fit.sigma0)
