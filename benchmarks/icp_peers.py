"""Adapters that run peer fine-registration methods (ICP) side by side with tiereg's fine stage.

Every peer starts from the same pose (tiereg's coarse answer) and gets the same data: the tie
points placed by that pose and the lidar's first returns (the visible surface, which is what the
tie points see), both in a local frame centred near the data so that no peer loses precision to
coordinates in the millions. Each answer is the increment ``T_ref_start`` (4x4) that takes the
placed tie points onto the lidar; the benchmark composes it with the start.

* ``cloudcompare_icp`` -- CloudCompare's command line ICP (``-ICP``) with scale adjustment
  (``-ADJUST_SCALE``), as its documentation shows: the first cloud opened is the data (aligned),
  the second the model. Random sampling is off (its limit, which also thins the model, is set
  above the number of points: a sampled lidar would be far too sparse here), the run stops
  when the RMS improves by less than ``1e-6`` or after 100 iterations; the registration matrix is
  read from the text file CloudCompare writes next to the data. It needs the Debian package
  ``cloudcompare`` and runs headless with ``QT_QPA_PLATFORM=offscreen``.
* ``open3d_icp_point`` -- Open3D's ``registration_icp`` with the point-to-point estimator with
  scaling (Besl & McKay 1992; Umeyama 1991), the documented ICP tutorial, coarse to fine in
  correspondence distance.
* ``open3d_icp_plane`` -- the same with the point-to-plane estimator (Chen & Medioni 1992; no
  scale), target normals from 30 neighbours.

A peer that is missing or fails returns the identity and the reason in ``note``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ICP_ITERATIONS = 100


@dataclass(frozen=True)
class IcpEstimate:
    T_ref_start: np.ndarray  # 4x4: placed tie points -> reference (local frame)
    seconds: float
    note: str = ""
    ok: bool = True


def _failed(t0: float, note: str) -> IcpEstimate:
    return IcpEstimate(np.eye(4), time.perf_counter() - t0, note, ok=False)


def cloudcompare_available() -> str | None:
    return shutil.which("CloudCompare") or shutil.which("cloudcompare")


def run_cloudcompare_icp(placed: np.ndarray, lidar: np.ndarray, *, overlap_pct: int = 90,
                         timeout_s: float = 600.0) -> IcpEstimate:
    """CloudCompare ICP with scale of ``placed`` (data) onto ``lidar`` (model); the time is the
    whole CloudCompare process (start-up and reading the two binary PLY files included)."""
    t0 = time.perf_counter()
    exe = cloudcompare_available()
    if exe is None:
        return _failed(t0, "CloudCompare not installed (Debian package cloudcompare)")
    with tempfile.TemporaryDirectory(prefix="tiereg-cc-") as tmp:
        from tiereg.io.ply import write_ply

        data, model = Path(tmp) / "data.ply", Path(tmp) / "model.ply"
        write_ply(data, placed)
        write_ply(model, lidar)
        cmd = [exe, "-SILENT", "-NO_TIMESTAMP", "-AUTO_SAVE", "OFF",
               "-O", "-GLOBAL_SHIFT", "0", "0", "0", str(data),
               "-O", "-GLOBAL_SHIFT", "0", "0", "0", str(model),
               "-ICP", "-ADJUST_SCALE", "-ITER", str(ICP_ITERATIONS), "-MIN_ERROR_DIFF", "1e-6",
               "-OVERLAP", str(overlap_pct),
               "-RANDOM_SAMPLING_LIMIT", str(len(placed) + len(lidar))]
        env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
        t_run = time.perf_counter()
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=env,
                                  check=False)
        except subprocess.TimeoutExpired:
            return _failed(t0, f"CloudCompare timed out after {timeout_s:.0f} s")
        seconds = time.perf_counter() - t_run
        found = sorted(Path(tmp).glob("*REGISTRATION_MATRIX*.txt"))
        if not found:
            tail = (proc.stdout + proc.stderr).strip().splitlines()[-3:]
            return _failed(t0, f"CloudCompare wrote no matrix (exit {proc.returncode}): "
                           + " | ".join(tail))
        M = np.loadtxt(found[0]).reshape(4, 4)
    return IcpEstimate(M, seconds, "CloudCompare -ICP -ADJUST_SCALE")


def _open3d():
    import open3d as o3d  # optional benchmark dependency

    return o3d


def run_open3d_icp(placed: np.ndarray, lidar: np.ndarray, *, plane: bool,
                   distances_m: tuple[float, ...]) -> IcpEstimate:
    """Open3D ICP, one run per correspondence distance in ``distances_m`` (coarse to fine)."""
    t0 = time.perf_counter()
    try:
        o3d = _open3d()
    except Exception as exc:  # noqa: BLE001 -- optional dependency or its libraries missing
        return _failed(t0, f"Open3D unavailable: {type(exc).__name__}: {exc}")
    reg = o3d.pipelines.registration
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(placed, np.float64)))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(lidar, np.float64)))
    if plane:
        tgt.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=30))
        estimator = reg.TransformationEstimationPointToPlane()
    else:
        estimator = reg.TransformationEstimationPointToPoint(with_scaling=True)
    T = np.eye(4)
    criteria = reg.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7,
                                          max_iteration=ICP_ITERATIONS)
    fitness = rmse = float("nan")
    try:
        for d in distances_m:
            res = reg.registration_icp(src, tgt, d, T, estimator, criteria)
            T = np.asarray(res.transformation)
            fitness, rmse = float(res.fitness), float(res.inlier_rmse)
    except RuntimeError as exc:  # e.g. no normals on an empty or degenerate target
        return _failed(t0, f"Open3D: {str(exc).strip()[-120:]}")
    kind = "point-to-plane" if plane else "point-to-point with scaling"
    return IcpEstimate(T, time.perf_counter() - t0,
                       f"{kind}; fitness {fitness:.2f}, inlier RMSE {rmse:.3f}")
