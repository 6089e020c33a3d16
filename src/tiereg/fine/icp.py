"""Iterative closest point observation models, for comparison and for dense moving sets.

Both pair each moving point with its nearest lidar point anew at every iteration and feed the one
solver (:func:`~tiereg.fine.solver.solve_helmert`), whose robust weights make them trimmed ICP:

* ``icp-point`` (Besl & McKay 1992): the distance to the nearest lidar point,
  ``r = |q - p|``, ``g = (q - p) / |q - p|``; its least squares are those of the point-to-point
  sum of squares.
* ``icp-plane`` (Chen & Medioni 1992): the distance along the normal of the lidar's local plane at
  the nearest point, ``r = n . (q - p)``, ``g = n``; every patch counts, planar or not.

Unlike ``lsm`` they do not know that the tie points sit on the visible surface between the lidar
points: point-to-point is biased by the lidar's spacing, point-to-plane by edges and canopy.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .solver import Observer

NORMAL_POINTS = 12  # lidar neighbours for a normal


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


def plane_observer_icp(lidar: np.ndarray) -> Observer:
    """``r = n . (q - p)``, ``g = n``: ``p`` the nearest lidar point in 3-D, ``n`` the normal of
    its :data:`NORMAL_POINTS` neighbours (computed once per lidar point, when first needed)."""
    tree = cKDTree(lidar)
    normals = np.full((len(lidar), 3), np.nan)

    def normal_of(idx: np.ndarray) -> np.ndarray:
        todo = np.unique(idx[np.isnan(normals[idx, 0])])
        if len(todo):
            _, nb = tree.query(lidar[todo], k=min(NORMAL_POINTS, len(lidar)))
            pts = lidar[nb]
            d = pts - pts.mean(axis=1, keepdims=True)
            _, vecs = np.linalg.eigh(np.einsum("mki,mkj->mij", d, d))
            n = vecs[:, :, 0]
            normals[todo] = n * np.where(n[:, 2] < 0, -1.0, 1.0)[:, None]
        return normals[idx]

    def observe(q: np.ndarray):
        _, idx = tree.query(q)
        n = normal_of(idx)
        return np.einsum("mi,mi->m", n, q - lidar[idx]), n, np.ones(len(q), bool)

    return observe
