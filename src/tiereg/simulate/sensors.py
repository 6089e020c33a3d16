"""Sensors over a :class:`~tiereg.simulate.world.World`: an airborne lidar and an image block.

The lidar flies parallel strips with side overlap, sometimes leaves a gap, returns first echoes
from roofs and canopy and, under canopy, last echoes from the ground. The image block is a
regular photogrammetric flight (forward and side overlap); its tie points sit at radiometric
corners of the orthoimage, more often where more images see the ground, with heights of the
visible surface, Gaussian noise and a share of blunders.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .world import World

# ASPRS classes
GROUND, UNCLASSIFIED, HIGH_VEGETATION, BUILDING = 2, 1, 5, 6


@dataclass(frozen=True, eq=False)
class LidarPoints:
    xyz: np.ndarray = field(repr=False)
    return_number: np.ndarray = field(repr=False)
    number_of_returns: np.ndarray = field(repr=False)
    classification: np.ndarray = field(repr=False)


@dataclass(frozen=True)
class LidarSurvey:
    """Flight parameters of the lidar."""

    density_per_m2: float = 2.0
    strip_width_m: float = 600.0
    side_overlap: float = 0.2
    heading_deg: float | None = None  # None: random
    gap_probability: float = 0.1  # chance that a strip has a gap
    canopy_penetration: float = 0.4  # share of canopy pulses with a last return on the ground
    noise_z_m: float = 0.05
    noise_xy_m: float = 0.10


def sample_lidar(
    world: World,
    footprint: tuple[float, float, float, float],
    survey: LidarSurvey = LidarSurvey(),
    *,
    rng: np.random.Generator,
) -> LidarPoints:
    """Lidar points over the ``(xmin, ymin, xmax, ymax)`` footprint, in world coordinates."""
    xmin, ymin, xmax, ymax = footprint
    heading = np.radians(rng.uniform(0, 180) if survey.heading_deg is None else survey.heading_deg)
    d = np.array([np.cos(heading), np.sin(heading)])  # along track
    n_ = np.array([-d[1], d[0]])  # across track
    corners = np.array([[xmin, ymin], [xmin, ymax], [xmax, ymin], [xmax, ymax]])
    cx, cy = (xmin + xmax) / 2, (ymin + ymax) / 2
    across = (corners - [cx, cy]) @ n_
    along = (corners - [cx, cy]) @ d
    step = survey.strip_width_m * (1 - survey.side_overlap)
    offsets = np.arange(across.min(), across.max() + step, step)
    parts = []
    for off in offsets:
        area = survey.strip_width_m * (along.max() - along.min())
        n = rng.poisson(survey.density_per_m2 * area / (1 + survey.side_overlap))
        u = rng.uniform(along.min(), along.max(), n)
        v = off + rng.uniform(-0.5, 0.5, n) * survey.strip_width_m
        if rng.random() < survey.gap_probability:  # a stretch of this strip was not recorded
            g0 = rng.uniform(along.min(), along.max())
            keep = np.abs(u - g0) > rng.uniform(100, 400)
            u, v = u[keep], v[keep]
        xy = np.column_stack([cx + u * d[0] + v * n_[0], cy + u * d[1] + v * n_[1]])
        parts.append(xy)
    xy = np.concatenate(parts)
    xy = xy[(xy[:, 0] >= xmin) & (xy[:, 0] < xmax) & (xy[:, 1] >= ymin) & (xy[:, 1] < ymax)]
    x, y = xy[:, 0], xy[:, 1]
    under_canopy = world.sample("canopy", x, y, order=0) > 0.5
    on_building = world.sample("buildings", x, y, order=0) > 0.5
    z_first = world.sample("dsm", x, y)
    second = under_canopy & (rng.random(len(x)) < survey.canopy_penetration)
    z_ground = world.sample("dtm", x[second], y[second])
    xs = np.concatenate([x, x[second]])
    ys = np.concatenate([y, y[second]])
    zs = np.concatenate([z_first, z_ground])
    nret = np.concatenate([np.where(second, 2, 1), np.full(second.sum(), 2)]).astype(np.uint8)
    rnum = np.concatenate([np.ones(len(x)), np.full(second.sum(), 2)]).astype(np.uint8)
    cls = np.concatenate([
        np.where(under_canopy, HIGH_VEGETATION, np.where(on_building, BUILDING, GROUND)),
        np.full(second.sum(), GROUND),
    ]).astype(np.uint8)
    m = len(xs)
    xyz = np.column_stack([
        xs + rng.normal(0, survey.noise_xy_m, m),
        ys + rng.normal(0, survey.noise_xy_m, m),
        zs + rng.normal(0, survey.noise_z_m, m),
    ])
    return LidarPoints(xyz, rnum, nret, cls)


@dataclass(frozen=True)
class ImageBlock:
    """The photogrammetric flight and its tie points."""

    side_m: float = 3000.0  # square block
    image_footprint_m: float = 600.0
    forward_overlap: float = 0.6
    side_overlap: float = 0.3
    tie_points_per_km2: float = 350.0
    min_rays: int = 2  # a tie point is seen in at least this many images
    noise_xy_m: float = 0.15
    noise_z_m: float = 0.3
    blunder_fraction: float = 0.02
    blunder_xy_m: float = 10.0
    blunder_z_m: float = 20.0


@dataclass(frozen=True, eq=False)
class TiePoints:
    xyz: np.ndarray = field(repr=False)  # world frame
    rays: np.ndarray = field(repr=False)  # images that see each point
    blunder: np.ndarray = field(repr=False)
    true_xyz: np.ndarray = field(repr=False)  # before noise and blunders (on the surface)


def sample_tie_points(
    world: World,
    centre: tuple[float, float],
    block: ImageBlock = ImageBlock(),
    *,
    heading_deg: float = 0.0,
    rng: np.random.Generator,
) -> TiePoints:
    """Tie points of an image block centred on ``centre`` (world coordinates)."""
    half = block.side_m / 2
    a = np.radians(heading_deg)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    rows, cols = world.corner_rc[:, 0], world.corner_rc[:, 1]
    response = world.corner_response
    # corners are known to the cell; place them anywhere inside it
    x = world.x0 + (cols + rng.uniform(0, 1, len(cols))) * world.cell
    y = world.y0 - (rows + rng.uniform(0, 1, len(rows))) * world.cell
    local = (np.column_stack([x, y]) - centre) @ rot  # block frame: strips along local x
    inside = np.all(np.abs(local) < half, axis=1)
    local, x, y, response = local[inside], x[inside], y[inside], response[inside]
    # images on a regular grid; a point is seen by the images whose footprint contains it
    f = block.image_footprint_m
    base_along = f * (1 - block.forward_overlap)
    base_across = f * (1 - block.side_overlap)
    cu = np.arange(-half, half + base_along, base_along)
    cv = np.arange(-half, half + base_across, base_across)
    ru = (np.abs(local[:, 0:1] - cu[None, :]) < f / 2).sum(axis=1)
    rv = (np.abs(local[:, 1:2] - cv[None, :]) < f / 2).sum(axis=1)
    rays = ru * rv
    weight = np.sqrt(np.maximum(response, 0)) * np.maximum(rays - block.min_rays + 1, 0)
    area_km2 = (block.side_m / 1000) ** 2
    n = min(int(round(block.tie_points_per_km2 * area_km2)), int((weight > 0).sum()))
    pick = rng.choice(len(x), size=n, replace=False, p=weight / weight.sum())
    x, y, rays = x[pick], y[pick], rays[pick]
    true = np.column_stack([x, y, world.sample("dsm", x, y)])
    xyz = true + rng.normal(0, [block.noise_xy_m, block.noise_xy_m, block.noise_z_m], true.shape)
    blunder = rng.random(n) < block.blunder_fraction
    k = int(blunder.sum())
    xyz[blunder, :2] += rng.normal(0, block.blunder_xy_m, (k, 2))
    xyz[blunder, 2] += rng.choice([-1, 1], k) * rng.uniform(3, 3 * block.blunder_z_m, k)
    return TiePoints(xyz, rays, blunder, true)
