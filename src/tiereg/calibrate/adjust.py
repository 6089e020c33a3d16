"""The self-calibrating bundle adjustment: COLMAP's reprojection costs and lidar planes in Ceres.

One Ceres problem (pycolmap's bundle adjuster, through pyceres) holds

* the reprojection error of every observation (COLMAP's own cost functions, the camera's own
  model), with a robust (soft L1) loss at twice the pixel noise;
* one lidar constraint per control point: the normal distance of the tie point to the tangent
  plane of its lidar patch (:mod:`tiereg.calibrate.lidar`; on level patches the height),
  divided by the patch's standard deviation, robust too; a native Ceres cost
  (:func:`plane_cost`), so that Ceres evaluates every cost on all its threads;
* a weak prior on the horizontal position of every camera centre (the registration's), which
  fixes the horizontal datum where the lidar is flat (see :data:`GAUGE_SIGMA_M`).

Held intrinsics are fixed parameter by parameter (``SubsetManifold``). :func:`reduced_covariance`
gives the covariance of the intrinsics and poses (the points eliminated: the Schur complement of
the normal matrix at the solution), from which degenerate parameters are found.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from .model import MODELS, pycolmap_module

log = logging.getLogger(__name__)

# Horizontal prior of each camera centre at its registered position: only the datum in x, y and
# the heading where the lidar's planes are level and say nothing horizontally. Weak on purpose:
# the registered positions of a bent block are metres off, and a prior of sigma s on M centres
# spread over D also says the scale to s / D / sqrt(M), which must not decide the focal length
GAUGE_SIGMA_M = 100.0
# the focal length stays within this share of its input value: a block that does not determine
# it (level ground seen from above) may otherwise collapse towards f = 0 with the cameras on the
# ground, where every tie point lies on its plane
FOCAL_BOUND = 0.1
LOSS_PIXELS = 2.0  # robust loss scale in units of the pixel noise
# the robust loss of every residual: soft L1 (Ceres' SoftLOneLoss) took 14 iterations on a
# 50-image block where Cauchy's loss, not convex, took 56 short steps
LOSS = "soft_l1"
# the weight of a plane constraint along the plane, relative to across it (see plane_cost)
PLANE_EPS = 1e-8


def _pyceres():
    pycolmap_module()
    import pyceres

    return pyceres


@dataclass(frozen=True, eq=False)
class PlaneConstraints:
    """Lidar constraints on tie points: ``normal . (X - centroid) = 0`` with ``sigma_m``."""

    point_ids: np.ndarray = field(repr=False)  # (L,) point3D ids
    centroids: np.ndarray = field(repr=False)  # (L, 3) frame of the adjustment
    normals: np.ndarray = field(repr=False)  # (L, 3) unit; on level patches n / n_z
    sigma_m: np.ndarray = field(repr=False)  # (L,)
    loss_widening: float = 1.0  # the robust loss of the planes this many times wider


def plane_cost(normal: np.ndarray, point: np.ndarray, weight: float):
    """A native Ceres cost on one 3-D point X: ``weight * normal . (X - point)``, where ``point``
    lies on the plane (the tie point's start projected onto it).

    A point-to-plane distance is linear in X, so it is Ceres' ``NormalPrior``
    ``||A (X - point)||`` with ``A^T A = g g^T + EPS |g|^2 I`` (``g = weight * normal``): the
    normal distance at full weight and the position along the plane at a weight ``1 / EPS``
    times lower, which keeps the information matrix invertible and pulls nowhere measurable
    (``point`` is where the tie point starts). Being C++, the cost runs in Ceres' threads.
    """
    g = np.asarray(normal, dtype=np.float64) * weight
    info = np.outer(g, g) + PLANE_EPS * float(g @ g) * np.eye(3)
    return _pyceres().factors.NormalPrior(np.asarray(point, dtype=np.float64),
                                          np.linalg.inv(info))


def robust_loss(scale: float):
    """The pyceres loss of :data:`LOSS` at ``scale``."""
    pyceres = _pyceres()
    return {"soft_l1": pyceres.SoftLOneLoss, "cauchy": pyceres.CauchyLoss,
            "huber": pyceres.HuberLoss}[LOSS](scale)


def solver_threads() -> int:
    """Threads for Ceres: the cores this process may use (all lidar costs are native)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not on Linux
        return max(1, os.cpu_count() or 1)


@dataclass
class Adjustment:
    """A bundle adjustment of ``rec`` in place (see the module docstring)."""

    rec: object
    pixel_sigma: float
    refine: dict[int, tuple[int, ...]]  # per camera id: the indices of its params to refine
    planes: PlaneConstraints | None
    centre_priors: dict[int, np.ndarray]  # image id -> prior camera centre
    refine_poses: bool = True
    focal_start: dict[int, float] = field(default_factory=dict)  # the bounds' centre
    max_iterations: int = 100
    num_threads: int = 0  # 0: solver_threads()
    adjuster: object = None
    _keep: list = field(default_factory=list)

    def _options(self):
        pycolmap = pycolmap_module()
        options = pycolmap.BundleAdjustmentOptions(
            refine_focal_length=True, refine_principal_point=True, refine_extra_params=True,
            refine_rig_from_world=self.refine_poses, print_summary=False)
        options.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, LOSS.upper())
        options.ceres.loss_function_scale = LOSS_PIXELS * self.pixel_sigma
        solver = options.ceres.solver_options
        solver.max_num_iterations = self.max_iterations
        solver.function_tolerance = 1e-8
        solver.num_threads = self.num_threads or solver_threads()
        # every cost is native, so Ceres may evaluate them on all threads at any problem size
        options.ceres.min_num_residuals_for_cpu_multi_threading = 1
        return options

    def build(self) -> None:
        pycolmap = pycolmap_module()
        config = pycolmap.BundleAdjustmentConfig()
        for image_id in self.rec.reg_image_ids():
            config.add_image(image_id)
        self.adjuster = pycolmap.create_default_ceres_bundle_adjuster(
            self._options(), config, self.rec)
        self._intrinsics(self.adjuster.problem)
        if self.planes is not None:
            self._planes(self.adjuster.problem)
        self._centre_priors(self.adjuster.problem)

    def _intrinsics(self, problem) -> None:
        """Held intrinsics fixed (``SubsetManifold``), focal lengths bounded."""
        pyceres = _pyceres()
        for cam_id, cam in self.rec.cameras.items():
            free = self.refine.get(cam_id, ())
            params = cam.params
            self._keep.append(params)  # Ceres keeps raw pointers: the arrays must outlive it
            if not problem.has_parameter_block(params):
                continue
            n = len(params)
            held = [i for i in range(n) if i not in free]
            for i in MODELS[cam.model.name]["focal"]:  # no collapse onto the ground
                if i in free:
                    f0 = self.focal_start.get(cam_id, params[i])
                    problem.set_parameter_lower_bound(params, i, (1 - FOCAL_BOUND) * f0)
                    problem.set_parameter_upper_bound(params, i, (1 + FOCAL_BOUND) * f0)
            if len(held) == n:
                problem.set_parameter_block_constant(params)
            elif held:
                manifold = pyceres.SubsetManifold(n, held)
                self._keep.append(manifold)
                problem.set_manifold(params, manifold)

    def _planes(self, problem) -> None:
        """One native plane cost per control point, robust at the planes' width."""
        pl = self.planes
        wide = robust_loss(LOSS_PIXELS * self.pixel_sigma * pl.loss_widening)
        self._keep.append(wide)
        for pid, c, nrm, s in zip(pl.point_ids, pl.centroids, pl.normals, pl.sigma_m):
            xyz = self.rec.points3D[int(pid)].xyz
            self._keep.append(xyz)
            if not problem.has_parameter_block(xyz):
                continue
            unit = nrm / np.linalg.norm(nrm)
            on_plane = xyz - float(unit @ (xyz - c)) * unit
            cost = plane_cost(nrm, on_plane, self.pixel_sigma / s)
            self._keep.append(cost)
            problem.add_residual_block(cost, wide, [xyz])

    def _centre_priors(self, problem) -> None:
        import pycolmap.cost_functions as cf

        cov = np.diag([GAUGE_SIGMA_M**2, GAUGE_SIGMA_M**2, 1e8]) / self.pixel_sigma**2
        for image_id, prior in self.centre_priors.items():
            pose = self.rec.frames[self.rec.images[image_id].frame_id].rig_from_world.params
            self._keep.append(pose)
            if problem.has_parameter_block(pose):
                cost = cf.AbsolutePosePositionPriorCost(cov, prior)
                self._keep.append(cost)
                problem.add_residual_block(cost, None, [pose])

    def solve(self) -> object:
        if self.adjuster is None:
            self.build()
        return self.adjuster.solve()

    def parameter_blocks(self) -> tuple[list, list, list]:
        """The variable parameter blocks: cameras (id, params), poses, points (id, xyz)."""
        problem = self.adjuster.problem
        cams = [(cid, c.params) for cid, c in sorted(self.rec.cameras.items())
                if problem.has_parameter_block(c.params)
                and not problem.is_parameter_block_constant(c.params)]
        poses = []
        for image_id in sorted(self.rec.reg_image_ids()):
            p = self.rec.frames[self.rec.images[image_id].frame_id].rig_from_world.params
            if problem.has_parameter_block(p) and not problem.is_parameter_block_constant(p):
                poses.append((image_id, p))
        points = [(pid, self.rec.points3D[pid].xyz) for pid in sorted(self.rec.point3D_ids())]
        points = [(pid, x) for pid, x in points if problem.has_parameter_block(x)]
        return cams, poses, points


