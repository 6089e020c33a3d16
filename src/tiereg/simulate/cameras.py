"""Image blocks with known cameras: intrinsics with distortion, poses, 2-D observations.

A :class:`CameraBlock` flies a :class:`FlightPlan` over a scene (strips, optionally cross strips
and tilted views), sees the scene's tie points (on the visible surface; its blunders become
features the lidar does not have, such as vehicles that moved) through a COLMAP ``RADIAL``
camera (:class:`CameraModel`), and records their pixel positions with Gaussian noise. Everything
is in the reference (lidar) frame, so the truth of every intrinsic, pose and point is known.

:func:`flawed_model` turns a block into what a structure-from-motion program would have made of
it with a focal length a little off and the lens distortion ignored (held fixed during its
bundle adjustment): a COLMAP model in an arbitrary frame whose shape is bent (domed, scaled) by
the wrong camera, as a calibration's input.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..transform import Transform
from .scene import Scene


@dataclass(frozen=True)
class CameraModel:
    """A COLMAP ``RADIAL`` camera: ``f, cx, cy, k1, k2`` (pixels; distortion on normalized
    image coordinates, ``u = f (1 + k1 r^2 + k2 r^4) x + cx``)."""

    width_px: int = 4000
    height_px: int = 3000
    focal_px: float = 4000.0
    cx_px: float = 2000.0
    cy_px: float = 1500.0
    k1: float = 0.0
    k2: float = 0.0

    @property
    def params(self) -> np.ndarray:
        return np.array([self.focal_px, self.cx_px, self.cy_px, self.k1, self.k2])

    @classmethod
    def random(cls, rng: np.random.Generator, *, width_px: int = 4000,
               height_px: int = 3000) -> CameraModel:
        """A plausible aerial camera: focal 0.8-1.2 image widths, principal point within 1 %
        of the centre, barrel or pincushion distortion of 10-50 pixels at the image corner."""
        f = width_px * rng.uniform(0.8, 1.2)
        r2 = ((width_px / 2) ** 2 + (height_px / 2) ** 2) / f**2  # corner, normalized
        k1 = rng.choice([-1, 1]) * rng.uniform(10, 50) / (f * r2)
        k2 = -0.2 * k1 * rng.uniform(0, 1)
        return cls(width_px, height_px, float(f),
                   float(width_px / 2 + rng.uniform(-0.01, 0.01) * width_px),
                   float(height_px / 2 + rng.uniform(-0.01, 0.01) * height_px),
                   float(k1), float(k2))

    def project(self, R_cam_ref: np.ndarray, centre: np.ndarray,
                xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel positions ``(N, 2)`` of points ``(N, 3)`` in one camera, and whether each is in
        front of it and inside the image."""
        pc = (xyz - centre) @ R_cam_ref.T
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = pc[:, 0] / z, pc[:, 1] / z
        r2 = x * x + y * y
        d = 1 + self.k1 * r2 + self.k2 * r2 * r2
        uv = np.column_stack([self.focal_px * d * x + self.cx_px,
                              self.focal_px * d * y + self.cy_px])
        inside = ((z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < self.width_px)
                  & (uv[:, 1] >= 0) & (uv[:, 1] < self.height_px) & (r2 < 1.0))
        return uv, inside


@dataclass(frozen=True)
class FlightPlan:
    """Parallel strips over the block centre, along the scene's block heading.

    ``cross``: as many strips again at right angles. ``tilt_deg``: the camera looks that far
    forward on odd strips and backward on even ones (0: nadir).
    """

    strips: int = 3
    images_per_strip: int = 6
    flying_height_m: float = 600.0  # above the block's median ground height
    forward_overlap: float = 0.6
    side_overlap: float = 0.3
    cross: bool = False
    tilt_deg: float = 0.0

    @property
    def n_images(self) -> int:
        return self.strips * self.images_per_strip * (2 if self.cross else 1)


