"""Nearest-point observation models: the lidar's local surface at the nearest first return.

All pair each moving point with its nearest lidar point (3-D) anew at every iteration and feed the
one solver (:func:`~tiereg.fine.solver.solve_helmert`), whose robust weights trim them:

* ``icp-point`` (Besl & McKay 1992): the distance to the nearest lidar point,
  ``r = |q - p|``, ``g = (q - p) / |q - p|``; its least squares are those of the point-to-point
  sum of squares. Biased by the lidar's spacing: a tie point lies between lidar points.
* ``icp-plane`` (Chen & Medioni 1992): the distance along the normal of the lidar's local plane at
  the nearest point, ``r = n . (q - p)``, ``g = n``, every patch with equal weight.
* the surface model of ``lsm`` (:func:`nearest_plane_observer` with ``weighted=True``): the same
  normal distance, in the sense of least-squares 3-D surface matching (LS3D: Gruen & Akca 2005,
  ISPRS J. 59(3), the correspondence along the local surface normal), with a stochastic model for
  the patch. A patch's roughness ``rho`` (the standard deviation of its points off their plane:
  canopy, edges, rubble) adds to the tie point's own noise ``sigma``, so the observation's weight is
  ``sigma^2 / (sigma^2 + rho^2)``, with ``sigma`` the robust spread of the current distances.

The distance is measured to the nearest lidar point ``p`` itself, not to the patch centroid: on a
curved patch (a crown, a ridge) the centroid lies off the surface and biases the heights.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from ..robust import nmad
from ..surface import fit_planes
from .solver import Observer

NORMAL_POINTS = 12  # lidar neighbours of a normal (icp-plane)
BEND_RAD = 0.15  # a patch turning by more than this across its radius is curved (9 degrees)
# the tie points on vegetation (:func:`crown_lift`): at least this many estimate their lift, on
# patches whose normal is within 60 degrees of the vertical
MIN_CROWNS = 10
STEADY_NZ = 0.5
# a lift is taken off only where it is positive (an image sees the crowns' tops, the first
# returns lie below them, never above) by at least this many standard errors (one-sided, 97.7 %)
LIFT_SE = 2.0


def point_observer(lidar: np.ndarray) -> Observer:
    """``r = |q - p|``, ``g = (q - p) / r`` with ``p`` the nearest lidar point in 3-D."""
    tree = cKDTree(lidar)

    def observe(q: np.ndarray):
        dist, idx = tree.query(q)
        d = q - lidar[idx]
        ok = dist > 1e-9
        g = np.zeros_like(q)
        g[ok] = d[ok] / dist[ok, None]
        return dist, g, ok

    return observe


class NearestPlanes:
    """The observation model ``r = n . (q - p)``, ``g = n``: ``p`` the nearest lidar point in 3-D,
    ``n`` the upward normal of its ``neighbours`` nearest points (computed once per lidar point,
    when first needed). Call it as an :data:`~tiereg.fine.solver.Observer`.

    ``weighted``: rows scaled by ``1 / sqrt(1 + (rho / sigma)^2)`` (see the module docstring), so
    that the solver's standardized residuals are those of the weighted problem.

    ``reach`` (distance units): a point whose nearest lidar point lies farther than this in plan
    has no observation. Where the lidar covers only part of the block, the tie points beyond its
    edge would otherwise measure their distance to a plane tens of metres away: at half overlap
    half the observations, more than any robust weight can trim.

    ``solid`` (one flag per lidar point): where given, the tie points whose nearest lidar point
    is not on a solid surface (vegetation: :func:`~tiereg.reference.open_ground_mask`) sit a
    common height, the crowns' lift, above it: an image sees the crowns' tops while a lidar's
    first returns lie anywhere down the crowns. Where a good share of the block is on trees that
    shared bias pulled the block down by decimetres, more than any robust weight sets aside.
    :meth:`fix_lift` measures the lift where the points are at the start of a solve, against the
    open ground's own distances, and where the data show one (above the open ground by
    :data:`LIFT_SE` standard errors) the calls that follow take it off those tie points'
    distances: they still place and turn the block in plan, and the open ground alone sets its
    height. Where the crowns' tie points do sit on the lidar, the lift is not taken off and they
    count in height like the others. Measured against the open ground, the lift does not depend
    on the block's height, so each solve keeps one value (re-estimated at every iteration it made
    the fit cycle) and the fine stage's settling passes, each with a new observer, bring it up
    to date.

    :meth:`surface_class` tells the solver's jackknife what kind of surface each observation sees:
    the bend of the patch, from the osculating paraboloid at ``p``, ``h(u) = -kappa |u|^2 / 2``
    fitted to its neighbours (``kappa = -2 sum h_j / sum |u_j|^2``, ``h_j`` their heights over
    the plane at ``p`` and ``u_j`` their offsets along it). Tie points in the creases between
    crowns or at the foot of a wall lie below the plane a patch of lidar 1 m apart gives them,
    those on crowns and ridges above it; a bias of one kind shows as disagreement between them.
    """

    def __init__(self, lidar: np.ndarray, *, neighbours: int = NORMAL_POINTS,
                 weighted: bool = False, reach: float = np.inf,
                 solid: np.ndarray | None = None) -> None:
        self.lidar, self.weighted, self.reach, self.solid = lidar, weighted, reach, solid
        self.lift = math.nan
        self._tree = cKDTree(lidar)
        self._k = min(neighbours, len(lidar))
        self._normal = np.full((len(lidar), 3), np.nan)
        self._roughness = np.full(len(lidar), np.nan)
        self._turn = np.zeros(len(lidar))  # kappa times the patch radius (radians)

    def _patch(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        todo = np.unique(idx[np.isnan(self._normal[idx, 0])])
        if len(todo):
            _, nb = self._tree.query(self.lidar[todo], k=self._k)
            patches = self.lidar[nb]
            _, n, self._roughness[todo] = fit_planes(patches)
            self._normal[todo] = n
            d = patches - self.lidar[todo][:, None, :]
            h = np.einsum("mki,mi->mk", d, n)
            u2 = np.maximum(np.sum(d**2, axis=2) - h**2, 0.0).sum(axis=1)
            kappa = -2.0 * h.sum(axis=1) / np.maximum(u2, 1e-300)
            self._turn[todo] = kappa * np.sqrt(u2 / max(self._k - 1, 1))
        return self._normal[idx], self._roughness[idx], self._turn[idx]

    def _distances(self, q: np.ndarray) -> tuple[np.ndarray, ...]:
        """The nearest lidar point of each of ``q``, its patch's normal and roughness, the
        signed distance to the patch and whether the point lies within ``reach`` in plan."""
        _, idx = self._tree.query(q)
        n, rho, _ = self._patch(idx)
        d = q - self.lidar[idx]
        return idx, n, rho, np.einsum("mi,mi->m", n, d), np.hypot(d[:, 0], d[:, 1]) <= self.reach

    def __call__(self, q: np.ndarray):
        idx, n, rho, r, ok = self._distances(q)
        if self.solid is not None and math.isfinite(self.lift):
            r = r - self.lift * n[:, 2] * (ok & ~self.solid[idx])
        if self.weighted:
            sigma = max(nmad(r[ok]), 1e-12) if ok.any() else 1.0
            s = 1.0 / np.sqrt(1.0 + (rho / sigma) ** 2)
            r, n = r * s, n * s[:, None]
        return r, n, ok

    def fix_lift(self, q: np.ndarray) -> float:
        """Measure the crowns' lift at ``q``: the height of the tie points on vegetation above
        the lidar less that of those on open ground (:func:`crown_lift` of each), and keep it
        for the calls that follow where the data show it (:data:`LIFT_SE`); NaN, nothing taken
        off, where they do not, without ``solid`` or with too few tie points on either."""
        self.lift = math.nan
        if self.solid is None:
            return self.lift
        idx, n, _, r, near = self._distances(q)
        crown, ground = near & ~self.solid[idx], near & self.solid[idx]
        lift = crown_lift(r, n, crown) - crown_lift(r, n, ground)
        if lift > LIFT_SE * (lift_se(r, n, crown) ** 2 + lift_se(r, n, ground) ** 2) ** 0.5:
            self.lift = lift
        return self.lift

    def nearest(self, q: np.ndarray) -> np.ndarray:
        """The index of the lidar point nearest each of ``q`` in 3-D (the one it observes)."""
        return self._tree.query(q)[1]

    def surface_class(self, q: np.ndarray) -> np.ndarray:
        """0 where the patch at the nearest lidar point is concave (it turns up by more than
        :data:`BEND_RAD` across its radius), 2 where convex, 1 where it is about flat."""
        _, idx = self._tree.query(q)
        turn = self._patch(idx)[2]
        return np.digitize(turn, (-BEND_RAD, BEND_RAD))


def crown_lift(r: np.ndarray, n: np.ndarray, crown: np.ndarray) -> float:
    """The height of the points ``crown`` above the lidar's surface: the median of their
    vertical distances ``r / n_z`` over patches less steep than :data:`STEADY_NZ` (on steeper
    ones a small error in plan is a large one in height); NaN with fewer than
    :data:`MIN_CROWNS` of them."""
    v = _vertical(r, n, crown)
    return float(np.median(v)) if len(v) >= MIN_CROWNS else math.nan


def lift_se(r: np.ndarray, n: np.ndarray, crown: np.ndarray) -> float:
    """The standard error of :func:`crown_lift`: ``1.2533 NMAD / sqrt(m)`` over its ``m``
    vertical distances (the median's, at normal errors); inf where it has none."""
    v = _vertical(r, n, crown)
    return 1.2533 * nmad(v) / math.sqrt(len(v)) if len(v) >= MIN_CROWNS else math.inf


def _vertical(r: np.ndarray, n: np.ndarray, crown: np.ndarray) -> np.ndarray:
    """The vertical distances ``r / n_z`` of the points ``crown`` on patches less steep than
    :data:`STEADY_NZ`."""
    steady = crown & (n[:, 2] > STEADY_NZ)
    return r[steady] / n[steady, 2]


def nearest_plane_observer(lidar: np.ndarray, *, neighbours: int = NORMAL_POINTS,
                           weighted: bool = False, reach: float = np.inf,
                           solid: np.ndarray | None = None) -> NearestPlanes:
    """The nearest-plane observation model (:class:`NearestPlanes`)."""
    return NearestPlanes(lidar, neighbours=neighbours, weighted=weighted, reach=reach,
                         solid=solid)


def plane_observer_icp(lidar: np.ndarray) -> Observer:
    """The classic point-to-plane ICP observation model (equal weights)."""
    return nearest_plane_observer(lidar, neighbours=NORMAL_POINTS, weighted=False)
