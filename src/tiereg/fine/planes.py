"""Tie points matched to planar segments of the lidar (``--fine planes``).

Roofs, streets and flat ground are planes, and a plane fitted to many lidar points is known far
better than the 8-point patch of the ``lsm`` surface model. Around each tie point the lidar is
segmented into at most :data:`MAX_PLANES` planes by RANSAC (Fischler & Bolles 1981): the plane
through three of its points that the most neighbours lie on (within :data:`INLIER_SPACINGS` of
the lidar's spacing), refitted to those by principal axes, then the same among the points left (a
roof and the ground beside it). A plane counts when at least :data:`MIN_INLIERS` points lie on it
and it is not a wall.

The observation is the normal distance ``r = n . (q - c)``, ``g = n`` to the plane of the tie
point's neighbourhood that the tie point is nearest to, among those whose points reach within a
spacing of it in plan (chosen at the start of a pass, :class:`SegmentPlanes`), weighted like the
``lsm`` surface model by the plane's roughness (:mod:`tiereg.fine.icp`). Tie points near no
plane (canopy, rubble, steep slopes) give no observation: on such ground ``planes`` determines
less than ``lsm`` and says so in ``held``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..robust import nmad

MAX_PLANES = 2
NEIGHBOURS = 24  # lidar points of a tie point's neighbourhood (in plan) ...
RADIUS_SPACINGS = 3.0  # ... within this many spacings
HYPOTHESES = 64  # RANSAC triples per neighbourhood
INLIER_SPACINGS = 0.15  # a point lies on a plane within this share of the spacing
MIN_INLIERS = 8
MIN_NZ = 0.3  # steeper planes (walls, the lidar's few points on them) are left out


def segment_planes(lidar: np.ndarray, xy: np.ndarray, *, spacing: float,
                   seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Up to :data:`MAX_PLANES` planes of the lidar around each position ``xy`` (M, 2).

    Returns centroids ``(M, P, 3)``, upward unit normals ``(M, P, 3)`` (NaN where a
    neighbourhood has fewer planes), the planes' roughness ``(M, P)`` and the plan positions of
    their inliers ``(M, P, K, 2)`` (inf for points not on the plane), for the footprint test.
    """
    rng = np.random.default_rng(seed)
    m = len(xy)
    k = min(NEIGHBOURS, len(lidar))
    tol = INLIER_SPACINGS * spacing
    dist, idx = cKDTree(lidar[:, :2]).query(xy, k=k, distance_upper_bound=RADIUS_SPACINGS
                                            * spacing)
    dist, idx = dist.reshape(m, k), idx.reshape(m, k)
    valid = np.isfinite(dist)
    pts = lidar[np.where(valid, idx, 0)]  # (M, K, 3); invalid rows masked below
    centre = np.full((m, MAX_PLANES, 3), np.nan)
    normal = np.full((m, MAX_PLANES, 3), np.nan)
    rough = np.full((m, MAX_PLANES), np.nan)
    footprint = np.full((m, MAX_PLANES, k, 2), np.inf)
    free = valid.copy()
    rows = np.arange(m)
    for p in range(MAX_PLANES):
        n_free = free.sum(axis=1)
        ok = n_free >= MIN_INLIERS
        if not ok.any():
            break
        # triples drawn among each neighbourhood's free points
        order = np.argsort(~free, axis=1, kind="stable")  # free points first
        pick = (rng.random((m, HYPOTHESES, 3)) * np.maximum(n_free, 1)[:, None, None]).astype(int)
        tri = pts[rows[:, None, None], order[rows[:, None, None], pick]]  # (M, H, 3, 3)
        nrm = np.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])
        length = np.linalg.norm(nrm, axis=2, keepdims=True)
        nrm = nrm / np.maximum(length, 1e-300)
        d = np.einsum("mhi,mki->mhk", nrm, pts) - np.einsum("mhi,mhi->mh", nrm, tri[:, :, 0])[
            ..., None]
        inl = (np.abs(d) < tol) & free[:, None, :] & (length > 1e-9 * spacing**2)
        best = inl.sum(axis=2).argmax(axis=1)
        on = inl[rows, best]  # (M, K)
        ok &= on.sum(axis=1) >= MIN_INLIERS
        # refit each plane to its inliers (principal axes of the masked points)
        wgt = on / np.maximum(on.sum(axis=1, keepdims=True), 1)
        c = np.einsum("mk,mki->mi", wgt, pts)
        dd = (pts - c[:, None, :]) * on[..., None]
        cov = np.einsum("mki,mkj->mij", dd, dd) / np.maximum(on.sum(axis=1), 1)[:, None, None]
        evals, vecs = np.linalg.eigh(cov)
        n = vecs[:, :, 0] * np.where(vecs[:, 2, 0] < 0, -1.0, 1.0)[:, None]
        ok &= np.abs(n[:, 2]) >= MIN_NZ
        centre[ok, p], normal[ok, p] = c[ok], n[ok]
        rough[ok, p] = np.sqrt(np.maximum(evals[ok, 0], 0.0))
        footprint[ok, p] = np.where(on[ok][..., None], pts[ok][..., :2], np.inf)
        free &= ~(on & ok[:, None])
    return centre, normal, rough, footprint


class SegmentPlanes:
    """The observation model of ``planes`` (see the module docstring); an
    :data:`~tiereg.fine.solver.Observer` for tie points near where they are given here.

    Each tie point keeps the plane it is nearest to at the given positions ``placed``: a choice
    made anew at every iteration could flip between a roof and the ground beside it, and the
    iterations would never settle. The fine stage segments again around where its first solution
    puts the tie points.
    """

    def __init__(self, lidar: np.ndarray, placed: np.ndarray, *, spacing: float) -> None:
        centre, normal, rough, footprint = segment_planes(lidar, placed[:, :2], spacing=spacing)
        r_all = np.einsum("mpi,mpi->mp", normal, placed[:, None, :] - centre)
        reach = np.sqrt(np.min(np.sum((footprint - placed[:, None, None, :2]) ** 2, axis=3),
                               axis=2))
        score = np.where(np.isfinite(r_all) & (reach <= spacing), np.abs(r_all), np.inf)
        best = score.argmin(axis=1)
        rows = np.arange(len(placed))
        self.ok = np.isfinite(score[rows, best])
        self.centre = np.where(self.ok[:, None], centre[rows, best], 0.0)
        self.normal = np.where(self.ok[:, None], normal[rows, best], 0.0)
        self.rough = np.where(self.ok, rough[rows, best], 0.0)

    def __call__(self, q: np.ndarray):
        r = np.where(self.ok, np.einsum("mi,mi->m", self.normal, q - self.centre), np.nan)
        sigma = max(nmad(r[self.ok]), 1e-12) if self.ok.sum() >= 10 else 1.0
        s = 1.0 / np.sqrt(1.0 + (self.rough / sigma) ** 2)
        return r * s, self.normal * s[:, None], self.ok.copy()


__all__ = ["SegmentPlanes", "segment_planes"]
