"""Sensors of a second design over any :class:`~tiereg.simulate.World`, independent of
``tiereg.simulate.sensors``: an image block's tie points, an airborne lidar, spikes, a LAZ file.

* Tie points: Foerstner corners of the orthoimage (``worlds_alt_parts.foerstner_corners``) inside
  a rectangular block of any heading, drawn with probability growing with the corner's strength
  and falling towards the block's edge (fewer images there); the height is that of the surface
  cell the corner lies in (a roof corner is on the roof, not half-way down a bilinear wall),
  Gaussian noise (horizontal half the vertical) and a share of blunders.
* Lidar: parallel strips with side lap, zig-zag scan lines across the track (points along a line
  at the across-track spacing, lines alternating in direction), first returns off the surface
  (a little into crowns), last returns off the ground under a share of crown hits, few returns
  off open water; ASPRS classes 2, 5, 6, 9.
* Spikes: unclassified (class 1) returns far above the ground (birds, clouds, multipath).
* ``write_laz``: LAS 1.4 point format 6, millimetre scales, a projected CRS (EPSG:32632 by
  default) at a georeference offset.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from tiereg.simulate import World
from tiereg.transform import Transform

GROUND, UNCLASSIFIED, VEGETATION, BUILDING, WATER = 2, 1, 5, 6, 9
GEOREF = (500_000.0, 5_000_000.0, 0.0)


@dataclass(frozen=True, eq=False)
class Ties:
    xyz: np.ndarray = field(repr=False)  # world frame, with noise and blunders
    true_xyz: np.ndarray = field(repr=False)
    blunder: np.ndarray = field(repr=False)


@dataclass(frozen=True, eq=False)
class Lidar:
    xyz: np.ndarray = field(repr=False)
    return_number: np.ndarray = field(repr=False)
    number_of_returns: np.ndarray = field(repr=False)
    classification: np.ndarray = field(repr=False)

    def __len__(self) -> int:
        return len(self.xyz)


def _cells(world: World, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = world.shape
    r = np.clip(((world.y0 - y) / world.cell).astype(int), 0, rows - 1)
    c = np.clip(((x - world.x0) / world.cell).astype(int), 0, cols - 1)
    return r, c


def _bilinear(world: World, raster: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    r = (world.y0 - y) / world.cell - 0.5
    c = (x - world.x0) / world.cell - 0.5
    return ndimage.map_coordinates(raster, np.vstack([r, c]), order=1, mode="nearest")


def in_block(xy: np.ndarray, centre, side_m: float, aspect: float, heading_deg: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """(inside, margin to the edge in metres) of points in a ``side_m * aspect`` x ``side_m``
    rectangle centred on ``centre``, its long side along ``heading_deg``."""
    a = np.radians(heading_deg)
    d = np.asarray(xy)[:, :2] - np.asarray(centre)[:2]
    u = np.cos(a) * d[:, 0] + np.sin(a) * d[:, 1]
    v = -np.sin(a) * d[:, 0] + np.cos(a) * d[:, 1]
    margin = np.minimum(side_m * aspect / 2 - np.abs(u), side_m / 2 - np.abs(v))
    return margin > 0, margin


def sample_ties(world: World, corners: tuple[np.ndarray, np.ndarray], *, centre, side_m: float,
                aspect: float, heading_deg: float, n: int, noise_z_m: float,
                blunder_fraction: float, blunder_max_m: float, rng: np.random.Generator) -> Ties:
    """At most ``n`` tie points at the corners inside the block (fewer if it has fewer)."""
    rc, strength = corners
    x = world.x0 + (rc[:, 1] + rng.uniform(0, 1, len(rc))) * world.cell
    y = world.y0 - (rc[:, 0] + rng.uniform(0, 1, len(rc))) * world.cell
    inside, margin = in_block(np.column_stack([x, y]), centre, side_m, aspect, heading_deg)
    weight = np.sqrt(np.maximum(strength, 0)) * np.clip(margin / (0.08 * side_m), 0.25, 1.0)
    weight = np.where(inside, weight, 0.0)
    k = min(int(n), int((weight > 0).sum()))
    if k == 0:
        raise ValueError("no orthoimage corner inside the block")
    pick = rng.choice(len(x), size=k, replace=False, p=weight / weight.sum())
    x, y = x[pick], y[pick]
    r, c = _cells(world, x, y)
    true = np.column_stack([x, y, world.dsm[r, c]])
    xyz = true + rng.normal(0, [noise_z_m / 2, noise_z_m / 2, noise_z_m], true.shape)
    blunder = rng.random(k) < blunder_fraction
    m = int(blunder.sum())
    xyz[blunder, 2] += rng.choice([-1.0, 1.0], m) * rng.uniform(2.0, blunder_max_m, m)
    ang, rad = rng.uniform(0, 2 * np.pi, m), rng.uniform(0, blunder_max_m / 4, m)
    xyz[blunder, 0] += rad * np.cos(ang)
    xyz[blunder, 1] += rad * np.sin(ang)
    return Ties(xyz, true, blunder)


def _strip_points(centre, side_m: float, density: float, heading: float, swath: float,
                  sidelap: float, rng: np.random.Generator) -> np.ndarray:
    """(x, y) of all strips' pulses over the square footprint, zig-zag scan lines."""
    per_strip = density * (1 - sidelap)  # overlaps bring the mean back to ``density``
    spacing = np.sqrt(1.0 / (1.3 * per_strip))  # along a scan line; lines 1.3 x farther apart
    half = side_m / np.sqrt(2) + swath
    along_dir = np.array([np.cos(heading), np.sin(heading)])
    across_dir = np.array([-along_dir[1], along_dir[0]])
    parts = []
    step = swath * (1 - sidelap)
    for off in np.arange(-half + swath / 2, half, step):
        lines = np.arange(-half, half, 1.3 * spacing)
        pos = np.arange(-swath / 2, swath / 2, spacing)
        li, pj = np.meshgrid(np.arange(len(lines)), np.arange(len(pos)), indexing="ij")
        zig = np.where(li % 2 == 0, pj, len(pos) - 1 - pj) / max(len(pos), 1) - 0.5
        a = lines[li] + zig * 1.3 * spacing * 0.6 + rng.normal(0, 0.05 * spacing, li.shape)
        b = off + pos[pj] + rng.normal(0, 0.05 * spacing, li.shape)
        xy = np.asarray(centre)[:2] + a.ravel()[:, None] * along_dir + b.ravel()[:, None] \
            * across_dir
        keep = np.all(np.abs(xy - np.asarray(centre)[:2]) < side_m / 2, axis=1)
        parts.append(xy[keep])
    return np.concatenate(parts)


