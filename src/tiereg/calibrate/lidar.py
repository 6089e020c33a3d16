"""Lidar planes under the tie points: which points the lidar can control, and how well.

The lidar near the tie points is read once (:meth:`~tiereg.reference.Reference.points_near`); at any
positions of the tie points, :meth:`LidarPatches.at` fits a quadratic surface to each point's
nearest lidar points (:func:`fit_quadrics`) and constrains the point to its tangent plane there.
Every tie point whose patch is not steep (:data:`MAX_CONTROL_SLOPE_DEG`) and not rough
(:data:`MAX_SIGMA_NOISE` times the lidar's noise floor) may be a control point, with the patch's
roughness (the standard deviation of its lidar points off the surface, at least the noise floor)
as the standard deviation of its constraint: a smooth patch holds its tie point to the lidar's
noise, a patch across a roof edge or in a crown hardly at all. Tie points sit at image corners,
where the lidar is seldom a clean plane, so this keeps most of them where the strict rules of
the lidar control points (:mod:`tiereg.control`, after Gneeniss et al. 2015) keep a few per
cent. Smooth patches with the point near their middle (``ok``: those rules, the quadratic
surface taking the place of their curvature test and the control points' slope limit of theirs)
give the held-out check points. Level patches give the height
only (a vertical normal); sloped ones the normal distance, which also constrains the position
across the slope.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ..control import (
    LEVEL_SLOPE_DEG,
    MAX_OFFSET,
    MAX_ROUGHNESS_NOISE,
    PATCH_POINTS,
)
from ..reference import Reference

MARGIN_M = 5.0  # the tie points may move this far during calibration (reference units)
MAX_CONTROL_SLOPE_DEG = 30.0  # steeper patches control no tie point
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


def lidar_reference(reference, *, reference_format: str | None = None) -> Reference:
    """The lidar ``reference`` (paths as :func:`tiereg.register` takes them, a point array or
    :class:`~tiereg.points.PointSet`) prepared as the registration prepares it."""
    from ..io import open_points
    from ..io.base import ArraySource
    from ..points import PointSet
    from ..reference import point_spacing, prepare_reference

    if isinstance(reference, np.ndarray):
        reference = PointSet(np.asarray(reference, dtype=np.float64), source="<reference array>")
    src = ArraySource(reference) if isinstance(reference, PointSet) else open_points(
        reference, format=reference_format)
    return prepare_reference(src, base_cell=max(4.0 * point_spacing(src), 1e-3))


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
        pts = reference.points_near(xyz_local[:, :2], radius + MARGIN_M)
        tree = cKDTree(pts[:, :2]) if len(pts) >= PATCH_POINTS else None
        fit = cls(pts, radius, tree)._fit(xyz_local)[1]
        floor = float(np.percentile(fit[2], 10)) if fit is not None else 0.0
        return cls(pts, radius, tree, max(floor, 1e-6))

    def _fit(self, xyz: np.ndarray):
        """Rows of ``xyz`` with a full patch, and there ``(height, gradient, roughness, offset,
        reach)`` of the patch's quadratic surface (:func:`fit_quadrics`; ``offset``: from the
        patch's centroid to the point in plan; ``None`` when there is no patch)."""
        if self._tree is None:
            return np.zeros(0, np.int64), None
        dist, idx = self._tree.query(xyz[:, :2], k=PATCH_POINTS, distance_upper_bound=self.radius)
        rows = np.flatnonzero(np.isfinite(dist).all(axis=1))
        if len(rows) == 0:
            return rows, None
        nb = self.points[idx[rows]]
        height, gradient, roughness = fit_quadrics(nb, xyz[rows, :2])
        offset = np.hypot(*(xyz[rows, :2] - nb[:, :, :2].mean(axis=1)).T)
        return rows, (height, gradient, roughness, offset, dist[rows, -1])

    def at(self, xyz: np.ndarray) -> Patches:
        """The patches at positions ``xyz`` (local frame); see the module docstring."""
        n = len(xyz)
        nan3 = np.full((n, 3), np.nan)
        out = {"ok": np.zeros(n, bool), "usable": np.zeros(n, bool), "centroid": nan3,
               "normal": nan3.copy(), "sigma_m": np.full(n, np.nan),
               "distance_m": np.full(n, np.nan), "dz_m": np.full(n, np.nan),
               "level": np.zeros(n, bool)}
        rows, fit = self._fit(xyz)
        if fit is None:
            return Patches(**out)
        height, gradient, roughness, offset, reach = fit
        q = xyz[rows]
        # the constraint: the tangent plane of the patch's quadratic surface at the point
        normal = np.column_stack([-gradient, np.ones(len(q))])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        slope = np.degrees(np.arccos(np.clip(normal[:, 2], -1.0, 1.0)))
        floor = self.floor_m
        sigma = np.maximum(roughness, floor)
        out["ok"][rows] = ((slope <= MAX_CONTROL_SLOPE_DEG)
                           & (roughness <= MAX_ROUGHNESS_NOISE * floor)
                           & (offset <= MAX_OFFSET * reach))
        out["usable"][rows] = (slope <= MAX_CONTROL_SLOPE_DEG) & (sigma <= MAX_SIGMA_NOISE * floor)
        level = slope <= LEVEL_SLOPE_DEG
        # level patches: the height above the plane (the normal scaled to a unit vertical part)
        normal = np.where(level[:, None], normal / normal[:, 2:3], normal)
        c = np.column_stack([q[:, :2], height])
        out["centroid"][rows] = c
        out["normal"][rows] = normal
        out["sigma_m"][rows] = sigma
        out["distance_m"][rows] = np.einsum("ij,ij->i", q - c, normal)
        out["dz_m"][rows] = q[:, 2] - height
        out["level"][rows] = level
        return Patches(**out)
