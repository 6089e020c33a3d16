"""The calibration benchmark's speed block: time, memory and solvers (see calibration.py).

The speed block: 50 images (5 strips of 10, nadir, 600 m over a suburban world) and 5,000 tie
points. In a fresh process each (``--child``), so that the peak memory is the calibration's:

* ``tiereg calibrate`` on one and on two threads: seconds with and without reading the lidar,
  CPU seconds, peak resident memory (psutil, sampled every 50 ms);
* one adjustment from the same start (the registered model, the first round's control points):
  the lidar costs as Python callbacks on one thread (the first version; on two threads they
  deadlocked on the interpreter lock), as native Ceres costs on one and two threads, and the
  same problem with ``scipy.optimize.least_squares`` (method ``trf``, a finite-difference
  Jacobian with its sparsity given, ``x_scale="jac"``, the same soft-L1 losses).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

SPEED_PLAN = {"strips": 5, "images_per_strip": 10, "flying_height_m": 600.0}


def _python_plane_cost(normal, point, weight):
    """The first version's lidar cost: a pyceres cost function written in Python."""
    import pyceres

    class PlaneCost(pyceres.CostFunction):
        def __init__(self) -> None:
            pyceres.CostFunction.__init__(self)
            self.set_num_residuals(1)
            self.set_parameter_block_sizes([3])
            self._g = np.asarray(normal, dtype=np.float64) * weight
            self._c = float(self._g @ point)

        def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres' name
            x = parameters[0]
            residuals[0] = self._g[0] * x[0] + self._g[1] * x[1] + self._g[2] * x[2] - self._c
            if jacobians is not None and jacobians[0] is not None:
                jacobians[0][:] = self._g
            return True

    return PlaneCost()


def write_speed_block(folder: Path) -> dict:
    """The speed block's model, lidar and registration on disk; its size."""
    from calibration_blocks import make_block

    from tiereg.simulate.cameras import (
        CameraModel,
        FlightPlan,
        fitted_registration,
        flawed_model,
    )

    camera = CameraModel(2000, 1500, 2000.0, 1003.0, 748.0, k1=-0.03, k2=0.005)
    scene, block = make_block("suburban", False, FlightPlan(**SPEED_PLAN), camera, seed=4,
                              heading=20.0)
    rec, _ = flawed_model(block, focal_error=0.02, principal_px=(1000.0, 750.0))
    (folder / "model").mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(folder / "model"))
    np.save(folder / "lidar.npy", scene.lidar.xyz)
    np.save(folder / "T.npy", fitted_registration(rec, block).matrix)
    return {"images": int(len(block.centres)), "points": int(len(block.xyz)),
            "observations": int(len(block.uv)), "lidar_points": int(len(scene.lidar.xyz))}


def _child(folder: Path, mode: str, threads: int) -> dict:
    """Run in a fresh process: a whole calibration, or one adjustment with a solver."""
    from calibration_blocks import PeakMemory

    lidar = np.load(folder / "lidar.npy")
    T = np.load(folder / "T.npy")
    if mode == "calibrate":
        from tiereg.calibrate import calibrate

        with PeakMemory() as mem:
            c0 = time.process_time()
            r = calibrate(folder / "model", lidar, T_ref_mov=T, num_threads=threads)
            cpu = time.process_time() - c0
        cam = r.camera()
        return {"seconds": r.seconds, "lidar_read_seconds": r.solver["lidar_read_seconds"],
                "solve_seconds": r.solver["solve_seconds"], "cpu_seconds": cpu,
                "rounds": r.rounds, "iterations": r.solver["iterations"],
                "peak_rss_mb": mem.peak, "rss_before_mb": mem.start,
                "focal": cam.value("f"), "k1": cam.value("k1")}
    return _one_adjustment(folder, lidar, T, mode, threads)


