"""Peers of tiereg's fine stage for ``fine_far.py``, each started from the same pose.

Every peer gets the tie points placed by the starting pose and the lidar's first returns (cropped
to the block and a margin) in one local frame, and returns the increment ``T_ref_start`` (4x4)
that takes the placed tie points onto the lidar; the benchmark composes it with the start.

* Open3D (``registration_icp``): point-to-point with scaling (Besl & McKay 1992; Umeyama 1991) and
  point-to-plane (Chen & Medioni 1992; rigid), target normals from 20 neighbours computed once a
  lidar (by small_gicp where it is installed, else by Open3D from 30); correspondence distance
  narrowed over :data:`DISTANCES_M` (the start is metres off).
* small_gicp (``small_gicp.align`` on clouds preprocessed once a lidar): GICP (Segal et al. 2009)
  and point-to-plane ICP, rigid, the same distances.
* xdem: Nuth & Kaab (2011) (a horizontal and vertical shift), its ICP (point-to-plane, rigid) and
  LZD (Rosenholm & Torlegard 1988; rigid), each fitting the tie points, given as an elevation
  point cloud (a GeoDataFrame with a ``z`` column in the lidar's CRS), to a DSM of the lidar:
  the mean of its first returns in 2 m cells. The transform xdem found is read off the points it
  moves (a least-squares similarity between the points before and after ``apply``).

A peer that fails returns ``ok=False`` and the reason.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

DISTANCES_M = (30.0, 5.0, 1.0)
DSM_CELL_M = 2.0


@dataclass(frozen=True)
class PeerResult:
    T_ref_start: np.ndarray
    seconds: float
    used: float | None = None  # share of tie points with a correspondence at the end
    converged: bool | None = None
    note: str = ""
    ok: bool = True


def _failed(t0: float, exc: Exception) -> PeerResult:
    return PeerResult(np.eye(4), time.perf_counter() - t0, note=f"{type(exc).__name__}: "
                      f"{str(exc).strip()[:150]}", ok=False)


def similarity_from_pairs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least-squares similarity (Umeyama 1991) taking points ``a`` onto ``b`` (4x4)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    A, B = a - ca, b - cb
    U, S, Vt = np.linalg.svd(B.T @ A / len(a))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = np.trace(np.diag(S) @ D) / (A**2).sum(axis=1).mean()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = s * R, cb - s * R @ ca
    return T


# --------------------------------------------------------------------------------- Open3D
def open3d_target(cloud: np.ndarray, gicp_prepared=None):
    """The lidar as an Open3D cloud with normals: small_gicp's (20 neighbours) where it has
    prepared the cloud already (Open3D's own estimate takes many minutes on millions of points),
    else Open3D's from 30 neighbours."""
    import open3d as o3d

    if gicp_prepared is not None:
        pc = gicp_prepared[0]
        tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pc.points()[:, :3].copy()))
        tgt.normals = o3d.utility.Vector3dVector(pc.normals()[:, :3].copy())
        return tgt
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(cloud, np.float64)))
    tgt.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=30))
    return tgt


def open3d_icp(placed: np.ndarray, target, *, plane: bool) -> PeerResult:
    t0 = time.perf_counter()
    try:
        import open3d as o3d

        reg = o3d.pipelines.registration
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(placed, np.float64)))
        est = (reg.TransformationEstimationPointToPlane() if plane
               else reg.TransformationEstimationPointToPoint(with_scaling=True))
        crit = reg.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7,
                                          max_iteration=100)
        T = np.eye(4)
        for d in DISTANCES_M:
            res = reg.registration_icp(src, target, d, T, est, crit)
            T = np.asarray(res.transformation)
        return PeerResult(T, time.perf_counter() - t0, used=float(res.fitness),
                          note=f"inlier RMSE {res.inlier_rmse:.3f} m")
    except Exception as exc:  # noqa: BLE001 -- a peer's failure is recorded, not raised
        return _failed(t0, exc)


