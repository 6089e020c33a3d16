"""Scenes of the structure-from-motion benchmark: a surface, a flight over it, lidar of it.

Each :class:`SfmScene` names a surface (a simulator world kind with a seed, or one of the real
surfaces of ``real_worlds.py``), a flight plan and a camera. :func:`build_scene` renders the
block (``sfm_render``), reconstructs it with pycolmap and computes the truth
(``sfm_reconstruct``), and samples the lidar: over the whole block, and over 50-70 % of it (the
block cut by a straight line). Everything is cached under ``benchmarks/work/sfm/<scene>/``; a
second run reuses what is there.

Reference frame: the world's local coordinates plus :data:`GEOREF` (about 500,000 E,
5,000,000 N), written as LAZ in UTM zone 32N (EPSG:32632), as ``tiereg simulate`` does.
"""

from __future__ import annotations

import json
import logging
import pickle
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from real_worlds import _SIZING, REAL_WORLDS, load_real_world
from sfm_reconstruct import compute_truth, read_observations, reconstruct
from sfm_render import (
    Camera,
    FlightPlan,
    HeightField,
    Pose,
    make_texture,
    plan_block,
    render_image,
)
from tiereg.simulate.scene import GEOREF
from tiereg.simulate.sensors import LidarPoints, LidarSurvey, sample_lidar
from tiereg.simulate.world import World, make_world
from tiereg.transform import Transform

log = logging.getLogger(__name__)

HERE = Path(__file__).resolve().parent
WORK = HERE / "work" / "sfm"
CRS_EPSG = 32632
MAX_LIDAR_POINTS = 4_000_000


@dataclass(frozen=True)
class SfmScene:
    """A surface, a flight over it and a camera. ``surface``: a world kind or a real world's
    name; ``seed``: the synthetic world's seed and the seed of everything random here (even:
    development half, odd: held-out half)."""

    surface: str
    seed: int
    plan: FlightPlan
    camera: Camera = Camera()
    cell: float = 1.0  # synthetic world cell (real worlds have their own)
    lidar_density: float = 2.0  # points per square unit, at most (MAX_LIDAR_POINTS over all)

    @property
    def name(self) -> str:
        return f"{self.surface}-{self.seed}"

    @property
    def half(self) -> str:
        return "dev" if self.seed % 2 == 0 else "held-out"

    @property
    def real(self) -> bool:
        return self.surface in REAL_WORLDS

    @property
    def n_images(self) -> int:
        return self.plan.strips * self.plan.images_per_strip


def _plan(strips, per_strip, gsd, forward, side, heading) -> FlightPlan:
    return FlightPlan(strips=strips, images_per_strip=per_strip, gsd=gsd, forward_overlap=forward,
                      side_overlap=side, heading_deg=heading)


# The scene list is fixed before any result is seen; the half follows the seed's parity.
SCENES = (
    SfmScene("farmland", 10, _plan(3, 5, 1.5, 0.70, 0.30, 20.0), cell=1.5),
    SfmScene("suburban", 12, _plan(3, 8, 1.0, 0.75, 0.30, 110.0), cell=1.0),
    SfmScene("urban", 14, _plan(4, 6, 0.8, 0.70, 0.35, 200.0), Camera(focal_px=1400.0, k1=-0.04,
                                                                      k2=0.01), cell=1.0),
    SfmScene("forest", 16, _plan(3, 6, 1.2, 0.70, 0.30, 290.0), Camera(focal_px=900.0, k1=-0.09,
                                                                       k2=0.03), cell=1.2),
    SfmScene("mountains", 18, _plan(3, 6, 3.0, 0.70, 0.30, 45.0), cell=3.0,
             lidar_density=0.5),
    SfmScene("farmland", 11, _plan(4, 8, 1.2, 0.80, 0.30, 160.0), cell=1.5),
    SfmScene("suburban", 13, _plan(2, 9, 1.3, 0.70, 0.25, 75.0), Camera(focal_px=1250.0),
             cell=1.3),
    SfmScene("urban", 15, _plan(3, 7, 1.0, 0.65, 0.30, 330.0), cell=1.2),
    SfmScene("forest", 17, _plan(4, 10, 1.0, 0.80, 0.30, 250.0), cell=1.25),
    SfmScene("mountains", 19, _plan(3, 5, 4.0, 0.70, 0.30, 135.0), Camera(focal_px=950.0),
             cell=4.0, lidar_density=0.5),
    SfmScene("muscatatuck", 20, _plan(3, 5, 0.11, 0.70, 0.30, 0.0)),
    SfmScene("muscatatuck", 21, _plan(3, 5, 0.10, 0.75, 0.35, 90.0), Camera(focal_px=1000.0)),
    SfmScene("longyearbyen", 22, _plan(3, 5, 3.2, 0.70, 0.30, 30.0)),
    SfmScene("longyearbyen", 23, _plan(4, 6, 2.5, 0.70, 0.30, 300.0), Camera(focal_px=1200.0)),
    SfmScene("autzen", 24, _plan(3, 5, 0.40, 0.70, 0.30, 90.0)),
    SfmScene("autzen", 25, _plan(2, 9, 0.35, 0.75, 0.30, 0.0), Camera(focal_px=1150.0)),
)
QUICK = ("suburban-12", "autzen-24")


