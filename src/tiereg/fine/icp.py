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

import numpy as np
from scipy.spatial import cKDTree

from ..robust import nmad
from ..surface import fit_planes
from .solver import Observer

NORMAL_POINTS = 12  # lidar neighbours of a normal (icp-plane)


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


def nearest_plane_observer(lidar: np.ndarray, *, neighbours: int = NORMAL_POINTS,
                           weighted: bool = False) -> Observer:
    """``r = n . (q - p)``, ``g = n``: ``p`` the nearest lidar point in 3-D, ``n`` the upward
    normal of its ``neighbours`` nearest points (computed once per lidar point, when first needed).

    ``weighted``: rows scaled by ``1 / sqrt(1 + (rho / sigma)^2)`` (see the module docstring), so
    that the solver's standardized residuals are those of the weighted problem.
    """
    tree = cKDTree(lidar)
    k = min(neighbours, len(lidar))
    normals = np.full((len(lidar), 3), np.nan)
    roughness = np.full(len(lidar), np.nan)

    def patch_of(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        todo = np.unique(idx[np.isnan(normals[idx, 0])])
        if len(todo):
            _, nb = tree.query(lidar[todo], k=k)
            _, normals[todo], roughness[todo] = fit_planes(lidar[nb])
        return normals[idx], roughness[idx]

    def observe(q: np.ndarray):
        _, idx = tree.query(q)
        n, rho = patch_of(idx)
        r = np.einsum("mi,mi->m", n, q - lidar[idx])
        if weighted:
            sigma = max(nmad(r), 1e-12)
            s = 1.0 / np.sqrt(1.0 + (rho / sigma) ** 2)
            r, n = r * s, n * s[:, None]
        return r, n, np.ones(len(q), bool)

    return observe


def plane_observer_icp(lidar: np.ndarray) -> Observer:
    """The classic point-to-plane ICP observation model (equal weights)."""
    return nearest_plane_observer(lidar, neighbours=NORMAL_POINTS, weighted=False)
