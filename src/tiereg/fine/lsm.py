"""Least-squares surface matching of tie points to the lidar (the fine stage).

Two observation models feed the one solver (:func:`~tiereg.fine.solver.solve_helmert`):

1. **vertical**: the height difference to the gridded lidar surface (bilinear heights and
   gradients of the reference's base grid; Rosenholm & Torlegard 1988). Every tie point on the
   lidar contributes; it converges from a coarse pose a cell or two away.
2. **planes**: the normal distance to a plane fitted to the lidar points around each tie point
   (point-to-plane; the LS3D model of Gruen & Akca 2005 with planar patches). Only points whose
   neighbourhood is planar (roofs, open ground) contribute; the lidar is read once more, and only
   the points near the tie points are kept.

``lsm`` runs the vertical model, then the planes model from its answer when enough planar patches
exist. Tie points sit on the visible surface, so both use first returns; robust weights keep
canopy, edges and blunders from pulling the answer.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..reference import Reference
from ..surface import SurfaceSampler
from ..transform import Transform
from .solver import PARAMETERS, HelmertFit, Observer, solve_helmert

PATCH_POINTS = 12  # lidar neighbours per plane
MAX_SURFACE_VARIATION = 0.01  # lambda_min / sum(lambda) of a planar patch (Pauly et al. 2002)
# Gently sloped surfaces only (roofs, ground; cf. Gneeniss et al. 2015): at steeper ones (walls,
# the step at a roof's edge) a tie point's horizontal error and the kink between the patch and
# its neighbour bias the distance, and tie points gather at exactly such edges (image corners).
MAX_SLOPE = 1.0  # rise over run: 45 degrees
CENTRED = 0.35  # offset from the patch centroid, as a share of the farthest neighbour's distance
MIN_PLANES = 50  # fewer planar patches than this: the vertical answer stands


@dataclass(frozen=True)
class FineResult:
    """The fine stage's answer: an increment in the local reference frame and its precision."""

    T_increment: Transform  # local reference frame: applies after the coarse pose
    method: str
    model: str  # the observation model of the final solution
    fit: HelmertFit
    n_planes: int  # tie points with a planar lidar patch
    seconds: float

    @property
    def held(self) -> tuple[str, ...]:
        return self.fit.held

    def precision(self, scale: float) -> dict[str, Any]:
        """One standard deviation per parameter (RESULT.json ``precision``); ``None`` if held.

        Angles and the scale are those of the whole transform; the translation's is that of the
        block centroid (the transform's own translation, far from the data, is not meaningful).
        """
        s = self.fit.sigma

        def val(i: int, factor: float = 1.0) -> float | None:
            return None if not np.isfinite(s[i]) else float(s[i] * factor)

        return {
            "scale": val(0, scale),
            "omega_deg": val(1, 180 / math.pi),
            "phi_deg": val(2, 180 / math.pi),
            "kappa_deg": val(3, 180 / math.pi),
            "translation": [val(4), val(5), val(6)],
            "translation_at": "block centroid",
        }

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": "fine",
            "method": self.method,
            "model": self.model,
            "seconds": round(self.seconds, 3),
            "converged": self.fit.converged,
            "iterations": self.fit.iterations,
            "sigma0": self.fit.sigma0,
            "n_observed": self.fit.n_observed,
            "n_used": self.fit.n_used,
            "n_planes": self.n_planes,
            "held": list(self.fit.held),
            "parameters": list(PARAMETERS),
        }


def vertical_observer(sampler: SurfaceSampler) -> Observer:
    """``r = z - Z(x, y)`` and ``g = (-Z_x, -Z_y, 1)`` against a gridded surface, where its slope
    is at most :data:`MAX_SLOPE`."""

    def observe(q: np.ndarray):
        z, ok = sampler.sample(q[:, 0], q[:, 1])
        zx, zy = sampler.gradient(q[:, 0], q[:, 1])
        g = np.column_stack([-zx, -zy, np.ones(len(q))])
        return q[:, 2] - z, g, ok & (np.hypot(zx, zy) <= MAX_SLOPE)

    return observe


def lidar_near(reference: Reference, xy: np.ndarray, radius: float) -> np.ndarray:
    """The reference points (local coordinates) within about ``radius`` of any of ``xy``.

    One streaming pass; a mask of cells of size ``radius`` marks the tie points' neighbourhoods,
    so memory follows the number of tie points, not the lidar.
    """
    lo = xy.min(axis=0) - 2 * radius
    shape = (np.ceil((xy.max(axis=0) + 2 * radius - lo) / radius)).astype(int) + 1
    near = np.zeros((shape[1], shape[0]), bool)  # rows: y, cols: x
    ix = ((xy - lo) / radius).astype(int)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            near[ix[:, 1] + dy, ix[:, 0] + dx] = True
    kept = []
    for chunk in reference.local_chunks():
        jx = np.floor((chunk[:, 0] - lo[0]) / radius).astype(np.int64)
        jy = np.floor((chunk[:, 1] - lo[1]) / radius).astype(np.int64)
        inside = (jx >= 0) & (jx < shape[0]) & (jy >= 0) & (jy < shape[1])
        sel = np.flatnonzero(inside)
        sel = sel[near[jy[sel], jx[sel]]]
        if len(sel):
            kept.append(chunk[sel])
    return np.concatenate(kept) if kept else np.empty((0, 3))