def reduced_covariance(adj: Adjustment) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Covariance (pixel noise ``adj.pixel_sigma``) of the free intrinsics, the points
    eliminated, and for each of its rows ``(camera id, index into params)``.

    The normal matrix ``N = J^T J`` of the robustly weighted Jacobian at the solution is reduced
    to the cameras' and poses' tangent parameters (Schur complement over the points), inverted
    by eigen-decomposition (a near-singular direction gives a huge variance, not an error).
    """
    pyceres = _pyceres()
    cams, poses, points = adj.parameter_blocks()
    problem = adj.adjuster.problem
    blocks = [p for _, p in cams] + [p for _, p in poses] + [x for _, x in points]
    opts = pyceres.EvaluateOptions()
    opts.set_parameter_blocks(blocks)
    opts.apply_loss_function = True
    crs = problem.evaluate_jacobian(opts)
    J = sp.csr_matrix((np.asarray(crs.values), np.asarray(crs.cols), np.asarray(crs.rows)),
                      shape=(crs.num_rows, crs.num_cols))
    labels = []
    for cid, params in cams:
        free = [i for i in range(len(params)) if i in adj.refine.get(cid, ())]
        labels += [(cid, i) for i in free]
    n_cam = len(labels)
    n_outer = n_cam + sum(problem.parameter_block_tangent_size(p) for _, p in poses)
    N = (J.T @ J).tocsr()
    A = N[:n_outer, :n_outer].toarray()
    B = N[:n_outer, n_outer:]
    C = N[n_outer:, n_outer:].toarray() if len(points) < 2 else None
    if C is None:
        n_pts = (N.shape[0] - n_outer) // 3
        diag = np.zeros((n_pts, 3, 3))
        Cs = N[n_outer:, n_outer:].tocoo()
        diag[Cs.row // 3, Cs.row % 3, Cs.col % 3] = Cs.data
        inv = np.linalg.pinv(diag + np.eye(3) * 1e-12)
        Cinv = sp.block_diag(list(inv), format="csr")
    else:
        Cinv = sp.csr_matrix(np.linalg.pinv(C))
    S = A - (B @ Cinv @ B.T).toarray()
    w, V = np.linalg.eigh((S + S.T) / 2)
    w = np.maximum(w, w.max() * 1e-15)
    cov = (V / w) @ V.T * adj.pixel_sigma**2
    return cov[:n_cam, :n_cam], labels


def refine_indices(model_name: str, refine: tuple[str, ...]) -> tuple[int, ...]:
    """Indices into a camera's params for the kinds of intrinsics in ``refine``."""
    kinds = MODELS[model_name]
    out: list[int] = []
    for kind in ("focal", "principal", "distortion"):
        if kind in refine:
            out += kinds[kind]
    return tuple(sorted(out))