def _start_state(folder: Path, lidar, T):
    """The registered model in the lidar's local frame and the first round's planes."""
    from tiereg.calibrate.adjust import refine_indices
    from tiereg.calibrate.lidar import LidarPatches, lidar_reference
    from tiereg.calibrate.model import observations, poses_points, read_model, transform_model
    from tiereg.calibrate.rounds import (
        check_split,
        pixel_sigma,
        plane_constraints,
        select_control,
        spread,
    )
    from tiereg.transform import Transform

    rec = read_model(folder / "model")
    ref = lidar_reference(lidar)
    transform_model(rec, Transform.from_translation(-ref.origin) @ Transform(T))
    obs = observations(rec)
    xyz = poses_points(rec, obs)[2]
    patches = LidarPatches.read(ref, xyz)
    p0 = patches.at(xyz)
    check = check_split(xyz) & p0.ok
    s0 = spread(p0, check, patches.floor_m)
    planes = plane_constraints(p0, select_control(p0, check, s0), obs.point_ids, s0)
    refine = {c: refine_indices(cam.model.name, ("focal", "principal", "distortion"))
              for c, cam in rec.cameras.items()}
    priors = {int(i): np.array(rec.images[int(i)].projection_center()) for i in obs.image_ids}
    return rec, obs, planes, refine, priors, pixel_sigma(rec, obs)


def _one_adjustment(folder: Path, lidar, T, mode: str, threads: int) -> dict:
    import importlib

    adjust_module = importlib.import_module("tiereg.calibrate.adjust")
    from tiereg.calibrate.adjust import Adjustment

    rec, obs, planes, refine, priors, sigma_px = _start_state(folder, lidar, T)
    if mode == "scipy":
        return scipy_adjustment(rec, obs, planes, priors, sigma_px)
    if mode == "python":
        adjust_module.plane_cost = _python_plane_cost
    adj = Adjustment(rec, sigma_px, refine, planes, priors, num_threads=threads,
                     focal_start={c: float(cam.params[0]) for c, cam in rec.cameras.items()})
    t = time.perf_counter()
    s = adj.solve().ceres_summary
    return {"seconds": time.perf_counter() - t, "iterations": s.num_successful_steps
            + s.num_unsuccessful_steps, "final_cost": s.final_cost,
            "threads_used": s.num_threads_used, "message": s.message,
            "focal": float(rec.cameras[1].params[0]), "k1": float(rec.cameras[1].params[3])}


