"""Structure from motion on a rendered block (pycolmap), and the truth of what it made.

Reconstruction: the settings a user would start from on a CPU: SIFT features (COLMAP's
defaults, at most :data:`MAX_FEATURES` per image), exhaustive matching, incremental mapping;
one camera for all images (``RADIAL``: focal length, k1, k2 estimated; the principal point is
kept at the image centre). The model with the most registered images (then the most points) is
written as a binary COLMAP model folder (``cameras.bin``, ``images.bin``, ``points3D.bin``, and
COLMAP 4's ``rigs.bin``, ``frames.bin``) in COLMAP's own gauge: nothing is rescaled or turned.

Truth: every observation of a model point is cast, through the *true* camera (intrinsics and
pose of the rendering), onto the true surface; the point's surface position is the median of
its observations' hits. A similarity from the model points to those positions (Umeyama 1991,
refitted on the points within three robust standard deviations until the set no longer
changes) is ``T_world_model``; a second similarity from the reconstructed to the true camera
centres checks it. Residuals are given in world units and in GSD.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from sfm_render import Camera, HeightField, Pose
from tiereg.transform import Transform

log = logging.getLogger(__name__)

MAX_FEATURES = 4096  # SIFT features per image; COLMAP's default is 8192 (GPU-sized)
CAMERA_MODEL = "RADIAL"


def reconstruct(image_dir: Path, work_dir: Path, *, max_features: int = MAX_FEATURES) -> dict:
    """Run pycolmap on ``image_dir`` into ``work_dir`` (``database.db``, ``sparse/``, ``model/``);
    returns statistics. Cached: a finished ``work_dir`` (``reconstruction.json``) is reused."""
    import pycolmap

    done = work_dir / "reconstruction.json"
    if done.is_file():
        return json.loads(done.read_text())
    if work_dir.exists():
        shutil.rmtree(work_dir)
    work_dir.mkdir(parents=True)
    db = work_dir / "database.db"
    seconds = {}
    t = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = CAMERA_MODEL
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = max_features
    extraction.num_threads = 2
    pycolmap.extract_features(db, image_dir, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction,
                              device=pycolmap.Device.cpu)
    seconds["extract"] = time.perf_counter() - t
    t = time.perf_counter()
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = 2
    pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    seconds["match"] = time.perf_counter() - t
    t = time.perf_counter()
    sparse = work_dir / "sparse"
    sparse.mkdir()
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = 2
    models = pycolmap.incremental_mapping(db, image_dir, sparse, options=mapping)
    seconds["map"] = time.perf_counter() - t
    stats = {"seconds": seconds, "n_images": len(list(image_dir.glob("*.png"))),
             "n_models": len(models), "models": []}
    if models:
        best = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
        model_dir = work_dir / "model"
        model_dir.mkdir()
        best.write_binary(str(model_dir))
        cam = next(iter(best.cameras.values()))
        stats.update(n_registered=best.num_reg_images(), n_points=best.num_points3D(),
                     reprojection_error_px=best.compute_mean_reprojection_error(),
                     camera_model=cam.model.name, camera_params=list(map(float, cam.params)))
        stats["models"] = [[r.num_reg_images(), r.num_points3D()] for r in models.values()]
    done.write_text(json.dumps(stats, indent=2) + "\n")
    return stats


@dataclass(frozen=True, eq=False)
class Observations:
    """The model's points and, per observation, the point's row, the image and the pixel."""

    xyz: np.ndarray = field(repr=False)  # (N, 3) model frame
    point_ids: np.ndarray = field(repr=False)  # (N,) COLMAP ids
    obs_point: np.ndarray = field(repr=False)  # (K,) row into xyz
    obs_image: np.ndarray = field(repr=False)  # (K,) image name
    obs_xy: np.ndarray = field(repr=False)  # (K, 2) pixels (COLMAP: corner of the image at 0)
    centres: dict = field(repr=False)  # image name -> reconstructed centre (model frame)
    intrinsics: tuple = ()  # the estimated camera parameters


def read_observations(model_dir: Path) -> Observations:
    import pycolmap

    rec = pycolmap.Reconstruction(str(model_dir))
    names = {i: im.name for i, im in rec.images.items()}
    ids = np.array(sorted(rec.points3D), dtype=np.int64)
    xyz = np.array([rec.points3D[i].xyz for i in ids], dtype=np.float64)
    rows, images, xy = [], [], []
    for row, pid in enumerate(ids):
        for el in rec.points3D[pid].track.elements:
            rows.append(row)
            images.append(names[el.image_id])
            xy.append(rec.images[el.image_id].points2D[el.point2D_idx].xy)
    centres = {im.name: np.asarray(im.projection_center(), float) for im in rec.images.values()
               if im.has_pose}
    cam = next(iter(rec.cameras.values()))
    return Observations(xyz, ids, np.asarray(rows), np.asarray(images), np.asarray(xy, float),
                        centres, tuple(map(float, cam.params)))


def surface_points(obs: Observations, poses: dict[str, Pose], camera: Camera,
                   field_: HeightField) -> tuple[np.ndarray, np.ndarray]:
    """Per model point, the median of its observations' hits on the true surface (world frame),
    and the largest distance of a hit from that median (NaN where no ray hit)."""
    hits = np.full((len(obs.obs_point), 3), np.nan)
    for name in np.unique(obs.obs_image):
        sel = np.flatnonzero(obs.obs_image == name)
        pose = poses[str(name)]
        rays = pose.world_rays(camera, obs.obs_xy[sel, 0], obs.obs_xy[sel, 1])
        hits[sel] = field_.intersect(pose.centre, rays)
    order = np.argsort(obs.obs_point, kind="stable")
    starts = np.searchsorted(obs.obs_point[order], np.arange(len(obs.xyz)))
    med = np.full((len(obs.xyz), 3), np.nan)
    spread = np.full(len(obs.xyz), np.nan)
    ends = np.append(starts[1:], len(order))
    for row, (a, b) in enumerate(zip(starts, ends)):
        h = hits[order[a:b]]
        h = h[~np.isnan(h[:, 0])]
        if len(h):
            med[row] = np.median(h, axis=0)
            spread[row] = np.linalg.norm(h - med[row], axis=1).max()
    return med, spread


def umeyama(src: np.ndarray, dst: np.ndarray) -> Transform:
    """The least-squares similarity ``dst ~ s R src + t`` (Umeyama 1991)."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    var_s = (a**2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var_s)
    return Transform.from_similarity(s, R, mu_d - s * R @ mu_s)


