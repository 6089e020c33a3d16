"""Robust least-squares estimation of a 7-parameter similarity (Helmert) from surface distances.

The one home of the fine stage's solver. Each observation is a signed distance ``r_i(q_i)`` of a
moving point ``q_i`` (reference frame, local coordinates) to the reference surface, with its
gradient ``g_i = dr_i/dq_i``: for the vertical distance to a DSM ``r = z - Z(x, y)``,
``g = (-Z_x, -Z_y, 1)``; for the normal distance to a plane through ``c`` with unit normal ``n``,
``r = n . (q - c)``, ``g = n``. The increment of the similarity about the block centroid ``c0``,

    q' = c0 + (1 + ds) R(omega, phi, kappa) (q - c0) + t,

is linear to first order in ``theta = (ds, omega, phi, kappa, tx, ty, tz)``:
``dq = ds q_c + [omega, phi, kappa] x q_c + t`` with ``q_c = q - c0``, so the design matrix row is
``A_i = g_i^T [q_c, e_x x q_c, e_y x q_c, e_z x q_c, I]`` and the normal equations
``(A^T P A) theta = -A^T P r`` (least squares surface matching: Gruen & Akca 2005, ISPRS J. 59(3),
eq. 8-11, with the distance gradients of Rosenholm & Torlegard 1988 for vertical distances).

Weights are robust (iteratively reweighted): Huber for the first iterations, Tukey's biweight
after, both on residuals scaled by their NMAD. The precision is ``sigma0^2 (A^T P A)^-1`` at
convergence, or the delete-one-group jackknife's where that is larger (:func:`jackknife_sd`):
errors correlated in space (:func:`spatial_blocks`) or shared by one kind of surface (its slope,
aspect and roughness, :func:`surface_classes`, and its bend, where the observer tells it). A
parameter the data cannot determine (horizontal shift on flat ground, heading on a featureless
plane) is detected by its standard deviation, converted to a displacement at the edge of the
block, and held at its starting value.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..robust import nmad
from ..transform import Transform, rotation_matrix

PARAMETERS = ("scale", "omega", "phi", "kappa", "tx", "ty", "tz")
HUBER_K, TUKEY_C = 1.345, 4.685  # in units of the residual scale (95 % efficiency each)
HUBER_ITERATIONS = 3
# a pose the iteration returns to after this many steps closes a cycle (:func:`_in_cycle`): the
# cycles seen on the verdict benchmark's development half were of 2 and 4 steps
CYCLE_LAGS = (2, 3, 4)

# observe(q) -> (r, g, ok): distances (N,), their gradients (N, 3), and which points have one.
# An observer may also have ``surface_class(q) -> (N,) int``: groups of observations whose
# errors may share a bias (see :func:`jackknife_sd`; e.g. ``NearestPlanes.surface_class``)
Observer = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class HelmertFit:
    """The increment ``T`` (local reference frame) and what is known about it."""

    T: Transform  # applies to points already placed by the coarse stage (local coordinates)
    centre: np.ndarray  # the block centroid the increment turns and scales about
    sigma: np.ndarray  # standard deviation of each parameter (nan where held)
    held: tuple[str, ...]  # parameters the data could not determine
    sigma0: float  # a posteriori standard deviation of unit weight (distance units)
    n_used: int  # observations with weight above 0.5 at the end
    n_observed: int
    weights: np.ndarray  # final robust weight per point (0 for points without an observation)
    residuals: np.ndarray  # final distances (nan for points without an observation)
    iterations: int
    converged: bool
    # how far the last few iterates lie from the answer (the largest displacement of a point of
    # the block between the answer and the poses of the last ``CYCLE_LAGS[-1]`` steps): an
    # iteration that ends at its limit stepping back and forth has settled to within this;
    # inf where the iteration broke off (too few observations, a runaway step)
    wander: float = math.inf


def design_matrix(q: np.ndarray, g: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Rows ``g^T [q_c, e_x x q_c, e_y x q_c, e_z x q_c, I]`` (see the module docstring)."""
    qc = q - centre
    gx, gy, gz = g[:, 0], g[:, 1], g[:, 2]
    x, y, z = qc[:, 0], qc[:, 1], qc[:, 2]
    return np.column_stack([
        gx * x + gy * y + gz * z,  # scale
        -gy * z + gz * y,  # omega: e_x x q = (0, -z, y)
        gx * z - gz * x,  # phi: e_y x q = (z, 0, -x)
        -gx * y + gy * x,  # kappa: e_z x q = (-y, x, 0)
        gx, gy, gz,
    ])