def scene_by_name(name: str) -> SfmScene:
    return next(s for s in SCENES if s.name == name)


def world_size(scene: SfmScene) -> float:
    """The side of a square world that holds the block turned to its heading, moved off the
    centre by up to 5 % (:func:`_ground_height`) and seen with a few degrees of tilt."""
    along, across = scene.plan.extent(scene.camera)
    h = np.radians(scene.plan.heading_deg)
    half = max(abs(along * np.sin(h)) + abs(across * np.cos(h)),
               abs(along * np.cos(h)) + abs(across * np.sin(h))) / 2
    height = scene.plan.gsd * scene.camera.focal_px
    return float(np.ceil(2 * (half + 0.05 * min(along, across) + 0.12 * height)
                         + 20 * scene.cell))


def load_world(scene: SfmScene) -> World:
    """The scene's world (cached; a synthetic one sized to hold the block with a margin)."""
    if scene.real:
        return load_real_world(scene.surface)
    size = world_size(scene)
    path = WORK / "worlds" / f"{scene.surface}-{scene.seed}-{size:.0f}-{scene.cell:g}.pkl"
    if path.is_file():
        with open(path, "rb") as fh:
            return pickle.load(fh)
    t = time.perf_counter()
    world = make_world(scene.surface, size_m=size, cell=scene.cell, seed=scene.seed)
    log.info("world %s: %d x %d cells in %.0f s", scene.name, *world.shape,
             time.perf_counter() - t)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_suffix(".tmp"), "wb") as fh:
        pickle.dump(world, fh, protocol=pickle.HIGHEST_PROTOCOL)
    path.with_suffix(".tmp").rename(path)
    return world


@dataclass(frozen=True, eq=False)
class Block:
    """A rendered block: where its images are, the true cameras and what they saw."""

    scene: SfmScene
    image_dir: Path
    poses: list[Pose] = field(repr=False)
    gsd: float  # median over the images of the centre pixel's footprint
    footprint: tuple[float, float, float, float] = ()  # xmin, ymin, xmax, ymax (world)
    miss_fraction: float = 0.0
    render_seconds: float = 0.0


def _ground_height(world: World, field_: HeightField, plan: FlightPlan, camera: Camera,
                   rng: np.random.Generator) -> tuple[float, tuple[float, float]]:
    """The height the block is planned above, and its centre: the world's centre moved by up to
    5 % of the block; the height is the median ground under the block, raised where needed so
    that the cameras stay at least 40 % of the flying height above the highest ground."""
    along, across = plan.extent(camera)
    centre = tuple(rng.uniform(-0.05, 0.05, 2) * min(along, across))
    g = np.linspace(-0.5, 0.5, 60)
    u, v = np.meshgrid(g * along, g * across)
    h = np.radians(plan.heading_deg)
    x = centre[0] + u * np.sin(h) + v * np.cos(h)
    y = centre[1] + u * np.cos(h) - v * np.sin(h)
    z = field_.height(x.ravel(), y.ravel())
    z = z[np.isfinite(z)]
    height = plan.gsd * camera.focal_px
    return max(float(np.median(z)), float(z.max()) - 0.6 * height), centre