def scipy_adjustment(rec, obs, planes, priors, sigma_px: float) -> dict:
    """The same adjustment with ``scipy.optimize.least_squares`` (see the module docstring)."""
    import scipy.sparse as sp
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    from tiereg.calibrate.adjust import GAUGE_SIGMA_M, LOSS_PIXELS
    from tiereg.calibrate.model import poses_points

    R, C, xyz = poses_points(rec, obs)
    m, n, k = len(C), len(xyz), len(obs.uv)
    row_of = {int(p): i for i, p in enumerate(obs.point_ids)}
    prow = np.array([row_of[int(p)] for p in planes.point_ids])
    unit = planes.normals / np.linalg.norm(planes.normals, axis=1, keepdims=True)
    xyz_p = xyz[prow]
    on_plane = xyz_p - np.einsum("ij,ij->i", xyz_p - planes.centroids, unit)[:, None] * unit
    g = planes.normals * (sigma_px / planes.sigma_m)[:, None]
    prior = np.array([priors[int(i)] for i in obs.image_ids])
    w_prior = sigma_px / np.array([GAUGE_SIGMA_M, GAUGE_SIGMA_M, 1e4])
    # the rotations as small rotation vectors applied to the start ones (a rotation vector of a
    # nadir camera itself is near pi, where it is singular)
    x0 = np.concatenate([np.asarray(rec.cameras[1].params, dtype=np.float64), np.zeros(3 * m),
                         C.ravel(), xyz.ravel()])
    oi, op = obs.obs_image, obs.obs_point

    def fun(x):
        f, cx, cy, k1, k2 = x[:5]
        rv = x[5:5 + 3 * m].reshape(m, 3)
        cc = x[5 + 3 * m:5 + 6 * m].reshape(m, 3)
        pts = x[5 + 6 * m:].reshape(n, 3)
        pc = Rotation.from_rotvec(rv[oi]).apply(
            np.einsum("kij,kj->ki", R[oi], pts[op] - cc[oi]))
        u, v = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
        r2 = u * u + v * v
        dist = 1 + k1 * r2 + k2 * r2 * r2
        reproj = np.column_stack([f * dist * u + cx, f * dist * v + cy]) - obs.uv
        plane = np.einsum("ij,ij->i", pts[prow] - on_plane, g)
        return np.concatenate([reproj.ravel(), plane, ((cc - prior) * w_prior).ravel()])

    J = sp.lil_matrix((2 * k + len(prow) + 3 * m, len(x0)), dtype=np.int8)
    rows = np.arange(k)
    for r in (2 * rows, 2 * rows + 1):
        for j in range(5):
            J[r, j] = 1
        for j in range(3):
            J[r, 5 + 3 * oi + j] = 1
            J[r, 5 + 3 * m + 3 * oi + j] = 1
            J[r, 5 + 6 * m + 3 * op + j] = 1
    for j in range(3):
        J[2 * k + np.arange(len(prow)), 5 + 6 * m + 3 * prow + j] = 1
        J[2 * k + len(prow) + 3 * np.arange(m) + j, 5 + 3 * m + 3 * np.arange(m) + j] = 1
    scale = np.concatenate([np.full(2 * k, LOSS_PIXELS * sigma_px),
                            np.full(len(prow), LOSS_PIXELS * sigma_px * planes.loss_widening),
                            np.full(3 * m, np.inf)])

    def soft_l1(z):  # Ceres' SoftLOneLoss(a) on each residual, a per residual
        a2 = scale**2
        t = np.sqrt(1 + z / a2)
        rho = np.where(np.isinf(a2), [z, np.ones_like(z), np.zeros_like(z)],
                       [2 * a2 * (t - 1), 1 / t, -0.5 / (a2 * t**3)])
        return rho

    t = time.perf_counter()
    res = least_squares(fun, x0, jac_sparsity=J.tocsr(), method="trf", x_scale="jac",
                        loss=soft_l1, ftol=1e-8, max_nfev=200)
    return {"seconds": time.perf_counter() - t, "iterations": int(res.nfev),
            "jacobians": int(res.njev), "final_cost": float(res.cost), "message": res.message,
            "focal": float(res.x[0]), "k1": float(res.x[3]), "threads_used": 1}


def _run_child(folder: Path, mode: str, threads: int) -> dict:
    env = {**os.environ, "PYTHONPATH": str(HERE) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    out = subprocess.run([sys.executable, str(Path(__file__)), "--child", str(folder), mode,
                          str(threads)], capture_output=True, text=True, env=env, check=False)
    if out.returncode != 0:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr.strip() else "?"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def speed_block(quick: bool) -> dict:
    """The speed block's measurements (see the module docstring)."""
    with tempfile.TemporaryDirectory(prefix="tiereg-calib-speed-") as tmp:
        folder = Path(tmp)
        out = {"block": write_speed_block(folder), "load_average": os.getloadavg()}
        for threads in (1, 2):
            out[f"calibrate_{threads}_threads"] = _run_child(folder, "calibrate", threads)
        out["solvers"] = solver_comparison(folder, quick)
        out["load_average_after"] = os.getloadavg()
    return out


def solver_comparison(folder: Path, quick: bool) -> dict:
    runs = {"ceres, Python lidar costs, 1 thread": ("python", 1),
            "ceres, native lidar costs, 1 thread": ("native", 1),
            "ceres, native lidar costs, 2 threads": ("native", 2)}
    if not quick:
        runs["scipy least_squares (trf, sparse finite differences)"] = ("scipy", 1)
    return {name: _run_child(folder, mode, threads) for name, (mode, threads) in runs.items()}


if __name__ == "__main__" and sys.argv[1:2] == ["--child"]:
    sys.path.insert(0, str(HERE))
    result = _child(Path(sys.argv[2]), sys.argv[3], int(sys.argv[4]))
    print(json.dumps(result, default=float))