@dataclass(frozen=True)
class Fit:
    """A robust similarity fit and its residuals (world units)."""

    T: Transform = field(repr=False)
    n: int
    n_used: int
    rms: float
    median: float
    p90: float


def robust_similarity(src: np.ndarray, dst: np.ndarray, *, k: float = 3.0,
                      floor: float = 0.0) -> tuple[Fit, np.ndarray]:
    """Umeyama refitted on the pairs whose residual is within ``k`` robust standard deviations
    (1.4826 MAD of the residual lengths about zero; at least ``floor``) until the set no longer
    changes; the fit and the mask of the pairs used."""
    use = np.all(np.isfinite(src), axis=1) & np.all(np.isfinite(dst), axis=1)
    valid = use.copy()
    for _ in range(30):
        T = umeyama(src[use], dst[use])
        res = np.full(len(src), np.inf)
        res[valid] = np.linalg.norm(T.apply(src[valid]) - dst[valid], axis=1)
        limit = max(k * 1.4826 * np.median(res[use]), floor)
        new = valid & (res <= limit)
        if np.array_equal(new, use) or new.sum() < 4:
            break
        use = new
    r = res[use]
    return Fit(T, int(valid.sum()), int(use.sum()), float(np.sqrt(np.mean(r**2))),
               float(np.median(r)), float(np.percentile(r, 90))), use


@dataclass(frozen=True)
class Truth:
    """What a registration of the model must find, and how well it is known."""

    T_ref_mov: Transform = field(repr=False)  # model frame -> reference frame (with georef)
    gsd: float  # reference units per pixel at the block's median ground
    points: Fit = field(repr=False)
    cameras: Fit = field(repr=False)
    n_points: int
    n_inconsistent: int  # points whose observations hit the surface far apart (> 3 GSD)
    centre_difference: float  # the two fits at the block centre, reference units
    rotation_difference_deg: float
    scale_difference: float  # relative
    up_model: tuple[float, float, float]  # the reference's up direction in the model frame

    def to_dict(self) -> dict:
        def fit(f: Fit) -> dict:
            d = {k: v for k, v in asdict(f).items() if k != "T"}
            d.update(rms_gsd=f.rms / self.gsd, median_gsd=f.median / self.gsd)
            return d

        return {**self.T_ref_mov.to_dict(), "scale_ref_per_model": self.T_ref_mov.scale,
                "model_units_per_ref_unit": 1.0 / self.T_ref_mov.scale, "gsd": self.gsd,
                "n_points": self.n_points, "n_inconsistent": self.n_inconsistent,
                "fit_points": fit(self.points), "fit_cameras": fit(self.cameras),
                "fits_differ": {"at_block_centre": self.centre_difference,
                                "rotation_deg": self.rotation_difference_deg,
                                "scale_relative": self.scale_difference},
                "up_in_model_frame": list(self.up_model)}


def rotation_angle_deg(A: Transform, B: Transform) -> float:
    c = (np.trace(A.rotation @ B.rotation.T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def compute_truth(model_dir: Path, poses: list[Pose], camera: Camera, field_: HeightField, *,
                  gsd: float, georef: np.ndarray) -> Truth:
    """The truth of one reconstruction: see the module's docstring. ``georef``: added to world
    coordinates to give reference coordinates."""
    obs = read_observations(model_dir)
    by_name = {p.name: p for p in poses}
    surface, spread = surface_points(obs, by_name, camera, field_)
    consistent = spread <= 3 * gsd
    src = np.where(consistent[:, None], obs.xyz, np.nan)
    pts, _ = robust_similarity(src, surface, floor=0.5 * gsd)
    names = sorted(obs.centres)
    cams, _ = robust_similarity(np.array([obs.centres[n] for n in names]),
                                np.array([by_name[n].centre for n in names]))
    centre = np.median(obs.xyz, axis=0, keepdims=True)
    up = pts.T.rotation.T @ np.array([0.0, 0.0, 1.0])
    T_ref_mov = Transform.from_translation(georef) @ pts.T
    return Truth(T_ref_mov, gsd, pts, cams, len(obs.xyz), int((~consistent).sum()),
                 float(np.linalg.norm(pts.T.apply(centre) - cams.T.apply(centre))),
                 rotation_angle_deg(pts.T, cams.T), cams.T.scale / pts.T.scale - 1.0,
                 tuple(float(u) for u in up))
