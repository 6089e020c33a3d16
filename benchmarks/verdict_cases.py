"""The verdict benchmark's cases and their scenes (see ``verdict.py``).

The case list is fixed in code: :func:`all_cases` draws every case's parameters from its own seed
(dev: seeds 0-499, held-out: 1000-1499), so the halves never share a scene. Half the synthetic
worlds come from tiereg's simulator (``tiereg.simulate.make_world`` / ``make_scene``), half from
the independent generator (``worlds_alt.py`` with ``sensors_alt.py``); the real surfaces of
``real_worlds.py`` are sensed by either simulator's sensors in turn.

A scene is written once into ``benchmarks/work/verdict/<case id>/``: ``reference.laz`` (EPSG:32632
at about 500,000 E / 5,000,000 N), ``moving.npy`` (the tie points in the model frame) and
``truth.json`` (``T_ref_mov`` and the case's parameters as realised).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
WORK = HERE / "work" / "verdict"
SCENE_VERSION = 2  # bump when a generator changes: cached scenes are made again

SYNTHETIC = ("suburban", "urban", "farmland", "mountains", "forest")
REAL = ("muscatatuck", "longyearbyen", "autzen")
GENERATORS = ("tiereg", "alt")
N_BINS = ((300, 600), (600, 1000), (1000, 3000), (3000, 6000))
MAX_LIDAR_POINTS = 1.5e6
WORLD_CELLS = 2200  # a world raster is at most about this many cells a side
SPECIAL_SCALES = (0.25, 0.3048, 1.0, 3.2808, 4.0)
HALF_SEED = {"dev": 0, "heldout": 1000}
# corners per km^2 a world offers for tie points at 1 m cells (measured on a few worlds of each
# family; at 2 m about a quarter): tie densities are drawn up to half of it. tiereg's worlds get
# their Harris corners again down to 1e-3 of the strongest (its default, 5e-3, leaves too few for
# the dense blocks; ``real_worlds.py`` goes down to 1e-4)
TIEREG_CORNER_THRESHOLD = 1e-3
CORNERS_PER_KM2 = {
    "tiereg": {"suburban": 12000, "urban": 12000, "farmland": 12000, "mountains": 8000,
               "forest": 10000},
    "alt": {"suburban": 12000, "urban": 7000, "farmland": 12000, "mountains": 5000,
            "forest": 15000},
}
# the real surfaces: (lidar side, block side, tie points per km^2, lidar density range)
REAL_SIZING = {"muscatatuck": (170.0, 150.0, 16_000.0, (0.5, 8.0)),
               "longyearbyen": (6500.0, 5500.0, 30.0, (0.03, 0.07)),
               "autzen": (560.0, 480.0, 2_500.0, (0.5, 8.0))}


@dataclass(frozen=True)
class Case:
    case_id: str
    half: str  # "dev" or "heldout"
    seed: int
    family: str  # a synthetic family, "spikes", or a real surface's name
    generator: str  # whose simulator made the world (and sensed it): "tiereg" or "alt"
    world_family: str  # the world's family (spikes: the one under the spikes)
    negative: str  # "", "other-world" or "other-place"
    n_target: int
    tie_density_km2: float
    block_m: float
    aspect: float
    lidar_m: float
    lidar_density: float
    world_m: float
    cell_m: float
    noise_z_m: float
    blunder_fraction: float
    blunder_max_m: float
    overlap: float
    heading_deg: float
    scale: float
    tilt_deg: tuple[float, float]
    model_origin: tuple[float, float, float]
    spikes_fraction: float = 0.0

    @property
    def directory(self) -> Path:
        return WORK / self.case_id


def _log_uniform(rng, lo, hi) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _scale(rng) -> float:
    if rng.random() < 0.35:
        return float(rng.choice(SPECIAL_SCALES))
    return _log_uniform(rng, 0.25, 4.0)


def _common(rng) -> dict:
    return {"noise_z_m": float(rng.uniform(0.1, 0.5)),
            "blunder_fraction": 0.0 if rng.random() < 0.25 else float(rng.uniform(0.005, 0.05)),
            "blunder_max_m": float(rng.uniform(5, 20)), "overlap": float(rng.uniform(0.5, 1.0)),
            "heading_deg": float(rng.uniform(0, 360)), "scale": _scale(rng),
            "tilt_deg": (float(rng.normal(0, 0.3)), float(rng.normal(0, 0.3))),
            "model_origin": (float(rng.uniform(-1e5, 1e5)), float(rng.uniform(-1e5, 1e5)),
                             float(rng.uniform(-100, 100)))}


def _synthetic_geometry(rng, generator: str, family: str, n_bin, negative: str) -> dict:
    """Block, lidar and world sizes for about ``n`` tie points at a lidar density, with at most
    :data:`MAX_LIDAR_POINTS` lidar points and a lidar 1.15-3.5 times as wide as the block: the
    tie density is drawn between what that allows and half the corners the world offers (a
    block asking for more gets the corners there are: fewer tie points)."""
    n = int(round(_log_uniform(rng, *n_bin)))
    density = _log_uniform(rng, 0.5, 8.0)
    widest_lidar = np.sqrt(MAX_LIDAR_POINTS / density)
    widest_block = widest_lidar / 1.15
    rho_lo = max(150.0, n / (widest_block / 1000) ** 2)
    u, ratio, aspect = rng.random(), _log_uniform(rng, 1.15, 3.5), float(rng.uniform(1.0, 1.5))
    far = 2.0 if negative == "other-place" else 1.0
    cell = 1.0
    for _ in range(3):  # a coarser world raster has fewer corners: size it again
        rho_hi = max(rho_lo * 1.001, 0.5 * CORNERS_PER_KM2[generator][family] / cell**2)
        rho = float(np.exp(np.log(rho_lo) + u * (np.log(rho_hi) - np.log(rho_lo))))
        block = 1000 * np.sqrt(n / rho)
        lidar = min(ratio * block, widest_lidar)
        world = lidar + 2 * far * 0.9 * block * aspect + 100
        coarser = 1.0 if world <= WORLD_CELLS else 2.0 if world <= 2 * WORLD_CELLS else \
            float(np.ceil(world / WORLD_CELLS * 2) / 2)
        if coarser == cell:
            break
        cell = coarser
    return {"n_target": n, "tie_density_km2": float(rho), "block_m": float(block),
            "aspect": aspect, "lidar_m": float(lidar), "lidar_density": float(density),
            "world_m": float(np.ceil(world / 10) * 10), "cell_m": cell}


def _real_geometry(rng, name: str) -> dict:
    lidar, block, rho, dens = REAL_SIZING[name]
    rho = rho * rng.uniform(0.5, 1.0)
    density = _log_uniform(rng, *dens)
    density = min(density, MAX_LIDAR_POINTS / lidar**2)
    return {"n_target": int(rho * (block / 1000) ** 2), "tie_density_km2": float(rho),
            "block_m": block, "aspect": 1.0, "lidar_m": lidar, "lidar_density": float(density),
            "world_m": 0.0, "cell_m": 0.0}


def _slots() -> list[tuple[str, str, str, str]]:
    """(family, generator, world family, negative) of one half, in a fixed order."""
    slots = []
    for family in SYNTHETIC:
        for generator in GENERATORS:
            slots += [(family, generator, family, "")] * 9
    for i in range(10):  # lidar with unclassified spikes over either generator's worlds
        slots.append(("spikes", GENERATORS[i % 2], SYNTHETIC[i % 5], ""))
    for i in range(12):
        name = REAL[i % 3]
        slots.append((name, GENERATORS[(i // 3) % 2], name, ""))
    for i in range(12):  # negatives: tie points from another world or from beside the lidar
        family = SYNTHETIC[i % 5]
        slots.append((family, GENERATORS[i % 2], family,
                      "other-world" if (i // 2) % 2 == 0 else "other-place"))
    return slots


def all_cases() -> list[Case]:
    """Every case of both halves; the same list on every run."""
    cases = []
    for half, seed0 in HALF_SEED.items():
        for i, (family, generator, world_family, negative) in enumerate(_slots()):
            seed = seed0 + i
            rng = np.random.default_rng([seed, 424242])
            common = _common(rng)
            if family in REAL:
                geometry = _real_geometry(rng, family)
            else:
                n_bin = N_BINS[(i + seed0 // 1000) % len(N_BINS)]
                geometry = _synthetic_geometry(rng, generator, world_family, n_bin, negative)
            spikes = float(rng.uniform(0.005, 0.02)) if family == "spikes" else 0.0
            tag = f"{family}-{generator}" + (f"-{negative}" if negative else "")
            cases.append(Case(f"{half}-{i:03d}-{tag}", half, seed, family, generator,
                              world_family, negative, **geometry, **common,
                              spikes_fraction=spikes))
    return cases


# ------------------------------------------------------------------------------------ scenes
def scene_ready(case: Case) -> bool:
    truth = case.directory / "truth.json"
    if not (truth.exists() and (case.directory / "reference.laz").exists()
            and (case.directory / "moving.npy").exists()):
        return False
    saved = json.loads(truth.read_text())
    return saved.get("scene_version") == SCENE_VERSION and saved.get("case") == _jsonable(case)


def _jsonable(case: Case) -> dict:
    return json.loads(json.dumps(asdict(case)))


def make_case_scene(case: Case) -> dict:
    """Simulate the case's scene and write it; returns its truth."""
    from sensors_alt import GEOREF, add_spikes, write_laz

    rng = np.random.default_rng([case.seed, 5150])
    if case.generator == "tiereg":
        lidar, ties_ref, blunders, overlap, T_ref_mov = _tiereg_scene(case)
    else:
        lidar, ties_ref, blunders, overlap, T_ref_mov = _alt_scene(case, rng)
    if case.spikes_fraction:
        lidar = add_spikes(lidar, case.spikes_fraction, rng)
    out = case.directory
    out.mkdir(parents=True, exist_ok=True)
    write_laz(out / "reference.laz", lidar)
    moving = T_ref_mov.inverse.apply(ties_ref)
    np.save(out / "moving.npy", moving)
    truth = {"scene_version": SCENE_VERSION, "case": _jsonable(case),
             "T_ref_mov": T_ref_mov.matrix.tolist(), "n_tie_points": int(len(moving)),
             "n_blunders": int(blunders), "n_lidar_points": int(len(lidar)),
             "n_spikes": round(case.spikes_fraction * len(lidar) / (1 + case.spikes_fraction)),
             "overlap_measured": float(overlap), "georef": list(GEOREF)}
    (out / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
    return truth


def _tiereg_scene(case: Case):
    """tiereg's simulator: its world, lidar and image block (or its sensors on a real world)."""
    from sensors_alt import GEOREF, Lidar

    from tiereg.simulate import (
        HiddenTransform,
        ImageBlock,
        LidarSurvey,
        SceneSpec,
        make_scene,
        make_world,
    )
    from tiereg.simulate.world import find_corners

    hidden = HiddenTransform(heading_deg=case.heading_deg, scale=case.scale,
                             tilt_deg=case.tilt_deg, model_origin=case.model_origin)
    block = ImageBlock(side_m=case.block_m, image_footprint_m=max(case.block_m / 5, 60.0),
                       tie_points_per_km2=case.tie_density_km2, noise_xy_m=case.noise_z_m / 2,
                       noise_z_m=case.noise_z_m, blunder_fraction=case.blunder_fraction,
                       blunder_xy_m=case.blunder_max_m / 4, blunder_z_m=case.blunder_max_m / 3)
    overlap = 0.0 if case.negative == "other-place" else case.overlap
    if case.family in REAL:
        from real_worlds import load_real_world, real_scene_spec

        world = load_real_world(case.family)
        spec = replace(real_scene_spec(case.family, case.seed, overlap=overlap),
                       lidar_size_m=case.lidar_m, block=block, hidden=hidden,
                       survey=replace(real_scene_spec(case.family, 0).survey,
                                      density_per_m2=case.lidar_density))
    else:
        spec = SceneSpec(kind=case.world_family, seed=case.seed, world_size_m=case.world_m,
                         world_cell_m=case.cell_m, lidar_size_m=case.lidar_m,
                         survey=LidarSurvey(density_per_m2=case.lidar_density), block=block,
                         overlap=overlap, hidden=hidden,
                         tie_world_seed=case.seed + 500 if case.negative == "other-world"
                         else None)
        world = make_world(spec.kind, size_m=spec.world_size_m, cell=spec.world_cell_m,
                           seed=spec.seed)
        world = replace(world, **dict(zip(("corner_rc", "corner_response"), find_corners(
            world.ortho, threshold_rel=TIEREG_CORNER_THRESHOLD))))
    scene = make_scene(spec, world=world)
    lidar = Lidar(scene.lidar.xyz, scene.lidar.return_number, scene.lidar.number_of_returns,
                  scene.lidar.classification)
    ties_ref = scene.tie_points.xyz + np.asarray(GEOREF)
    if case.negative == "other-place":
        overlap_measured = 0.0
    else:
        overlap_measured = scene.overlap
    return (lidar, ties_ref, int(scene.tie_points.blunder.sum()), overlap_measured,
            scene.T_ref_mov)


def _place(rng, overlap: float, case: Case, half_lidar: float) -> np.ndarray:
    """A block centre (world frame) whose share of tie-block area inside the lidar is about
    ``overlap`` (0: just beside it), found by bisection along a random direction."""
    g = (np.arange(30) + 0.5) / 30 - 0.5
    u, v = np.meshgrid(g * case.block_m * case.aspect, g * case.block_m)
    a = np.radians(case.heading_deg)
    probe = np.column_stack([np.cos(a) * u.ravel() - np.sin(a) * v.ravel(),
                             np.sin(a) * u.ravel() + np.cos(a) * v.ravel()])
    d = rng.uniform(0, 2 * np.pi)
    direction = np.array([np.cos(d), np.sin(d)])

    def share(t):
        p = probe + direction * t
        return float(np.mean(np.all(np.abs(p) < half_lidar, axis=1)))

    lo, hi = 0.0, half_lidar * 1.5 + case.block_m * case.aspect
    if share(lo) <= overlap:
        return direction * lo
    for _ in range(40):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if share(mid) > overlap else (lo, mid)
    return direction * hi


def _alt_scene(case: Case, rng):
    """The independent generator and its sensors (or its sensors on a real world)."""
    from sensors_alt import GEOREF, T_mov_ref, fly_lidar, sample_ties
    from worlds_alt import make_alt_world
    from worlds_alt_parts import foerstner_corners

    if case.family in REAL:
        from real_worlds import load_real_world

        world, water = load_real_world(case.family), None
        corners = foerstner_corners(world.ortho, threshold_rel=0.3)
    else:
        alt = make_alt_world(case.world_family, size_m=case.world_m, cell=case.cell_m,
                             seed=case.seed)
        world, water = alt.world, alt.water
        corners = (world.corner_rc, world.corner_response)
    half = case.lidar_m / 2
    lidar = fly_lidar(world, water, centre=(0.0, 0.0), side_m=case.lidar_m,
                      density=case.lidar_density, heading_deg=float(rng.uniform(0, 180)), rng=rng)
    lidar = replace(lidar, xyz=lidar.xyz + np.asarray(GEOREF))
    centre = _place(rng, 0.0 if case.negative == "other-place" else case.overlap, case, half)
    tie_world = world
    if case.negative == "other-world":
        other = make_alt_world(case.world_family, size_m=case.world_m, cell=case.cell_m,
                               seed=case.seed + 500)
        tie_world, corners = other.world, (other.world.corner_rc, other.world.corner_response)
    ties = sample_ties(tie_world, corners, centre=centre, side_m=case.block_m,
                       aspect=case.aspect, heading_deg=case.heading_deg, n=case.n_target,
                       noise_z_m=case.noise_z_m, blunder_fraction=case.blunder_fraction,
                       blunder_max_m=case.blunder_max_m, rng=rng)
    overlap = 0.0 if case.negative else float(
        np.mean(np.all(np.abs(ties.true_xyz[:, :2]) < half, axis=1)))
    ties_ref = ties.xyz + np.asarray(GEOREF)
    centre_ref = np.array([centre[0], centre[1], float(np.median(ties.xyz[:, 2]))]) \
        + np.asarray(GEOREF)
    T = T_mov_ref(centre_ref, heading_deg=case.heading_deg, scale=case.scale,
                  tilt_deg=case.tilt_deg, model_origin=case.model_origin)
    return lidar, ties_ref, int(ties.blunder.sum()), overlap, T.inverse