# ------------------------------------------------------------------------------ small_gicp
def gicp_target(cloud: np.ndarray):
    """The lidar preprocessed for small_gicp (covariances and normals from 20 neighbours, no
    thinning below 0.25 m) and its KD-tree."""
    import small_gicp

    return small_gicp.preprocess_points(np.asarray(cloud, np.float64),
                                        downsampling_resolution=0.25, num_neighbors=20,
                                        num_threads=2)


def gicp(placed: np.ndarray, target, *, kind: str) -> PeerResult:
    """``kind``: ``GICP`` or ``PLANE_ICP``."""
    t0 = time.perf_counter()
    try:
        import small_gicp

        pc, tree = target
        src, _ = small_gicp.preprocess_points(np.asarray(placed, np.float64),
                                              downsampling_resolution=0.01, num_neighbors=20)
        T = np.eye(4)
        for d in DISTANCES_M:
            res = small_gicp.align(pc, src, tree, init_T_target_source=T, registration_type=kind,
                                   max_correspondence_distance=d, num_threads=2,
                                   max_iterations=100)
            T = np.asarray(res.T_target_source)
        return PeerResult(T, time.perf_counter() - t0, used=res.num_inliers / len(placed),
                          converged=bool(res.converged), note=f"{res.iterations} iterations")
    except Exception as exc:  # noqa: BLE001
        return _failed(t0, exc)


# ------------------------------------------------------------------------------------ xdem
def lidar_dsm(cloud_world: np.ndarray, epsg: int):
    """A DSM of the lidar for xdem: the mean of the first returns in :data:`DSM_CELL_M` cells,
    NaN where a cell has none."""
    import rasterio
    import xdem

    c = DSM_CELL_M
    x0, y1 = np.floor(cloud_world[:, 0].min()), np.ceil(cloud_world[:, 1].max())
    cols = int(np.ceil((cloud_world[:, 0].max() - x0) / c)) + 1
    rows = int(np.ceil((y1 - cloud_world[:, 1].min()) / c)) + 1
    r = ((y1 - cloud_world[:, 1]) / c).astype(int)
    k = ((cloud_world[:, 0] - x0) / c).astype(int)
    flat = r * cols + k
    total = np.bincount(flat, weights=cloud_world[:, 2], minlength=rows * cols)
    count = np.bincount(flat, minlength=rows * cols)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.ma.masked_invalid((total / count).reshape(rows, cols).astype(np.float32))
    transform = rasterio.transform.from_origin(x0, y1, c, c)
    return xdem.DEM.from_array(z, transform=transform, crs=rasterio.crs.CRS.from_epsg(epsg),
                               nodata=-9999.0)


def xdem_coreg(method: str, placed: np.ndarray, origin: np.ndarray, dsm, epsg: int
               ) -> PeerResult:
    """``method``: ``NuthKaab``, ``ICP`` or ``LZD``; ``placed``: the placed tie points in the
    local frame whose origin in the lidar's CRS is ``origin``."""
    t0 = time.perf_counter()
    try:
        import geopandas as gpd
        import xdem

        world = placed + origin
        pts = gpd.GeoDataFrame({"z": world[:, 2]}, crs=f"EPSG:{epsg}",
                               geometry=gpd.points_from_xy(world[:, 0], world[:, 1]))
        coreg = getattr(xdem.coreg, method)()
        coreg.fit(dsm, pts, z_name="z", random_state=0)
        moved = coreg.apply(pts, z_name="z")
        after = np.column_stack([moved.geometry.x, moved.geometry.y, moved["z"]]) - origin
        rows = moved.index.to_numpy()  # the points xdem kept, by their row
        ok = np.all(np.isfinite(after), axis=1)
        return PeerResult(similarity_from_pairs(placed[rows[ok]], after[ok]),
                          time.perf_counter() - t0,
                          note=("shift" if method == "NuthKaab" else "rigid")
                          + f"; {ok.sum()} of {len(placed)} points moved")
    except Exception as exc:  # noqa: BLE001
        return _failed(t0, exc)