def render_block(scene: SfmScene, world: World, field_: HeightField) -> Block:
    """Render the scene's images into ``WORK/<scene>/images`` (cached with ``block.json``)."""
    out = WORK / scene.name
    image_dir = out / "images"
    meta = out / "block.json"
    if meta.is_file():
        d = json.loads(meta.read_text())
        poses = [Pose(p["name"], np.array(p["centre"]), np.array(p["R_cam_world"]))
                 for p in d["poses"]]
        return Block(scene, image_dir, poses, d["gsd"], tuple(d["footprint"]),
                     d["miss_fraction"], d["render_seconds"])
    from PIL import Image

    rng = np.random.default_rng([scene.seed, 7])
    ground, centre = _ground_height(world, field_, scene.plan, scene.camera, rng)
    poses = plan_block(scene.plan, scene.camera, centre_xy=centre, ground_z=ground, rng=rng)
    texture = make_texture(world.ortho, x0=world.x0, y0=world.y0, cell=world.cell,
                           gsd=scene.plan.gsd, rng=np.random.default_rng([scene.seed, 8]))
    image_dir.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    misses, gsds, corners = [], [], []
    cam = scene.camera
    for pose in poses:
        img, miss = render_image(field_, texture, cam, pose, rng=rng,
                                 gain=float(rng.uniform(0.92, 1.05)))
        Image.fromarray(img).save(image_dir / pose.name)
        misses.append(miss)
        edge = np.array([[0, 0], [cam.width_px, 0], [0, cam.height_px],
                         [cam.width_px, cam.height_px], [cam.width_px / 2, cam.height_px / 2]])
        hits = field_.intersect(pose.centre, pose.world_rays(cam, edge[:, 0], edge[:, 1]))
        corners.append(hits[:4, :2])
        gsds.append(np.linalg.norm(hits[4] - pose.centre) / cam.focal_px)
    seconds = time.perf_counter() - t
    c = np.concatenate(corners)
    c = c[np.isfinite(c[:, 0])]
    footprint = (float(c[:, 0].min()), float(c[:, 1].min()), float(c[:, 0].max()),
                 float(c[:, 1].max()))
    block = Block(scene, image_dir, poses, float(np.median(gsds)), footprint,
                  float(np.mean(misses)), seconds)
    meta.write_text(json.dumps({
        "scene": scene.name, "plan": asdict(scene.plan), "camera": asdict(scene.camera),
        "gsd": block.gsd, "footprint": footprint, "miss_fraction": block.miss_fraction,
        "render_seconds": seconds, "world_cell": world.cell,
        "poses": [{"name": p.name, "centre": p.centre.tolist(),
                   "R_cam_world": p.R_cam_world.tolist()} for p in poses]}, indent=1) + "\n")
    log.info("%s: %d images in %.0f s (%.1f s each), GSD %.3f, %.2f %% missed", scene.name,
             len(poses), seconds, seconds / len(poses), block.gsd, 100 * block.miss_fraction)
    return block


def write_laz(path: Path, lidar: LidarPoints, *, crs_epsg: int = CRS_EPSG) -> None:
    """Lidar points (reference frame) as LAZ 1.4 with a projected CRS, written atomically."""
    import laspy
    import pyproj

    from tiereg.io.base import atomic_output

    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(lidar.xyz.min(axis=0))
    header.add_crs(pyproj.CRS.from_epsg(crs_epsg))
    data = laspy.LasData(header)
    data.x, data.y, data.z = lidar.xyz.T
    data.return_number = lidar.return_number
    data.number_of_returns = lidar.number_of_returns
    data.classification = lidar.classification
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as fh:
            data.write(fh, do_compress=True)


def _survey(scene: SfmScene, area: float) -> LidarSurvey:
    density = min(scene.lidar_density, MAX_LIDAR_POINTS / area)
    if scene.real:
        z = _SIZING[scene.surface]
        return LidarSurvey(density_per_m2=min(density, z.lidar_per_m2),
                           strip_width_m=z.strip_m, gap_probability=z.gap_probability)
    return LidarSurvey(density_per_m2=density)


def _subset(lidar: LidarPoints, keep: np.ndarray) -> LidarPoints:
    return LidarPoints(lidar.xyz[keep], lidar.return_number[keep],
                       lidar.number_of_returns[keep], lidar.classification[keep])