@dataclass(frozen=True, eq=False)
class CameraBlock:
    """An image block with its truth, all in the reference frame (file coordinates)."""

    camera: CameraModel
    plan: FlightPlan
    R_cam_ref: np.ndarray = field(repr=False)  # (M, 3, 3) reference -> camera
    centres: np.ndarray = field(repr=False)  # (M, 3)
    xyz: np.ndarray = field(repr=False)  # (N, 3) true points
    off_lidar: np.ndarray = field(repr=False)  # (N,) features the lidar does not have
    obs_image: np.ndarray = field(repr=False)  # (K,)
    obs_point: np.ndarray = field(repr=False)  # (K,)
    uv: np.ndarray = field(repr=False)  # (K, 2) observed (noisy) pixel positions
    pixel_noise_px: float = 0.5


def _poses(scene: Scene, plan: FlightPlan, camera: CameraModel,
           ground_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Camera rotations (reference -> camera) and centres of the flight plan."""
    H = plan.flying_height_m
    along = H * camera.height_px / camera.focal_px  # image y along the flight
    across = H * camera.width_px / camera.focal_px
    base, spacing = along * (1 - plan.forward_overlap), across * (1 - plan.side_overlap)
    u = (np.arange(plan.images_per_strip) - (plan.images_per_strip - 1) / 2) * base
    v = (np.arange(plan.strips) - (plan.strips - 1) / 2) * spacing
    georef = np.asarray(scene.spec.georef, dtype=np.float64)
    centre = np.array([*scene.block_centre, ground_m]) + georef
    R_out, C_out = [], []
    for turn in ((0.0, 90.0) if plan.cross else (0.0,)):
        h = np.radians(scene.block_heading_deg + turn)
        d, n = np.array([np.cos(h), np.sin(h), 0.0]), np.array([-np.sin(h), np.cos(h), 0.0])
        for s, vs in enumerate(v):
            tilt = np.radians(plan.tilt_deg) * (1 if s % 2 else -1)
            # camera axes in the reference frame: y along the flight, z down, tilted about x
            z = np.array([0.0, 0.0, -1.0]) * np.cos(tilt) + d * np.sin(tilt)
            y = d * np.cos(tilt) + np.array([0.0, 0.0, 1.0]) * np.sin(tilt)
            x = np.cross(y, z)
            R = np.vstack([x, y, z])
            for us in u:
                # tilted views are moved back so that they look at the same ground
                C_out.append(centre + us * d + vs * n + [0, 0, H] - d * H * np.tan(tilt))
                R_out.append(R)
    return np.array(R_out), np.array(C_out)


def make_camera_block(scene: Scene, plan: FlightPlan = FlightPlan(),
                      camera: CameraModel = CameraModel(), *, pixel_noise_px: float = 0.5,
                      min_views: int = 3, max_points: int | None = None,
                      seed: int = 0) -> CameraBlock:
    """Fly ``plan`` over ``scene`` with ``camera``: poses, the scene's tie points seen in at
    least ``min_views`` images (at most ``max_points`` of them), noisy pixel observations."""
    rng = np.random.default_rng([seed, 7])
    georef = np.asarray(scene.spec.georef, dtype=np.float64)
    ties = scene.tie_points
    ground = float(np.median(ties.true_xyz[:, 2]))
    R, C = _poses(scene, plan, camera, ground)
    # true 3-D features: the surface points; a blunder is a real feature off the lidar surface
    xyz = np.where(ties.blunder[:, None], ties.xyz, ties.true_xyz) + georef
    oi, op, uv = [], [], []
    for i in range(len(C)):
        p, inside = camera.project(R[i], C[i], xyz)
        k = np.flatnonzero(inside)
        oi.append(np.full(len(k), i))
        op.append(k)
        uv.append(p[k])
    obs_image, obs_point, uv_all = np.concatenate(oi), np.concatenate(op), np.concatenate(uv)
    views = np.bincount(obs_point, minlength=len(xyz))
    keep = np.flatnonzero(views >= min_views)
    if max_points is not None and len(keep) > max_points:
        keep = np.sort(rng.choice(keep, size=max_points, replace=False))
    new = np.full(len(xyz), -1)
    new[keep] = np.arange(len(keep))
    sel = new[obs_point] >= 0
    uv_noisy = uv_all[sel] + rng.normal(0, pixel_noise_px, (int(sel.sum()), 2))
    return CameraBlock(camera, plan, R, C, xyz[keep], ties.blunder[keep].copy(),
                       obs_image[sel], new[obs_point[sel]], uv_noisy, pixel_noise_px)


def block_model(block: CameraBlock, camera: CameraModel | None = None, *,
                T_model_ref: Transform | None = None):
    """The block as a :class:`pycolmap.Reconstruction` with ``camera`` (default: the true one),
    the true poses and points, moved into a model frame by ``T_model_ref``."""
    from ..calibrate.model import build_model, transform_model

    cam = camera or block.camera
    rec = build_model({1: ("RADIAL", cam.width_px, cam.height_px, cam.params)},
                      np.ones(len(block.centres), dtype=np.int64), block.R_cam_ref,
                      block.centres, block.xyz, block.obs_image, block.obs_point, block.uv)
    if T_model_ref is not None:
        transform_model(rec, T_model_ref)
    return rec


def flawed_model(block: CameraBlock, *, focal_error: float = 0.02, ignore_distortion: bool = True,
                 principal_px: tuple[float, float] | None = None,
                 T_model_ref: Transform | None = None, seed: int = 0):
    """What structure from motion makes of ``block`` with the focal length off by
    ``focal_error`` (relative), with ``ignore_distortion`` no distortion, and the principal
    point at ``principal_px`` (default: the true one; the image centre is what a program
    assumes without a calibration): a bundle adjustment of the poses and points with those
    intrinsics held fixed, moved into a model frame by ``T_model_ref`` (default: a random
    similarity of scale 0.25-4 about the block).

    Returns ``(reconstruction, T_model_ref)``.
    """
    import pycolmap

    cam = block.camera
    cx, cy = (cam.cx_px, cam.cy_px) if principal_px is None else principal_px
    wrong = CameraModel(cam.width_px, cam.height_px, cam.focal_px * (1 + focal_error),
                        float(cx), float(cy), 0.0 if ignore_distortion else cam.k1,
                        0.0 if ignore_distortion else cam.k2)
    # adjusted near the origin: the reference's large coordinates would cost digits
    origin = np.round(block.centres.mean(axis=0))
    rec = block_model(block, wrong, T_model_ref=Transform.from_translation(-origin))
    options = pycolmap.BundleAdjustmentOptions(refine_focal_length=False,
                                               refine_principal_point=False,
                                               refine_extra_params=False, print_summary=False)
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = 2.0 * block.pixel_noise_px
    pycolmap.bundle_adjustment(rec, options)
    if T_model_ref is None:
        rng = np.random.default_rng([seed, 11])
        scale = float(np.exp(rng.uniform(np.log(0.25), np.log(4.0))))
        angles = np.radians([rng.normal(0, 2), rng.normal(0, 2), rng.uniform(0, 360)])
        T_model_ref = (Transform.from_translation(rng.uniform(-1000, 1000, 3))
                       @ Transform.from_parameters(scale=scale, omega=angles[0], phi=angles[1],
                                                   kappa=angles[2])
                       @ Transform.from_translation(-origin))
    from ..calibrate.model import transform_model

    transform_model(rec, T_model_ref @ Transform.from_translation(origin))
    return rec, T_model_ref


def flat_world(world):
    """The world with level bare ground at height 0 everywhere (no relief, buildings or trees):
    a nadir block over it cannot separate the focal length from the flying height."""
    from dataclasses import replace

    zero = np.zeros_like(world.dsm)
    return replace(world, dtm=zero, dsm=zero.copy(), canopy=np.zeros_like(world.canopy),
                   buildings=np.zeros_like(world.buildings))


def fitted_registration(rec, block: CameraBlock) -> Transform:
    """The similarity (model -> reference) that best fits the model's points to the true ones
    (least squares, Umeyama 1991): a registration as good as the model's shape allows, for
    calibrating without registering first."""
    from ..calibrate.model import model_arrays

    a = model_arrays(rec)
    X, Y = a.xyz, block.xyz[a.point_ids - 1]
    mx, my = X.mean(axis=0), Y.mean(axis=0)
    U, S, Vt = np.linalg.svd((Y - my).T @ (X - mx) / len(X))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / ((X - mx) ** 2).sum() * len(X))
    return Transform.from_similarity(s, R, my - s * R @ mx)
