"""COLMAP models with their images and 2-D observations, through pycolmap.

tiereg's own COLMAP reader (:mod:`tiereg.io.colmap`) reads points and camera centres; calibration
needs the whole model (cameras, images, their 2-D points and the tracks), read and written as
COLMAP does it, so it goes through :class:`pycolmap.Reconstruction`. Models are moved between
frames with a :class:`~tiereg.transform.Transform` (a similarity).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError, MissingDependencyError, OutputError
from ..transform import Transform

log = logging.getLogger(__name__)

# COLMAP camera models whose parameters calibration refines, with the index of each kind of
# parameter in ``Camera.params``: focal lengths, principal point, radial distortion (k1, k2)
MODELS = {
    "SIMPLE_PINHOLE": {"focal": (0,), "principal": (1, 2), "distortion": ()},
    "PINHOLE": {"focal": (0, 1), "principal": (2, 3), "distortion": ()},
    "SIMPLE_RADIAL": {"focal": (0,), "principal": (1, 2), "distortion": (3,)},
    "RADIAL": {"focal": (0,), "principal": (1, 2), "distortion": (3, 4)},
    "OPENCV": {"focal": (0, 1), "principal": (2, 3), "distortion": (4, 5, 6, 7)},
}
MIN_IMAGES = 3
MIN_POINTS = 20


def pycolmap_module():
    """pycolmap, or a one-line error saying how to install it."""
    try:
        import pycolmap
    except ImportError:  # pragma: no cover - the calibrate extra installs it
        raise MissingDependencyError(
            "calibration needs pycolmap and pyceres; install them with "
            "`pip install 'tiereg[calibrate]'`") from None
    return pycolmap


def with_radial(camera):
    """The camera as a RADIAL camera (f, cx, cy, k1, k2) when its model has fewer distortion
    terms (SIMPLE_PINHOLE, SIMPLE_RADIAL): calibration estimates k1 and k2. Other supported
    models are kept."""
    pycolmap = pycolmap_module()
    name = camera.model.name
    if name not in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL"):
        return camera
    p = np.asarray(camera.params, dtype=np.float64)
    k1 = float(p[3]) if name == "SIMPLE_RADIAL" else 0.0
    return pycolmap.Camera(model="RADIAL", width=camera.width, height=camera.height,
                           params=[p[0], p[1], p[2], k1, 0.0], camera_id=camera.camera_id)


def read_model(path: str | os.PathLike[str]):
    """A COLMAP model folder (``.bin`` or ``.txt``) as a :class:`pycolmap.Reconstruction`, with
    its cameras as RADIAL where they had fewer distortion terms; a one-line
    :class:`~tiereg.errors.InputError` when it cannot be used for calibration."""
    pycolmap = pycolmap_module()
    folder = Path(path)
    if not folder.is_dir():
        raise InputError(f"{folder}: MODEL must be a COLMAP model folder (cameras, images, "
                         "points3D as .bin or .txt), e.g. sparse/0")
    have = {p.name for p in folder.iterdir()}
    for stem in ("cameras", "images", "points3D"):
        if f"{stem}.bin" not in have and f"{stem}.txt" not in have:
            raise InputError(f"{folder}: no {stem}.bin or {stem}.txt; calibration needs the "
                             "whole COLMAP model (cameras, images with their 2-D points, "
                             "points3D)")
    try:
        rec = pycolmap.Reconstruction(str(folder))
    except Exception as exc:  # pycolmap raises plain runtime errors with long messages
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"{folder}: COLMAP cannot read this model ({first[:120]}); "
                         "re-export it from COLMAP") from None
    check_model(rec, folder)
    for cam_id, cam in list(rec.cameras.items()):
        if cam.model.name not in MODELS:
            raise InputError(f"{folder}: camera {cam_id} has the {cam.model.name} model; "
                             f"calibration supports {', '.join(MODELS)}")
        radial = with_radial(cam)
        if radial is not cam:
            rec.cameras[cam_id] = radial
    return rec


def check_model(rec, folder: Path | str) -> None:
    """A model calibration can work on: enough registered images, points and observations."""
    n_img, n_pts = rec.num_reg_images(), rec.num_points3D()
    if n_img < MIN_IMAGES or n_pts < MIN_POINTS:
        raise InputError(f"{folder}: the model has {n_img} registered images and {n_pts} "
                         f"points; calibration needs at least {MIN_IMAGES} images and "
                         f"{MIN_POINTS} points seen in them")
    if rec.compute_num_observations() < 2 * n_pts:
        raise InputError(f"{folder}: the points have no 2-D observations in the images (empty "
                         "tracks); give the model COLMAP reconstructed, not exported points")


def transform_model(rec, T: Transform) -> None:
    """Move the model (cameras, points) by the similarity ``T`` (new frame <- old), in place."""
    pycolmap = pycolmap_module()
    s = T.scale
    R = T.matrix[:3, :3] / s
    rec.transform(pycolmap.Sim3d(s, pycolmap.Rotation3d(R), T.matrix[:3, 3]))


def write_model(rec, folder: str | os.PathLike[str]) -> Path:
    """Write the model as binary and text COLMAP files into ``folder`` (made if missing)."""
    out = Path(folder)
    try:
        out.mkdir(parents=True, exist_ok=True)
        rec.write_binary(str(out))
        rec.write_text(str(out))
    except OSError as exc:
        raise OutputError(f"{out}: cannot write the model ({exc.strerror}); "
                          "choose a writable output folder") from None
    return out


@dataclass(frozen=True, eq=False)
class Observations:
    """The model's observations in a fixed order (they do not change during calibration)."""

    image_ids: np.ndarray = field(repr=False)  # (M,)
    camera_of_image: np.ndarray = field(repr=False)  # (M,) camera id of each image
    point_ids: np.ndarray = field(repr=False)  # (N,)
    obs_image: np.ndarray = field(repr=False)  # (K,) row into the image arrays
    obs_point: np.ndarray = field(repr=False)  # (K,) row into the point arrays
    uv: np.ndarray = field(repr=False)  # (K, 2) observed pixel positions


