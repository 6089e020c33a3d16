"""Scenes: a world, its lidar, an image block over part of it, and a hidden transform.

The lidar is the reference; its coordinates are the world's plus a georeferencing offset (by
default near 500,000 E / 5,000,000 N, so float64 precision is exercised). The tie points are
moved into a "model" frame by the hidden similarity ``T_mov_ref``; the answer a registration must
find is its inverse, ``T_ref_mov``.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from ..transform import Transform
from .sensors import (
    ImageBlock,
    LidarPoints,
    LidarSurvey,
    TiePoints,
    sample_lidar,
    sample_tie_points,
)
from .world import World, make_world

GEOREF = (500_000.0, 5_000_000.0, 0.0)


@dataclass(frozen=True)
class HiddenTransform:
    """The similarity that moves tie points from the reference frame into the model frame.

    ``scale`` is model units per reference unit (3.2808 turns metres into feet); ``heading_deg``
    rotates the model frame about the vertical; ``tilt_deg`` tilts it (omega, phi); the model frame
    puts the block centre at ``model_origin``.
    """

    heading_deg: float = 0.0
    scale: float = 1.0
    tilt_deg: tuple[float, float] = (0.0, 0.0)
    model_origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def T_mov_ref(self, centre_ref: np.ndarray) -> Transform:
        local = Transform.from_parameters(
            scale=self.scale, omega=np.radians(self.tilt_deg[0]), phi=np.radians(self.tilt_deg[1]),
            kappa=np.radians(self.heading_deg))
        return (Transform.from_translation(self.model_origin) @ local
                @ Transform.from_translation(-np.asarray(centre_ref, dtype=np.float64)))

    @classmethod
    def random(cls, rng: np.random.Generator, *, scale_range: tuple[float, float] = (0.25, 4.0),
               tilt_sigma_deg: float = 0.3) -> HiddenTransform:
        lo, hi = np.log(scale_range[0]), np.log(scale_range[1])
        return cls(
            heading_deg=float(rng.uniform(0, 360)),
            scale=float(np.exp(rng.uniform(lo, hi))),
            tilt_deg=(float(rng.normal(0, tilt_sigma_deg)), float(rng.normal(0, tilt_sigma_deg))),
            model_origin=(float(rng.uniform(-1e5, 1e5)), float(rng.uniform(-1e5, 1e5)),
                          float(rng.uniform(-100, 100))),
        )


@dataclass(frozen=True)
class SceneSpec:
    """Everything that defines a scene; the same spec and seed give the same scene."""

    kind: str = "suburban"
    seed: int = 0
    world_size_m: float = 8000.0
    world_cell_m: float = 2.0
    lidar_size_m: float = 4000.0  # square footprint centred on the world
    survey: LidarSurvey = LidarSurvey()
    block: ImageBlock = ImageBlock()
    block_heading_deg: float | None = None  # flight direction of the image block (None: random)
    overlap: float = 1.0  # wanted share of the block covered by the lidar (0.3 .. 1)
    hidden: HiddenTransform | None = None  # None: random
    georef: tuple[float, float, float] = GEOREF
    tie_world_seed: int | None = None  # tie points from another world: a no-overlap case


@dataclass(frozen=True, eq=False)
class Scene:
    spec: SceneSpec
    lidar: LidarPoints  # reference frame
    tie_points: TiePoints  # world frame (before the hidden transform)
    moving: np.ndarray = field(repr=False)  # (N, 3) tie points in the model frame
    T_ref_mov: Transform  # the truth
    hidden: HiddenTransform
    overlap: float  # measured share of the block inside the lidar footprint
    block_centre: tuple[float, float]
    block_heading_deg: float = 0.0  # flight direction of the image block

    def truth_dict(self) -> dict:
        return {
            **self.T_ref_mov.to_dict(),
            "hidden": asdict(self.hidden),
            "overlap_fraction": self.overlap,
            "n_tie_points": int(len(self.moving)),
            "n_blunders": int(self.tie_points.blunder.sum()),
            "n_lidar_points": int(len(self.lidar.xyz)),
            "spec": _jsonable(asdict(self.spec)),
        }


def _jsonable(d):
    if isinstance(d, dict):
        return {k: _jsonable(v) for k, v in d.items()}
    if isinstance(d, (tuple, list)):
        return [_jsonable(v) for v in d]
    return d


def block_overlap(centre: np.ndarray, side: float, heading_deg: float, half_lidar: float) -> float:
    """Share of a square block (rotated by ``heading_deg``) inside the centred lidar square."""
    g = (np.arange(40) + 0.5) / 40 * side - side / 2
    u, v = np.meshgrid(g, g)
    a = np.radians(heading_deg)
    x = centre[0] + np.cos(a) * u - np.sin(a) * v
    y = centre[1] + np.sin(a) * u + np.cos(a) * v
    return float(np.mean((np.abs(x) < half_lidar) & (np.abs(y) < half_lidar)))


def place_block(overlap: float, side: float, heading_deg: float, half_lidar: float,
                rng: np.random.Generator) -> np.ndarray:
    """A block centre whose overlap with the lidar is ``overlap`` (bisection along a direction)."""
    d = rng.uniform(0, 2 * np.pi)
    direction = np.array([np.cos(d), np.sin(d)])
    lo, hi = 0.0, half_lidar + side
    if block_overlap(direction * lo, side, heading_deg, half_lidar) <= overlap:
        return direction * lo
    for _ in range(40):
        mid = (lo + hi) / 2
        if block_overlap(direction * mid, side, heading_deg, half_lidar) > overlap:
            lo = mid
        else:
            hi = mid
    return direction * (lo + hi) / 2


def make_scene(spec: SceneSpec = SceneSpec(), *, world: World | None = None,
               lidar: LidarPoints | None = None) -> Scene:
    """Simulate a scene; pass ``world`` to reuse one already made from the same kind and seed,
    and ``lidar`` to reuse the lidar of a scene with the same world, survey and seed (the lidar
    does not depend on the block or the hidden transform)."""
    rng = np.random.default_rng([spec.seed, 2])
    if world is None:
        world = make_world(spec.kind, size_m=spec.world_size_m, cell=spec.world_cell_m,
                           seed=spec.seed)
    half = spec.lidar_size_m / 2
    georef = np.asarray(spec.georef, dtype=np.float64)
    if lidar is None:
        lidar = sample_lidar(world, (-half, -half, half, half), spec.survey,
                             rng=np.random.default_rng([spec.seed, 1]))
        lidar = replace(lidar, xyz=lidar.xyz + georef)

    heading = float(rng.uniform(0, 360)) if spec.block_heading_deg is None \
        else spec.block_heading_deg
    centre = place_block(spec.overlap, spec.block.side_m, heading, half, rng)
    tie_world = world
    if spec.tie_world_seed is not None:
        tie_world = make_world(spec.kind, size_m=spec.world_size_m, cell=spec.world_cell_m,
                               seed=spec.tie_world_seed)
    ties = sample_tie_points(tie_world, (float(centre[0]), float(centre[1])), spec.block,
                             heading_deg=heading, rng=rng)
    overlap = 0.0 if spec.tie_world_seed is not None else block_overlap(
        centre, spec.block.side_m, heading, half)
    hidden = spec.hidden if spec.hidden is not None else HiddenTransform.random(rng)
    centre_ref = np.array([centre[0], centre[1], float(np.median(ties.xyz[:, 2]))]) + georef
    T_mov_ref = hidden.T_mov_ref(centre_ref)
    moving = T_mov_ref.apply(ties.xyz + georef)
    return Scene(spec, lidar, ties, moving, T_mov_ref.inverse, hidden, overlap,
                 (float(centre[0]), float(centre[1])), heading)


@dataclass(frozen=True, eq=False)
class OrientedModel:
    """A scene's tie points and images as an unreferenced model in any orientation."""

    xyz: np.ndarray = field(repr=False)  # tie points, model frame
    camera_centres: np.ndarray = field(repr=False)  # model frame
    rotations_world_to_cam: np.ndarray = field(repr=False)  # (M, 3, 3): model -> camera
    T_ref_mov: Transform  # the truth: model frame -> reference frame

    def write_colmap(self, folder: str | Path, *, cameras: bool = True) -> Path:
        """A COLMAP text model in ``folder``: ``points3D.txt``, and with ``cameras`` the images
        (``images.txt``, ``cameras.txt``) too."""
        from ..io.colmap import write_colmap_model_txt, write_colmap_points_txt

        out = Path(folder)
        if cameras:
            write_colmap_model_txt(out, self.xyz, self.camera_centres, self.rotations_world_to_cam)
        else:
            out.mkdir(parents=True, exist_ok=True)
            write_colmap_points_txt(out / "points3D.txt", self.xyz)
        return out