def fly_lidar(world: World, water: np.ndarray | None, *, centre, side_m: float, density: float,
              heading_deg: float, rng: np.random.Generator, sidelap: float = 0.25,
              noise_z_m: float = 0.04, noise_xy_m: float = 0.08, penetration: float = 0.35,
              water_returns: float = 0.1) -> Lidar:
    """Lidar over the axis-aligned square ``side_m`` footprint around ``centre`` (world frame)."""
    swath = float(np.clip(side_m / 3, 150, 700))
    xy = _strip_points(centre, side_m, density, np.radians(heading_deg), swath, sidelap, rng)
    x, y = xy[:, 0], xy[:, 1]
    r, c = _cells(world, x, y)
    if water is not None:
        keep = ~water[r, c] | (rng.random(len(x)) < water_returns)
        x, y, r, c = x[keep], y[keep], r[keep], c[keep]
    on_water = water[r, c] if water is not None else np.zeros(len(x), bool)
    veg, bld = world.canopy[r, c], world.buildings[r, c]
    dsm, dtm = _bilinear(world, world.dsm, x, y), _bilinear(world, world.dtm, x, y)
    z1 = np.where(veg, dsm - rng.uniform(0, 0.25, len(x)) * np.maximum(dsm - dtm, 0), dsm)
    last = veg & (rng.random(len(x)) < penetration)
    xs, ys = np.concatenate([x, x[last]]), np.concatenate([y, y[last]])
    zs = np.concatenate([z1, dtm[last]])
    nret = np.concatenate([np.where(last, 2, 1), np.full(last.sum(), 2)]).astype(np.uint8)
    rnum = np.concatenate([np.ones(len(x)), np.full(last.sum(), 2)]).astype(np.uint8)
    cls = np.where(veg, VEGETATION, np.where(bld, BUILDING, np.where(on_water, WATER, GROUND)))
    cls = np.concatenate([cls, np.full(last.sum(), GROUND)]).astype(np.uint8)
    m = len(xs)
    xyz = np.column_stack([xs + rng.normal(0, noise_xy_m, m), ys + rng.normal(0, noise_xy_m, m),
                           zs + rng.normal(0, noise_z_m, m)])
    return Lidar(xyz, rnum, nret, cls)


def add_spikes(lidar: Lidar, fraction: float, rng: np.random.Generator, *,
               height_m: tuple[float, float] = (20.0, 1500.0)) -> Lidar:
    """``fraction`` more points, unclassified, ``height_m`` (log-uniform) above real returns."""
    k = int(round(fraction * len(lidar)))
    if k == 0:
        return lidar
    base = lidar.xyz[rng.integers(0, len(lidar), k)]
    up = np.exp(rng.uniform(np.log(height_m[0]), np.log(height_m[1]), k))
    spikes = base + np.column_stack([rng.normal(0, 1, (k, 2)), up])
    one = np.ones(k, np.uint8)
    return Lidar(np.vstack([lidar.xyz, spikes]), np.concatenate([lidar.return_number, one]),
                 np.concatenate([lidar.number_of_returns, one]),
                 np.concatenate([lidar.classification, one * UNCLASSIFIED]))


def write_laz(path: Path, lidar: Lidar, *, epsg: int = 32632) -> Path:
    """LAS 1.4 / point format 6 / 1 mm scales / CRS ``epsg``; coordinates as given (already
    georeferenced)."""
    import laspy
    import pyproj

    path = Path(path)
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(lidar.xyz.min(axis=0))
    header.add_crs(pyproj.CRS.from_epsg(epsg))
    data = laspy.LasData(header)
    data.x, data.y, data.z = lidar.xyz.T
    data.return_number = lidar.return_number
    data.number_of_returns = lidar.number_of_returns
    data.classification = lidar.classification
    tmp = path.with_suffix(".tmp.laz")
    data.write(tmp, do_compress=True)
    tmp.replace(path)
    return path


def T_mov_ref(centre_ref, *, heading_deg: float, scale: float, tilt_deg=(0.0, 0.0),
              model_origin=(0.0, 0.0, 0.0)) -> Transform:
    """The hidden similarity into a model frame: about ``centre_ref``, scaled by ``scale``
    (model units per reference unit), turned by ``heading_deg`` and tilted, then moved to
    ``model_origin``."""
    local = Transform.from_parameters(scale=scale, omega=np.radians(tilt_deg[0]),
                                      phi=np.radians(tilt_deg[1]), kappa=np.radians(heading_deg))
    return (Transform.from_translation(model_origin) @ local
            @ Transform.from_translation(-np.asarray(centre_ref, dtype=np.float64)))