@dataclass(frozen=True, eq=False)
class ModelArrays:
    """The model as arrays (one frame): poses, points and observations in a fixed order."""

    image_ids: np.ndarray = field(repr=False)  # (M,)
    camera_of_image: np.ndarray = field(repr=False)  # (M,) camera id of each image
    R_cam_world: np.ndarray = field(repr=False)  # (M, 3, 3)
    centres: np.ndarray = field(repr=False)  # (M, 3)
    point_ids: np.ndarray = field(repr=False)  # (N,)
    xyz: np.ndarray = field(repr=False)  # (N, 3)
    obs_image: np.ndarray = field(repr=False)  # (K,) row into the image arrays
    obs_point: np.ndarray = field(repr=False)  # (K,) row into the point arrays
    uv: np.ndarray = field(repr=False)  # (K, 2) observed pixel positions


def observations(rec) -> Observations:
    """The registered images, points and their observations of a reconstruction."""
    image_ids = np.array(sorted(rec.reg_image_ids()), dtype=np.int64)
    row_of_image = {int(i): k for k, i in enumerate(image_ids)}
    cams = np.array([rec.images[int(i)].camera_id for i in image_ids], dtype=np.int64)
    point_ids = np.array(sorted(rec.point3D_ids()), dtype=np.int64)
    xy = {int(i): np.array([p.xy for p in rec.images[int(i)].points2D]).reshape(-1, 2)
          for i in image_ids}
    oi, op, uv = [], [], []
    for k, pid in enumerate(point_ids):
        for el in rec.points3D[int(pid)].track.elements:
            row = row_of_image.get(int(el.image_id))
            if row is None:
                continue
            oi.append(row)
            op.append(k)
            uv.append(xy[int(el.image_id)][el.point2D_idx])
    return Observations(image_ids, cams, point_ids, np.array(oi, dtype=np.int64),
                        np.array(op, dtype=np.int64),
                        np.array(uv, dtype=np.float64).reshape(-1, 2))