def increment(theta: np.ndarray, centre: np.ndarray) -> Transform:
    """The similarity ``q' = c0 + (1 + ds) R (q - c0) + t`` of a parameter vector."""
    ds, omega, phi, kappa, tx, ty, tz = theta
    M = np.eye(4)
    M[:3, :3] = (1.0 + ds) * rotation_matrix(omega, phi, kappa)
    M[:3, 3] = centre + np.array([tx, ty, tz]) - M[:3, :3] @ centre
    return Transform(M)


def robust_weights(u: np.ndarray, *, tukey: bool) -> np.ndarray:
    """Weights of standardized residuals ``u``: Huber (``k = 1.345``) or Tukey (``c = 4.685``)."""
    a = np.abs(u)
    if tukey:
        return np.where(a < TUKEY_C, (1 - (a / TUKEY_C) ** 2) ** 2, 0.0)
    return np.where(a <= HUBER_K, 1.0, HUBER_K / np.maximum(a, 1e-300))


def jackknife_sd(A: np.ndarray, w: np.ndarray, r: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Standard deviations of the weighted least-squares step ``(A^T W A)^-1 A^T W (-r)`` by the
    delete-one-group jackknife over the groups of observations that ``labels`` names.

    The formal covariance ``sigma0^2 N^-1`` assumes independent distances. Where the lidar's
    surface misses the tie points' one in places (canopy gaps, roof edges, steep slopes), the
    errors are correlated, in space or by the kind of surface, and the formal precision is too
    optimistic. Leaving out one group at a time and solving the normal equations of the rest
    measures that (Efron & Stein 1981; for spatial blocks, Kunsch 1989). Groups differ in size
    (a kind of surface may hold most of the points), so the estimator is that for unequal groups
    (Busing, Meijer & van der Leeden 1999, eq. 5-7): with ``h_j = n / m_j`` (``m_j`` the weight
    of group ``j``, ``n`` the total), pseudo-values ``t_j = h_j d - (h_j - 1) d_(-j)``, their
    mean-corrected estimate ``d_J = G d - sum (1 - 1/h_j) d_(-j)``, and
    ``var = 1/G sum (t_j - d_J)^2 / (h_j - 1)``; for equal groups it is the classic
    ``(G - 1) / G sum (d_(-j) - mean)^2``.
    """
    Aw = A * w[:, None]
    N, b = Aw.T @ A, -Aw.T @ r
    total = float(w.sum())
    steps, h = [], []
    for k in np.unique(labels):
        rows = labels == k
        m = float(w[rows].sum())
        if m <= 0 or m >= total:
            continue
        Nk = N - Aw[rows].T @ A[rows]
        bk = b + Aw[rows].T @ r[rows]
        try:
            steps.append(np.linalg.solve(Nk, bk))
        except np.linalg.LinAlgError:
            return np.full(A.shape[1], np.inf)
        h.append(total / m)
    if len(steps) < 3:
        return np.zeros(A.shape[1])
    try:
        d = np.linalg.solve(N, b)
    except np.linalg.LinAlgError:
        return np.full(A.shape[1], np.inf)
    d_j, h_j = np.array(steps), np.array(h)[:, None]
    G = len(d_j)
    pseudo = h_j * d - (h_j - 1) * d_j
    d_J = G * d - np.sum((1 - 1 / h_j) * d_j, axis=0)
    return np.sqrt(np.sum((pseudo - d_J) ** 2 / (h_j - 1), axis=0) / G)


def spatial_blocks(xy: np.ndarray, *, blocks_per_side: int = 4) -> np.ndarray:
    """Labels of a ``blocks_per_side`` squared grid over the points' positions."""
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    cell = np.floor((xy - lo) / np.maximum(hi - lo, 1e-12) * blocks_per_side).clip(
        0, blocks_per_side - 1).astype(int)
    return cell[:, 0] * blocks_per_side + cell[:, 1]


def surface_classes(g: np.ndarray) -> np.ndarray:
    """Labels by the kind of surface an observation sees: gently sloped (within 20 degrees of
    level) or facing one of four quadrants, each split at the median of the row's weight
    ``|g|`` (the roughness weight of :func:`~tiereg.fine.icp.nearest_plane_observer`; all equal
    for the vertical model). A bias that belongs to one kind of surface (tie points below canopy,
    at one side of the roofs) makes these groups disagree."""
    norm = np.linalg.norm(g, axis=1)
    n = g / np.maximum(norm, 1e-300)[:, None]
    quadrant = (np.floor((np.arctan2(n[:, 1], n[:, 0]) + np.pi / 4) / (np.pi / 2)) % 4).astype(int)
    orient = np.where(np.abs(n[:, 2]) >= np.cos(np.radians(20.0)), 0, 1 + quadrant)
    rough = (norm < np.median(norm)).astype(int)
    return orient * 2 + rough


def solve_helmert(
    q0: np.ndarray,
    observe: Observer,
    *,
    hold_displacement: float,
    fixed: tuple[str, ...] = (),
    max_iterations: int = 40,
    tol_displacement: float | None = None,
    biweight_from_start: bool = False,
) -> HelmertFit:
    """Estimate the similarity increment that brings the points ``q0`` onto the surface.

    ``hold_displacement`` (distance units): a parameter whose standard deviation moves the block
    (its edge, for scale and rotations) by more than this is not determined by the data and is held.
    ``fixed`` parameters are held from the start. Iterations stop when the increment moves no point
    of the block by more than ``tol_displacement`` (default ``hold_displacement / 1000``), or
    when they come back to a pose of a few steps before, each step within its own precision
    (:func:`_in_cycle`). ``biweight_from_start``: where the fit continues an earlier one from its
    answer (the same points, the lidar selected again), the biweight from the first iteration
    at the scale of the residuals there, without the Huber phase that would first pull the pose
    towards the outliers again.
    """
    q0 = np.asarray(q0, dtype=np.float64)
    centre, lever = _levers(q0)
    tol = hold_displacement / 1000 if tol_displacement is None else tol_displacement
    held = [PARAMETERS.index(p) for p in fixed]
    T = Transform.identity()
    huber_iterations = 0 if biweight_from_start else HUBER_ITERATIONS
    scale_r = float("nan")
    converged = False
    it = 0
    w_all, r_all = np.zeros(len(q0)), np.full(len(q0), np.nan)
    N, N_free = np.eye(7), list(range(7))
    sigma0 = float("nan")
    last = None  # the final iteration's scaled design rows, weights, distances and positions
    recent: list[tuple[Transform, float]] = []  # the latest poses and the steps that made them
    wander = math.inf  # a fit that broke off (too few observations, a runaway) settled nowhere
    for it in range(1, max_iterations + 1):
        q = T.apply(q0)
        r, g, ok = observe(q)
        ok = ok & np.isfinite(r)
        if ok.sum() < 10:
            break
        A = design_matrix(q[ok], g[ok], centre)
        rr = r[ok]
        if it <= huber_iterations or not np.isfinite(scale_r):
            scale_r = max(nmad(rr), 1e-12)
        if it == huber_iterations + 1:  # holds made far from the answer were provisional
            held = [PARAMETERS.index(p) for p in fixed]
        w = _weights(rr / scale_r, tukey=it > huber_iterations)
        # parameters the data cannot determine are held (``held`` grows)
        Af, N, N_free, step_scaled, sigma0, sd_step = _normal_step(
            A, w, rr, lever, held, scale_r=scale_r, hold_displacement=hold_displacement)
        step = np.zeros(7)
        step[N_free] = step_scaled / lever[N_free]
        if not np.all(np.isfinite(step_scaled)) or step[0] <= -0.5:
            break  # a step that would halve the block or worse is a runaway, not a fit
        last = (Af, w, rr, q[ok], g[ok])
        dT = increment(step, centre)
        T = dT @ T
        w_all, r_all = _scattered(ok, w, 0.0), _scattered(ok, rr, np.nan)
        moved = float(np.max(np.abs(step_scaled)))  # the step's largest displacement
        recent = [*recent[-CYCLE_LAGS[-1]:], (T, moved)]
        if it > huber_iterations and (moved < tol
                                      or _in_cycle(recent, q0, tol=tol, sd_step=sd_step)):
            converged = True
            wander = _wander(recent, q0)
            break
    else:  # the iteration limit
        wander = _wander(recent, q0)
    sigma = _precision(N, N_free, sigma0, last, observe, lever)
    return HelmertFit(T, centre, sigma, tuple(PARAMETERS[i] for i in sorted(held)), sigma0,
                      int((w_all > 0.5).sum()), int(np.isfinite(r_all).sum()), w_all, r_all, it,
                      converged, wander)


def _levers(q0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The block's centre, and its displacement per unit of each parameter: the RMS radius in
    plan for scale and rotations, 1 for the shifts."""
    centre = q0.mean(axis=0)
    extent = q0 - centre
    radius_xy = float(np.sqrt(np.mean(extent[:, 0] ** 2 + extent[:, 1] ** 2))) or 1.0
    return centre, np.array([radius_xy, radius_xy, radius_xy, radius_xy, 1.0, 1.0, 1.0])


def _weights(u: np.ndarray, *, tukey: bool) -> np.ndarray:
    """Robust weights of the standardised residuals ``u``: the biweight where ``tukey``, unless
    it leaves fewer than 10 observations (everything beyond its reach: keep descending with
    Huber's)."""
    w = robust_weights(u, tukey=tukey)
    return robust_weights(u, tukey=False) if tukey and w.sum() < 10 else w


def _scattered(ok: np.ndarray, values: np.ndarray, fill: float) -> np.ndarray:
    """``values`` at the positions where ``ok`` is set, ``fill`` elsewhere."""
    out = np.full(len(ok), fill)
    out[np.flatnonzero(ok)] = values
    return out


def _wander(recent: list[tuple[Transform, float]], q0: np.ndarray) -> float:
    """The largest displacement of a point of ``q0`` between the last pose of ``recent`` and
    each earlier one (0 with fewer than two)."""
    if len(recent) < 2:
        return 0.0
    return max(_apart(recent[-1][0], T, q0) for T, _ in recent[:-1])


def _apart(A: Transform, B: Transform, q0: np.ndarray) -> float:
    """The largest displacement of a coordinate of a point of ``q0`` between poses A and B."""
    return float(np.max(np.abs(A.apply(q0) - B.apply(q0))))


def _in_cycle(recent: list[tuple[Transform, float]], q0: np.ndarray, *, tol: float,
              sd_step: float) -> bool:
    """Whether the iteration has closed a cycle within the fit's own precision: the pose is back
    (every point within ``tol``) where it was 2 to 4 steps ago, and none of the steps since moved
    the block by more than ``sd_step``, one standard deviation of the step. The observers are
    piecewise (the nearest lidar point, a bilinear cell, a point crossing the biweight's reach
    changes between steps), so a settled fit may step back and forth between a few poses a
    centimetre apart for ever; any of them is the answer to within its precision."""
    T_now = recent[-1][0]
    for lag in CYCLE_LAGS:
        if len(recent) <= lag:
            break
        back = _apart(T_now, recent[-1 - lag][0], q0)
        if back < tol and max(step for _, step in recent[-lag:]) <= sd_step:
            return True
    return False


def _normal_step(A: np.ndarray, w: np.ndarray, rr: np.ndarray, lever: np.ndarray,
                 held: list[int], *, scale_r: float, hold_displacement: float):
    """One weighted Gauss-Newton step with the unknowns as displacements of the block
    (``u = theta * lever``: conditioned normals). Parameters the data cannot determine (a
    standard deviation that moves the block by more than ``hold_displacement``) are held, the
    worst first, one at a time, and the step solved again; ``held`` grows in place. Returns the
    scaled design rows, the normals and their free parameters, the scaled step, sigma0 and the
    largest standard deviation of the step's displacement of the block."""
    while True:
        free = [i for i in range(7) if i not in held]
        Af = A[:, free] / lever[free]
        N = (Af * w[:, None]).T @ Af
        b = -(Af * w[:, None]).T @ rr
        step_scaled = np.linalg.lstsq(N, b, rcond=None)[0]
        dof = max(float(w.sum()) - len(free), 1.0)
        sigma0 = math.sqrt(float(np.sum(w * rr**2)) / dof)
        # a vanishing ridge keeps singular normals invertible (their variances become huge); the
        # spread of the residuals, not their offset, is the noise level here
        ridge = 1e-12 * max(float(np.trace(N)) / len(free), 1e-300)
        cov = min(sigma0, scale_r) ** 2 * np.linalg.inv(N + ridge * np.eye(len(free)))
        sd_disp = np.sqrt(np.maximum(np.diag(cov), 0.0))
        if sd_disp.max() > hold_displacement and len(free) > 1:
            held.append(free[int(np.argmax(sd_disp))])
            continue
        return Af, N, free, step_scaled, sigma0, float(sd_disp.max())


def _precision(N: np.ndarray, N_free: list[int], sigma0: float, last, observe: Observer,
               lever: np.ndarray) -> np.ndarray:
    """Standard deviations of the 7 parameters (NaN where held): from the normals, and no
    smaller than the jackknife over spatial blocks and surface classes of the last completed
    step's rows (errors correlated in space or by surface count too)."""
    sigma = np.full(7, np.nan)
    if not N_free or not np.isfinite(sigma0):
        return sigma
    try:
        cov = sigma0**2 * np.linalg.inv(N)
        sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
        if last is not None and last[0].shape[1] == len(N_free):
            Af, w, rr, q_ok, g = last
            groups = [spatial_blocks(q_ok[:, :2]), surface_classes(g)]
            if hasattr(observe, "surface_class"):
                groups.append(observe.surface_class(q_ok))
            for labels in groups:
                sd = np.maximum(sd, jackknife_sd(Af, w, rr, labels))
        sigma[N_free] = sd / lever[N_free]
    except np.linalg.LinAlgError:
        pass
    return sigma
