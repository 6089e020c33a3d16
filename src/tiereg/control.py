"""Lidar control points: tie points whose height the lidar knows well, for camera calibration.

After Gneeniss, Mills & Miller (2015, ISPRS J. 109, "In-flight photogrammetric camera calibration
and validation via complementary lidar"): registered tie points are kept where the lidar around
them is a planar, gently sloped, smooth patch; the patch gives the point's height (the plane at the
tie point's position), the registration its position. Points that the fine stage rejected as
blunders, or that lie off their patch's plane, are left out, and at most one point is kept per
cell of a regular grid over the block so that they spread evenly.

Each control point has ``kind``: ``"height"`` on level patches (the lidar gives the height only),
``"xyz"`` on sloped ones (up to :data:`MAX_SLOPE_DEG`), whose position is as good as the
registration's; ``sx, sy`` are then the registration's horizontal precision.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .reference import Reference
from .robust import nmad
from .surface import fit_planes, plane_heights

PATCH_POINTS = 12  # lidar points per patch
MAX_SLOPE_DEG = 15.0  # gently sloped patches only
LEVEL_SLOPE_DEG = 5.0  # below this the patch gives the height only
MAX_ROUGHNESS_NOISE = 1.5  # patch roughness at most this many times the lidar's noise floor
MAX_CURVATURE_NOISE = 1.0  # the half patch's plane height within this many noise floors
MAX_OFFSET = 0.25  # the tie point within this share of the patch's reach from its centroid
MAX_RESIDUAL_NMADS = 3.0  # normal distance of the tie point to its plane
CELLS_PER_SIDE = 12  # at most one control point per cell of a 12 x 12 grid over the block


@dataclass(frozen=True)
class ControlPoint:
    name: str  # "tp<row>": the tie point's 1-based position in the moving file
    index: int  # 0-based index of the tie point
    xyz: tuple[float, float, float]  # reference frame (file coordinates)
    sigma: tuple[float | None, float | None, float]  # sx, sy (None: height only), sz
    kind: str  # "height" or "xyz"
    slope_deg: float
    roughness: float  # standard deviation of the patch's points off its plane


def select_control_points(
    xyz_local: np.ndarray,
    reference: Reference,
    *,
    blunder: np.ndarray | None = None,
    sigma_xy: float | None = None,
    cells_per_side: int = CELLS_PER_SIDE,
) -> tuple[ControlPoint, ...]:
    """Control points among the registered tie points ``xyz_local`` (reference local frame).

    ``blunder``: points the registration rejected; ``sigma_xy``: the registration's horizontal
    precision, given to the ``"xyz"`` points.
    """
    spacing = reference.spacing
    radius = 3.0 * spacing
    lidar = reference.points_near(xyz_local[:, :2], radius)
    if len(lidar) < PATCH_POINTS:
        return ()
    tree = cKDTree(lidar[:, :2])
    dist, idx = tree.query(xyz_local[:, :2], k=PATCH_POINTS, distance_upper_bound=radius)
    full = np.isfinite(dist).all(axis=1)
    if blunder is not None:
        full &= ~np.asarray(blunder, bool)
    rows = np.flatnonzero(full)
    if len(rows) == 0:
        return ()
    nb = lidar[idx[rows]]
    c, normal, rough = fit_planes(nb)
    roughness = rough * math.sqrt(PATCH_POINTS / (PATCH_POINTS - 3))  # unbiased: 3 parameters
    slope = np.degrees(np.arccos(np.clip(normal[:, 2], -1.0, 1.0)))
    q = xyz_local[rows]
    offset = np.hypot(*(q[:, :2] - c[:, :2]).T)
    z_plane = plane_heights(c, normal, q)  # the plane's height at the tie point
    residual = q[:, 2] - z_plane
    # the same plane from the nearest half of the patch: a curved patch (a ridge, a roof's edge,
    # a crown) gives another height, a plane the same
    c6, n6, _ = fit_planes(nb[:, : PATCH_POINTS // 2])
    z_half = plane_heights(c6, n6, q)
    floor = max(float(np.percentile(roughness, 10)), 1e-9)  # the lidar's own noise, roughly
    spread = max(nmad(residual), 1e-9)
    ok = ((slope <= MAX_SLOPE_DEG) & (roughness <= MAX_ROUGHNESS_NOISE * floor)
          & (offset <= MAX_OFFSET * dist[rows, -1])
          & (np.abs(z_half - z_plane) <= MAX_CURVATURE_NOISE * floor)
          & (np.abs(residual - np.median(residual)) <= MAX_RESIDUAL_NMADS * spread))
    if not ok.any():
        return ()
    # one per cell of a grid over the block: the smoothest patch in each
    lo, hi = xyz_local[:, :2].min(axis=0), xyz_local[:, :2].max(axis=0)
    cell = np.floor((q[:, :2] - lo) / np.maximum(hi - lo, 1e-12) * cells_per_side).clip(
        0, cells_per_side - 1).astype(int)
    label = cell[:, 0] * cells_per_side + cell[:, 1]
    order = np.lexsort((roughness, label))
    chosen = [i for i in order if ok[i]]
    seen: set[int] = set()
    out = []
    origin = reference.origin
    for i in chosen:
        if label[i] in seen:
            continue
        seen.add(int(label[i]))
        sz = roughness[i] / math.sqrt(PATCH_POINTS - 3)
        level = slope[i] <= LEVEL_SLOPE_DEG
        if not level and sigma_xy is not None:  # horizontal uncertainty moves the height too
            sz = math.hypot(sz, math.tan(math.radians(slope[i])) * sigma_xy)
        j = int(rows[i])
        out.append(ControlPoint(
            name=f"tp{j + 1}", index=j,
            xyz=(float(q[i, 0] + origin[0]), float(q[i, 1] + origin[1]),
                 float(z_plane[i] + origin[2])),
            sigma=(None if level else sigma_xy, None if level else sigma_xy, float(sz)),
            kind="height" if level else "xyz", slope_deg=float(slope[i]),
            roughness=float(roughness[i])))
    return tuple(sorted(out, key=lambda p: p.index))


def _num(v: float | None) -> str:
    return "" if v is None or not math.isfinite(v) else f"{v:.4f}"


def control_points_csv(points: tuple[ControlPoint, ...]) -> str:
    lines = ["name,x,y,z,sx,sy,sz,kind,slope_deg,roughness"]
    for p in points:
        lines.append(",".join([p.name, *(f"{v:.4f}" for v in p.xyz),
                               *(_num(v) for v in p.sigma), p.kind, f"{p.slope_deg:.2f}",
                               f"{p.roughness:.4f}"]))
    return "\n".join(lines) + "\n"


def control_points_list(points: tuple[ControlPoint, ...]) -> str:
    """The generic ``name x y z sx sy sz`` list most photogrammetric software imports as ground
    control; an unknown horizontal precision is written as 0 with the point marked in a comment
    line above the list (height-only control)."""
    lines = ["# tiereg lidar control points: name x y z sx sy sz (sx = sy = 0: height only)"]
    for p in points:
        sx, sy = (0.0 if v is None else v for v in p.sigma[:2])
        lines.append(f"{p.name} {p.xyz[0]:.4f} {p.xyz[1]:.4f} {p.xyz[2]:.4f} "
                     f"{sx:.4f} {sy:.4f} {p.sigma[2]:.4f}")
    return "\n".join(lines) + "\n"


def control_points_colmap(points: tuple[ControlPoint, ...]) -> str:
    """The control points as a COLMAP ``points3D.txt`` (lidar frame): ``POINT3D_ID`` is the tie
    point's 1-based row in the moving file, ``ERROR`` its height precision, tracks empty."""
    lines = ["# 3D point list with one line of data per point:",
             "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
             f"# Number of points: {len(points)}, lidar control points from tiereg"]
    for p in points:
        lines.append(f"{p.index + 1} {p.xyz[0]:.4f} {p.xyz[1]:.4f} {p.xyz[2]:.4f} 255 0 0 "
                     f"{p.sigma[2]:.4f}")
    return "\n".join(lines) + "\n"