def poses_points(rec, obs: Observations) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rotations (world -> camera) ``(M, 3, 3)`` and centres ``(M, 3)`` of the images and
    the positions ``(N, 3)`` of the points of ``obs``, as they are now."""
    R = np.array([rec.images[int(i)].cam_from_world().rotation.matrix()
                  for i in obs.image_ids]).reshape(-1, 3, 3)
    C = np.array([rec.images[int(i)].projection_center() for i in obs.image_ids]).reshape(-1, 3)
    xyz = np.array([rec.points3D[int(p)].xyz for p in obs.point_ids]).reshape(-1, 3)
    return R, C, xyz


def model_arrays(rec, obs: Observations | None = None) -> ModelArrays:
    """Arrays of a reconstruction's registered images, points and their observations."""
    obs = observations(rec) if obs is None else obs
    R, C, xyz = poses_points(rec, obs)
    return ModelArrays(obs.image_ids, obs.camera_of_image, R, C, obs.point_ids, xyz,
                       obs.obs_image, obs.obs_point, obs.uv)


def reprojection(rec, obs: Observations) -> tuple[np.ndarray, np.ndarray]:
    """Reprojection residuals ``(K, 2)`` (pixels) of the observations and the camera id of
    each, with the cameras, poses and points as they are now."""
    R, C, xyz = poses_points(rec, obs)
    res = np.full((len(obs.uv), 2), np.nan)
    cams = obs.camera_of_image[obs.obs_image]
    for cid in np.unique(cams):
        cam = rec.cameras[int(cid)]
        k = np.flatnonzero(cams == cid)
        pc = np.einsum("kij,kj->ki", R[obs.obs_image[k]], xyz[obs.obs_point[k]]
                       - C[obs.obs_image[k]])
        proj = np.asarray(cam.img_from_cam(pc), dtype=np.float64).reshape(-1, 2)
        res[k] = proj - obs.uv[k]
    return res, cams


def build_model(cameras: dict[int, tuple[str, int, int, np.ndarray]], camera_of_image: np.ndarray,
                R_cam_world: np.ndarray, centres: np.ndarray, xyz: np.ndarray,
                obs_image: np.ndarray, obs_point: np.ndarray, uv: np.ndarray):
    """A :class:`pycolmap.Reconstruction` from arrays: ``cameras`` maps a camera id to
    ``(model, width, height, params)``; image ``i`` has id ``i + 1``; every observation
    ``(obs_image[k], obs_point[k], uv[k])`` becomes a 2-D point of its image and an element of
    its point's track (points seen fewer than twice are left out)."""
    pycolmap = pycolmap_module()
    rec = pycolmap.Reconstruction()
    for cam_id, (model, w, h, params) in cameras.items():
        rec.add_camera_with_trivial_rig(pycolmap.Camera(
            model=model, width=int(w), height=int(h), params=list(map(float, params)),
            camera_id=int(cam_id)))
    order = np.lexsort((obs_point, obs_image))
    obs_image, obs_point, uv = obs_image[order], obs_point[order], uv[order]
    starts = np.searchsorted(obs_image, np.arange(len(centres) + 1))
    tracks: dict[int, list[tuple[int, int]]] = {}
    for i in range(len(centres)):
        lo, hi = starts[i], starts[i + 1]
        im = pycolmap.Image(name=f"img_{i + 1:05d}.jpg", camera_id=int(camera_of_image[i]),
                            image_id=i + 1)
        im.points2D = pycolmap.Point2DList([pycolmap.Point2D(p) for p in uv[lo:hi]])
        R = np.asarray(R_cam_world[i], dtype=np.float64)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ centres[i])
        rec.add_image_with_trivial_frame(im, pose)
        for j, p in enumerate(obs_point[lo:hi]):
            tracks.setdefault(int(p), []).append((i + 1, j))
    for p, elements in sorted(tracks.items()):
        if len(elements) < 2:
            continue
        track = pycolmap.Track()
        for image_id, idx in elements:
            track.add_element(image_id, idx)
        rec.add_point3D(np.asarray(xyz[p], dtype=np.float64), track)
    return rec
