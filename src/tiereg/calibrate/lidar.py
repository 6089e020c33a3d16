"""Lidar planes under the tie points: which points the lidar can control, and how well.

The lidar near the tie points is read once (:func:`~tiereg.fine.lsm.lidar_near`); at any
positions of the tie points, :meth:`LidarPatches.at` fits a plane to each point's nearest lidar
points. Every tie point whose patch is not steep (:data:`MAX_CONTROL_SLOPE_DEG`) and not rough
(:data:`MAX_SIGMA_NOISE` times the lidar's noise floor) may be a control point, with the patch's
roughness (the standard deviation of its lidar points off the plane, at least the noise floor)
as the standard deviation of its constraint: a planar patch holds its tie point to the lidar's
noise, a patch across a roof edge or in a crown hardly at all. Tie points sit at image corners,
where the lidar is seldom a clean plane, so this keeps most of them where the strict rules of
the lidar control points (:mod:`tiereg.control`, after Gneeniss et al. 2015; ``ok``) keep a few
per cent; those strict patches give the held-out check points. Level patches give the height
only (a vertical normal); sloped ones the normal distance, which also constrains the position
across the slope.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ..control import (
    LEVEL_SLOPE_DEG,
    MAX_CURVATURE_NOISE,
    MAX_OFFSET,
    MAX_ROUGHNESS_NOISE,
    MAX_SLOPE_DEG,
    PATCH_POINTS,
)
from ..fine.lsm import lidar_near
from ..reference import Reference
from ..surface import fit_planes, plane_heights

MARGIN_M = 5.0  # the tie points may move this far during calibration (reference units)
MAX_CONTROL_SLOPE_DEG = 30.0  # steeper patches control no tie point
SURFACE = "quadric"
MAX_SIGMA_NOISE = 6.0  # nor do patches rougher than this many times the lidar's noise floor


@dataclass(frozen=True, eq=False)
class Patches:
    """A lidar plane per tie point (local frame). ``usable``: the patch may control its point
    (with ``sigma_m``); ``ok``: it passes the strict rules of the lidar control points."""

    ok: np.ndarray = field(repr=False)  # (N,) bool
    usable: np.ndarray = field(repr=False)  # (N,) bool
    centroid: np.ndarray = field(repr=False)  # (N, 3)
    normal: np.ndarray = field(repr=False)  # (N, 3): unit; on level patches n / n_z
    sigma_m: np.ndarray = field(repr=False)  # (N,) the patch's roughness, at least the floor
    distance_m: np.ndarray = field(repr=False)  # (N,) normal distance of the point (signed)
    dz_m: np.ndarray = field(repr=False)  # (N,) height above the plane at the point
    level: np.ndarray = field(repr=False)  # (N,) bool


def fit_quadrics(patches: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                 np.ndarray]:
    """Quadratic surfaces ``z = a + b dx + c dy + d dx^2 + e dx dy + f dy^2`` through patches of
    points ``(m, k, 3)``, ``dx, dy`` from each position ``xy`` ``(m, 2)``: the height ``a`` and
    the slope ``(b, c)`` there, and the standard deviation of the points off the surface
    (``k - 6`` degrees of freedom).

    A plane through a patch on curved ground passes below a crest and above a hollow; tie points
    sit where the image's shading changes, on crests and in hollows more than on average, so a
    plane's heights there are biased with the relief, and with them the focal length. The
    quadratic surface follows the curvature.
    """
    d = patches[:, :, :2] - xy[:, None, :]
    dx, dy = d[..., 0], d[..., 1]
    A = np.stack([np.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy], axis=-1)
    N = np.einsum("mki,mkj->mij", A, A)
    scale = np.einsum("mii->m", N)[:, None, None] * 1e-9
    rhs = np.einsum("mki,mk->mi", A, patches[..., 2])[..., None]
    coef = np.linalg.solve(N + scale * np.eye(6), rhs)[..., 0]
    res = patches[..., 2] - np.einsum("mki,mi->mk", A, coef)
    dof = max(patches.shape[1] - 6, 1)
    return coef[:, 0], coef[:, 1:3], np.sqrt(np.sum(res**2, axis=1) / dof)


@dataclass(frozen=True, eq=False)
class LidarPatches:
    """The lidar points near the tie points (local frame of ``reference``)."""

    points: np.ndarray = field(repr=False)
    radius: float
    _tree: cKDTree = field(repr=False)
    floor_m: float = 0.0  # the lidar's noise: the 10th percentile of the patches' roughness

    @classmethod
    def read(cls, reference: Reference, xyz_local: np.ndarray) -> LidarPatches:
        """The lidar near ``xyz_local``; the noise floor from the patches at those points."""
        radius = 3.0 * reference.spacing
        pts = lidar_near(reference, xyz_local[:, :2], radius + MARGIN_M)
        tree = cKDTree(pts[:, :2]) if len(pts) >= PATCH_POINTS else None
        first = cls(pts, radius, tree)
        fit = first._fit(xyz_local)[1]
        floor = float(np.percentile(fit[3], 10)) if fit is not None else 0.0
        return cls(pts, radius, tree, max(floor, 1e-6))

    def _fit(self, xyz: np.ndarray):
        """Rows of ``xyz`` with a full patch, and ``(neighbours, centroids, normals,
        roughness, reach)`` there (``None`` when there is none)."""
        if self._tree is None:
            return np.zeros(0, np.int64), None
        dist, idx = self._tree.query(xyz[:, :2], k=PATCH_POINTS, distance_upper_bound=self.radius)
        rows = np.flatnonzero(np.isfinite(dist).all(axis=1))
        if len(rows) == 0:
            return rows, None
        nb = self.points[idx[rows]]
        c, normal, rough = fit_planes(nb)
        roughness = rough * math.sqrt(PATCH_POINTS / (PATCH_POINTS - 3))
        return rows, (nb, c, normal, roughness, dist[rows, -1])

    def at(self, xyz: np.ndarray) -> Patches:
        """The patches at positions ``xyz`` (local frame); see the module docstring."""
        n = len(xyz)
        nan3 = np.full((n, 3), np.nan)
        out = dict(ok=np.zeros(n, bool), usable=np.zeros(n, bool), centroid=nan3,
                   normal=nan3.copy(), sigma_m=np.full(n, np.nan), distance_m=np.full(n, np.nan),
                   dz_m=np.full(n, np.nan), level=np.zeros(n, bool))
        rows, fit = self._fit(xyz)
        if fit is None:
            return Patches(**out)
        nb, c, normal, roughness, reach = fit
        slope = np.degrees(np.arccos(np.clip(normal[:, 2], -1.0, 1.0)))
        q = xyz[rows]
        offset = np.hypot(*(q[:, :2] - c[:, :2]).T)
        z_plane = plane_heights(c, normal, q)
        c6, n6, _ = fit_planes(nb[:, : PATCH_POINTS // 2])
        z_half = plane_heights(c6, n6, q)
        floor = self.floor_m
        ok = ((slope <= MAX_SLOPE_DEG) & (roughness <= MAX_ROUGHNESS_NOISE * floor)
              & (offset <= MAX_OFFSET * reach)
              & (np.abs(z_half - z_plane) <= MAX_CURVATURE_NOISE * floor))
        level = slope <= LEVEL_SLOPE_DEG
        if SURFACE == "quadric":
            # the constraint: the tangent plane of the patch's quadratic surface at the point
            z_q, grad, rough_q = fit_quadrics(nb, q[:, :2])
            c = np.column_stack([q[:, :2], z_q])
            normal = np.column_stack([-grad, np.ones(len(q))])
            normal /= np.linalg.norm(normal, axis=1, keepdims=True)
            z_plane, roughness = z_q, np.minimum(roughness, rough_q)
            slope = np.degrees(np.arccos(np.clip(normal[:, 2], -1.0, 1.0)))
            level = slope <= LEVEL_SLOPE_DEG
        sigma = np.maximum(roughness, floor)
        out["usable"][rows] = (slope <= MAX_CONTROL_SLOPE_DEG) & (sigma <= MAX_SIGMA_NOISE * floor)
        # level patches: the height above the plane (the normal scaled to a unit vertical part)
        normal = np.where(level[:, None], normal / normal[:, 2:3], normal)
        out["ok"][rows] = ok
        out["centroid"][rows] = c
        out["normal"][rows] = normal
        out["sigma_m"][rows] = sigma
        out["distance_m"][rows] = np.einsum("ij,ij->i", q - c, normal)
        out["dz_m"][rows] = q[:, 2] - z_plane
        out["level"][rows] = level
        return Patches(**out)
