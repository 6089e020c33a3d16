"""Lidar planes under the tie points: which points the lidar can control, and how well.

The lidar near the tie points is read once (:func:`~tiereg.fine.lsm.lidar_near`); at any
positions of the tie points, :meth:`LidarPatches.at` fits a plane to each point's nearest lidar
points and keeps the planar, gently sloped, smooth patches by the rules of the lidar control
points (:mod:`tiereg.control`, after Gneeniss et al. 2015). Level patches give the height only
(a vertical normal); sloped ones the normal distance, which also constrains the position across
the slope.
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


@dataclass(frozen=True, eq=False)
class Patches:
    """A lidar plane per tie point (local frame); ``ok``: a patch fit to control the point."""

    ok: np.ndarray = field(repr=False)  # (N,) bool
    centroid: np.ndarray = field(repr=False)  # (N, 3)
    normal: np.ndarray = field(repr=False)  # (N, 3): unit; on level patches n / n_z
    sigma_m: np.ndarray = field(repr=False)  # (N,) precision of the plane at the point
    distance_m: np.ndarray = field(repr=False)  # (N,) normal distance of the point (signed)
    dz_m: np.ndarray = field(repr=False)  # (N,) height above the plane at the point
    level: np.ndarray = field(repr=False)  # (N,) bool


@dataclass(frozen=True, eq=False)
class LidarPatches:
    """The lidar points near the tie points (local frame of ``reference``)."""

    points: np.ndarray = field(repr=False)
    radius: float
    _tree: cKDTree = field(repr=False)

    @classmethod
    def read(cls, reference: Reference, xyz_local: np.ndarray) -> LidarPatches:
        radius = 3.0 * reference.spacing
        pts = lidar_near(reference, xyz_local[:, :2], radius + MARGIN_M)
        return cls(pts, radius, cKDTree(pts[:, :2]) if len(pts) else None)

    def at(self, xyz: np.ndarray) -> Patches:
        """The patches at positions ``xyz`` (local frame); see the module docstring."""
        n = len(xyz)
        nan3 = np.full((n, 3), np.nan)
        out = dict(ok=np.zeros(n, bool), centroid=nan3, normal=nan3.copy(),
                   sigma_m=np.full(n, np.nan), distance_m=np.full(n, np.nan),
                   dz_m=np.full(n, np.nan), level=np.zeros(n, bool))
        if self._tree is None or len(self.points) < PATCH_POINTS:
            return Patches(**out)
        dist, idx = self._tree.query(xyz[:, :2], k=PATCH_POINTS, distance_upper_bound=self.radius)
        rows = np.flatnonzero(np.isfinite(dist).all(axis=1))
        if len(rows) == 0:
            return Patches(**out)
        nb = self.points[idx[rows]]
        c, normal, rough = fit_planes(nb)
        roughness = rough * math.sqrt(PATCH_POINTS / (PATCH_POINTS - 3))
        slope = np.degrees(np.arccos(np.clip(normal[:, 2], -1.0, 1.0)))
        q = xyz[rows]
        offset = np.hypot(*(q[:, :2] - c[:, :2]).T)
        z_plane = plane_heights(c, normal, q)
        c6, n6, _ = fit_planes(nb[:, : PATCH_POINTS // 2])
        z_half = plane_heights(c6, n6, q)
        floor = max(float(np.percentile(roughness, 10)), 1e-9)  # the lidar's own noise
        ok = ((slope <= MAX_SLOPE_DEG) & (roughness <= MAX_ROUGHNESS_NOISE * floor)
              & (offset <= MAX_OFFSET * dist[rows, -1])
              & (np.abs(z_half - z_plane) <= MAX_CURVATURE_NOISE * floor))
        level = slope <= LEVEL_SLOPE_DEG
        # level patches: the height above the plane (the normal scaled to a unit vertical part)
        normal = np.where(level[:, None], normal / normal[:, 2:3], normal)
        out["ok"][rows] = ok
        out["centroid"][rows] = c
        out["normal"][rows] = normal
        out["sigma_m"][rows] = np.maximum(roughness, floor) / math.sqrt(PATCH_POINTS - 3)
        out["distance_m"][rows] = np.einsum("ij,ij->i", q - c, normal)
        out["dz_m"][rows] = q[:, 2] - z_plane
        out["level"][rows] = level
        return Patches(**out)