def plane_observer(lidar: np.ndarray, radius: float) -> Observer:
    """``r = n . (q - c)``, ``g = n`` for the plane through the lidar points around each point.

    Neighbours are the :data:`PATCH_POINTS` nearest in plan within ``radius``; the patch counts
    when its surface variation is below :data:`MAX_SURFACE_VARIATION` and its slope at most
    :data:`MAX_SLOPE`.
    """
    tree = cKDTree(lidar[:, :2])

    def observe(q: np.ndarray):
        n_q = len(q)
        r, g, ok = np.full(n_q, np.nan), np.zeros((n_q, 3)), np.zeros(n_q, bool)
        dist, idx = tree.query(q[:, :2], k=PATCH_POINTS, distance_upper_bound=radius)
        full = np.isfinite(dist).all(axis=1)
        if not full.any():
            return r, g, ok
        nb = lidar[idx[full]]  # (m, k, 3)
        c = nb.mean(axis=1)
        d = nb - c[:, None, :]
        cov = np.einsum("mki,mkj->mij", d, d) / PATCH_POINTS
        evals, evecs = np.linalg.eigh(cov)
        normal = evecs[:, :, 0]
        normal *= np.where(normal[:, 2] < 0, -1.0, 1.0)[:, None]  # upward
        variation = evals[:, 0] / np.maximum(evals.sum(axis=1), 1e-300)
        # the point must sit inside its patch, not beside it (a roof seen from the ground next to
        # it is planar too): its offset from the centroid small against the patch's reach
        off = np.hypot(*(q[full, :2] - c[:, :2]).T)
        gentle = normal[:, 2] >= 1.0 / math.sqrt(1.0 + MAX_SLOPE**2)
        planar = (variation < MAX_SURFACE_VARIATION) & gentle & (off < CENTRED * dist[full, -1])
        rows = np.flatnonzero(full)
        r[rows] = np.einsum("mi,mi->m", normal, q[rows] - c)
        g[rows] = normal
        ok[rows] = planar
        return r, g, ok

    return observe


def register_fine(
    placed: np.ndarray,
    reference: Reference,
    *,
    cell_size: float,
    method: str = "lsm",
) -> FineResult:
    """Fine registration of tie points ``placed`` by the coarse stage (local reference frame).

    ``cell_size``: the registration's grid cell; parameters that move the block by more than a
    quarter of it (one standard deviation) are not determined and are held. ``method``: ``lsm``
    (vertical, then planes), ``icp-point`` or ``icp-plane`` (:mod:`tiereg.fine.icp`).
    """
    t0 = time.perf_counter()
    hold = cell_size / 4
    if method in ("icp-point", "icp-plane"):
        from .icp import plane_observer_icp, point_observer

        lidar = lidar_near(reference, placed[:, :2], max(2.5 * reference.spacing, cell_size / 4))
        if len(lidar) < PATCH_POINTS:
            observe = _no_observations
        else:
            observe = point_observer(lidar) if method == "icp-point" else plane_observer_icp(lidar)
        fit = solve_helmert(placed, observe, hold_displacement=hold)
        return FineResult(fit.T, method, method, fit, 0, time.perf_counter() - t0)
    sampler = SurfaceSampler.from_grid(reference.base)
    fit = solve_helmert(placed, vertical_observer(sampler), hold_displacement=hold)
    model, n_planes = "vertical", 0
    radius = 2.5 * max(reference.spacing, reference.base_cell / 4)
    after_vertical = fit.T.apply(placed)
    lidar = lidar_near(reference, after_vertical[:, :2], radius)
    if len(lidar) >= PATCH_POINTS:
        observe = plane_observer(lidar, radius)
        n_planes = int(observe(after_vertical)[2].sum())
        if n_planes >= MIN_PLANES:
            planes = solve_helmert(after_vertical, observe, hold_displacement=hold,
                                   fixed=fit.held)
            if planes.converged or not fit.converged:
                fit = _compose(fit, planes)
                model = "planes"
    return FineResult(fit.T, "lsm", model, fit, n_planes, time.perf_counter() - t0)


def _no_observations(q: np.ndarray):
    return np.full(len(q), np.nan), np.zeros((len(q), 3)), np.zeros(len(q), bool)


def _compose(first: HelmertFit, second: HelmertFit) -> HelmertFit:
    """The second fit (made on points already moved by the first) after the first."""
    return replace(second, T=second.T @ first.T)