def oriented_model(scene: Scene, rotation_deg: tuple[float, float, float], *,
                   flying_height_m: float = 800.0) -> OrientedModel:
    """The scene's block as a structure-from-motion model turned by ``rotation_deg`` (omega, phi,
    kappa about the block centre, after the scene's hidden similarity), with its images: nadir
    cameras on the block's image grid (:class:`ImageBlock` footprint and overlaps) at
    ``flying_height_m`` above the block's median height."""
    block = scene.spec.block
    half = block.side_m / 2
    f = block.image_footprint_m
    cu = np.arange(-half, half + f * (1 - block.forward_overlap), f * (1 - block.forward_overlap))
    cv = np.arange(-half, half + f * (1 - block.side_overlap), f * (1 - block.side_overlap))
    u, v = (a.ravel() for a in np.meshgrid(cu, cv))
    h = np.radians(scene.block_heading_deg)
    d, n = np.array([np.cos(h), np.sin(h)]), np.array([-np.sin(h), np.cos(h)])
    georef = np.asarray(scene.spec.georef, dtype=np.float64)
    ground = float(np.median(scene.tie_points.xyz[:, 2]))
    centres_ref = np.column_stack([scene.block_centre[0] + u * d[0] + v * n[0],
                                   scene.block_centre[1] + u * d[1] + v * n[1],
                                   np.full(len(u), ground + flying_height_m)]) + georef
    # nadir views: camera x along the flight, optical axis (camera z) straight down
    R_cam_ref = np.array([[np.cos(h), np.sin(h), 0.0], [np.sin(h), -np.cos(h), 0.0],
                          [0.0, 0.0, -1.0]])
    T_mov_ref = scene.T_ref_mov.inverse
    c = scene.moving.mean(axis=0)
    om, ph, ka = np.radians(rotation_deg)
    turn = (Transform.from_translation(c) @ Transform.from_parameters(omega=om, phi=ph, kappa=ka)
            @ Transform.from_translation(-c))
    T_model_ref = turn @ T_mov_ref
    R = T_model_ref.matrix[:3, :3] / T_model_ref.parameters().scale
    rotations = np.repeat((R_cam_ref @ R.T)[None], len(u), axis=0)
    return OrientedModel(turn.apply(scene.moving), T_model_ref.apply(centres_ref), rotations,
                         T_model_ref.inverse)


def write_scene(scene: Scene, out_dir: str | Path, *, crs_epsg: int | None = 32632) -> Path:
    """Write ``reference.laz``, ``tiepoints.xyz`` and ``truth.json`` into ``out_dir``."""
    import laspy

    from ..io.base import atomic_output, write_text_atomic
    from ..io.text import write_xyz

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(scene.lidar.xyz.min(axis=0))
    if crs_epsg:
        import pyproj

        header.add_crs(pyproj.CRS.from_epsg(crs_epsg))
    data = laspy.LasData(header)
    data.x, data.y, data.z = scene.lidar.xyz.T
    data.return_number = scene.lidar.return_number
    data.number_of_returns = scene.lidar.number_of_returns
    data.classification = scene.lidar.classification
    with atomic_output(out / "reference.laz") as tmp:
        with open(tmp, "wb") as fh:
            data.write(fh, do_compress=True)
    write_xyz(out / "tiepoints.xyz", scene.moving)
    write_text_atomic(out / "truth.json", json.dumps(scene.truth_dict(), indent=2) + "\n")
    return out