def make_lidar(scene: SfmScene, world: World, block: Block,
               surface_xy: np.ndarray) -> dict:
    """``lidar.laz`` over the block's footprint and ``lidar-partial.laz``, the part of it on
    one side of a straight line that leaves 50-70 % of the model's points (``surface_xy``,
    world frame) covered; cached with ``lidar.json``."""
    out = WORK / scene.name
    meta = out / "lidar.json"
    if meta.is_file():
        return json.loads(meta.read_text())
    t0 = time.perf_counter()
    rng = np.random.default_rng([scene.seed, 9])
    x0, y0, x1, y1 = block.footprint
    mx, my = 0.03 * (x1 - x0), 0.03 * (y1 - y0)
    wx0, wy0, wx1, wy1 = world.bounds
    fp = (max(x0 - mx, wx0 + world.cell), max(y0 - my, wy0 + world.cell),
          min(x1 + mx, wx1 - world.cell), min(y1 + my, wy1 - world.cell))
    area = (fp[2] - fp[0]) * (fp[3] - fp[1])
    survey = _survey(scene, area)
    lidar = sample_lidar(world, fp, survey, rng=rng)
    inside = ((surface_xy[:, 0] >= fp[0]) & (surface_xy[:, 0] <= fp[2])
              & (surface_xy[:, 1] >= fp[1]) & (surface_xy[:, 1] <= fp[3]))
    georef = np.asarray(GEOREF)
    write_laz(out / "lidar.laz", LidarPoints(lidar.xyz + georef, lidar.return_number,
                                             lidar.number_of_returns, lidar.classification))
    # the partial lidar: a half-plane along a random direction through the block
    target = float(rng.uniform(0.5, 0.7))
    a = rng.uniform(0, 2 * np.pi)
    direction = np.array([np.cos(a), np.sin(a)])
    cut = float(np.quantile(surface_xy @ direction, target))
    partial = _subset(lidar, lidar.xyz[:, :2] @ direction <= cut)
    covered = float(np.mean((surface_xy @ direction <= cut) & inside))
    write_laz(out / "lidar-partial.laz", LidarPoints(
        partial.xyz + georef, partial.return_number, partial.number_of_returns,
        partial.classification))
    d = {"seconds": time.perf_counter() - t0,
         "footprint_world": fp, "density_per_unit2": survey.density_per_m2,
         "n_points": int(len(lidar.xyz)), "n_points_partial": int(len(partial.xyz)),
         "covered_full": float(inside.mean()), "covered_partial": covered,
         "partial_direction_deg": float(np.degrees(a)), "crs_epsg": CRS_EPSG,
         "georef": list(GEOREF)}
    meta.write_text(json.dumps(d, indent=1) + "\n")
    return d


@dataclass(frozen=True)
class BuiltScene:
    """Everything the benchmark's cases need from one scene."""

    scene: SfmScene
    model_dir: Path | None  # None: the reconstruction failed
    reconstruction: dict
    truth: dict | None
    lidar: dict | None
    block: dict
    seconds: dict


def build_scene(scene: SfmScene) -> BuiltScene:
    """Render, reconstruct, find the truth and sample the lidar of ``scene`` (cached)."""
    out = WORK / scene.name
    seconds = {}
    t = time.perf_counter()
    world = load_world(scene)
    field_ = HeightField(world.dsm, x0=world.x0, y0=world.y0, cell=world.cell)
    seconds["world"] = time.perf_counter() - t
    block = render_block(scene, world, field_)
    seconds["render"] = block.render_seconds
    rec = reconstruct(block.image_dir, out / "colmap")
    seconds["reconstruct"] = sum(rec["seconds"].values())
    block_d = {"gsd": block.gsd, "miss_fraction": block.miss_fraction,
               "n_images": len(block.poses), "world_cell": world.cell,
               "flying_height": float(block.gsd * scene.camera.focal_px)}
    if "n_points" not in rec or rec["n_points"] < 100:
        return BuiltScene(scene, None, rec, None, None, block_d, seconds)
    model_dir = out / "colmap" / "model"
    truth_path = out / "truth.json"
    t = time.perf_counter()
    if truth_path.is_file():
        truth = json.loads(truth_path.read_text())
    else:
        tr = compute_truth(model_dir, block.poses, scene.camera, field_, gsd=block.gsd,
                           georef=np.asarray(GEOREF))
        truth = tr.to_dict()
        truth["true_camera"] = asdict(scene.camera)
        truth["estimated_camera"] = rec["camera_params"]
        truth["seconds"] = time.perf_counter() - t
        truth_path.write_text(json.dumps(truth, indent=1) + "\n")
    seconds["truth"] = truth.get("seconds", time.perf_counter() - t)
    t = time.perf_counter()
    xyz = read_observations(model_dir).xyz
    T = Transform(np.asarray(truth["T_ref_mov"]))
    surface_xy = T.apply(xyz)[:, :2] - np.asarray(GEOREF)[:2]
    lidar = make_lidar(scene, world, block, surface_xy)
    seconds["lidar"] = lidar.get("seconds", time.perf_counter() - t)
    return BuiltScene(scene, model_dir, rec, truth, lidar, block_d, seconds)


__all__ = ["SCENES", "QUICK", "SfmScene", "BuiltScene", "build_scene", "scene_by_name"]
