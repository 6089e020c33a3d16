"""Synthetic worlds: terrain, parcels, roads, buildings, trees and an orthoimage on one raster.

A :class:`World` holds, on a square raster in local metres (north up, upper-left corner at
``(x0, y0)``, rows southwards as everywhere in tiereg), the bare ground (``dtm``), the visible
surface (``dsm``: ground, roofs, canopy), a grey-level orthoimage whose corners become tie points,
and masks of buildings and canopy. Kinds differ in relief and land cover:

============ ==================================================================================
farmland     low relief, large fields, farm roads, farmsteads, hedgerows
suburban     rolling terrain, a street grid, houses with gable roofs, garden trees
urban        moderate relief, dense blocks of large flat-roofed buildings, street trees
forest       hilly, closed canopy with clearings and forest roads
mountains    high relief with ridges and valleys, sparse trees and huts
============ ==================================================================================
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .._optional import require

KINDS = ("farmland", "suburban", "urban", "forest", "mountains")


@dataclass(frozen=True)
class KindParameters:
    relief_m: float  # standard deviation of the terrain heights
    spectral_slope: float  # terrain power spectrum ~ k^-slope
    ridged: bool  # ridged terrain (mountains)
    parcels_per_km2: float
    parcel_stretch: float  # fields are longer than wide
    road_spacing_m: float  # 0: no street grid
    buildings_per_km2: float
    building_size_m: tuple[float, float]
    building_height_m: tuple[float, float]
    gable_fraction: float
    building_clusters: int  # 0: buildings along the street grid, else this many clusters/km2
    trees_per_km2: float
    tree_cover: float  # fraction of land in closed canopy (forest patches)


KIND_PARAMETERS = {
    "farmland": KindParameters(6.0, 3.2, False, 12.0, 2.5, 900.0, 12.0, (12.0, 40.0),
                               (5.0, 10.0), 0.7, 2, 150.0, 0.05),
    "suburban": KindParameters(20.0, 3.0, False, 60.0, 1.3, 130.0, 700.0, (9.0, 18.0),
                               (5.0, 9.0), 0.85, 0, 1500.0, 0.08),
    "urban": KindParameters(10.0, 3.0, False, 40.0, 1.0, 160.0, 450.0, (18.0, 55.0),
                            (10.0, 45.0), 0.1, 0, 400.0, 0.02),
    "forest": KindParameters(45.0, 2.8, False, 15.0, 1.5, 1200.0, 2.0, (10.0, 20.0),
                             (4.0, 7.0), 0.8, 1, 0.0, 0.85),
    "mountains": KindParameters(250.0, 2.6, True, 8.0, 1.5, 0.0, 3.0, (8.0, 15.0),
                                (4.0, 7.0), 0.9, 1, 300.0, 0.15),
}


@dataclass(frozen=True, eq=False)
class World:
    """Rasters of one synthetic (or real) landscape; local metres, cell centres on a grid."""

    kind: str
    cell: float
    x0: float  # upper-left corner
    y0: float
    dtm: np.ndarray = field(repr=False)
    dsm: np.ndarray = field(repr=False)
    ortho: np.ndarray = field(repr=False)  # grey levels in [0, 1]
    canopy: np.ndarray = field(repr=False)  # vegetation: lidar partly reaches the ground below
    buildings: np.ndarray = field(repr=False)
    corner_rc: np.ndarray = field(repr=False)  # (K, 2) row, col of orthoimage corners
    corner_response: np.ndarray = field(repr=False)  # (K,) Harris response

    @property
    def shape(self) -> tuple[int, int]:
        return self.dsm.shape  # type: ignore[return-value]

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        rows, cols = self.shape
        return (self.x0, self.y0 - rows * self.cell, self.x0 + cols * self.cell, self.y0)

    def rowcol(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        row = (self.y0 - np.asarray(y)) / self.cell - 0.5
        return row, (np.asarray(x) - self.x0) / self.cell - 0.5

    def sample(self, name: str, x: np.ndarray, y: np.ndarray, *, order: int = 1) -> np.ndarray:
        """Bilinear (``order=1``) or nearest (``order=0``) values of a raster at positions."""
        r, c = self.rowcol(x, y)
        raster = getattr(self, name)
        return ndimage.map_coordinates(raster.astype(np.float64), np.vstack([r, c]), order=order,
                                       mode="nearest")


def _fractal(shape: tuple[int, int], cell: float, slope: float, rng: np.random.Generator,
             *, min_wavelength_m: float) -> np.ndarray:
    """Gaussian random field with power spectrum ``~ k^-slope``, unit standard deviation."""
    ky = np.fft.fftfreq(shape[0], d=cell)[:, None]
    kx = np.fft.rfftfreq(shape[1], d=cell)[None, :]
    k = np.hypot(kx, ky)
    k[0, 0] = np.inf
    amp = k ** (-slope / 2) * (k < 1.0 / min_wavelength_m)
    noise = rng.normal(size=(shape[0], kx.shape[1])) + 1j * rng.normal(size=(shape[0], kx.shape[1]))
    field_ = np.fft.irfft2(noise * amp, s=shape)
    return (field_ - field_.mean()) / max(field_.std(), 1e-12)


def _terrain(shape, cell, p: KindParameters, rng) -> np.ndarray:
    base = _fractal(shape, cell, p.spectral_slope, rng, min_wavelength_m=8 * cell)
    if p.ridged:  # sharp ridges and rounded valleys
        base = 1.0 - np.abs(base)
        base = base**2
        base += 0.5 * _fractal(shape, cell, p.spectral_slope + 0.4, rng, min_wavelength_m=8 * cell)
        base = (base - base.mean()) / base.std()
    return p.relief_m * base


def _parcels(xx, yy, p: KindParameters, rng, area_km2: float) -> np.ndarray:
    """Parcel id per cell: a Voronoi partition, stretched along a random direction."""
    n = max(4, int(p.parcels_per_km2 * area_km2))
    a = rng.uniform(0, np.pi)
    u = np.cos(a) * xx + np.sin(a) * yy
    v = (-np.sin(a) * xx + np.cos(a) * yy) * p.parcel_stretch
    seeds = np.column_stack([rng.uniform(u.min(), u.max(), n), rng.uniform(v.min(), v.max(), n)])
    _, ids = cKDTree(seeds).query(np.column_stack([u.ravel(), v.ravel()]), workers=-1)
    return ids.reshape(xx.shape)


def _roads(xx, yy, p: KindParameters, rng) -> tuple[np.ndarray, float]:
    """A rotated street grid (with a few streets missing) and its orientation."""
    angle = rng.uniform(0, np.pi / 2)
    mask = np.zeros(xx.shape, bool)
    if p.road_spacing_m <= 0:
        return mask, angle
    u = np.cos(angle) * xx + np.sin(angle) * yy + rng.uniform(0, p.road_spacing_m)
    v = -np.sin(angle) * xx + np.cos(angle) * yy + rng.uniform(0, p.road_spacing_m)
    half = rng.uniform(3.0, 5.0)
    for coord in (u, v):
        d = np.abs((coord + p.road_spacing_m / 2) % p.road_spacing_m - p.road_spacing_m / 2)
        line = np.floor((coord + p.road_spacing_m / 2) / p.road_spacing_m)
        keep = (np.abs(np.sin(line * 12.9898) * 43758.5453) % 1.0) > 0.2  # drop ~20 % of streets
        mask |= (d < half) & keep
    return mask, angle


def _buildings(world_xy, shape, cell, p: KindParameters, rng, roads: np.ndarray,
               road_angle: float, area_km2: float):
    """Rotated rectangles with flat or gable roofs: (height above ground, roof grey levels)."""
    xx, yy = world_xy
    height = np.zeros(shape)
    grey = np.full(shape, np.nan)
    n = int(p.buildings_per_km2 * area_km2)
    if n == 0:
        return height, grey
    x_lo, x_hi, y_lo, y_hi = xx.min(), xx.max(), yy.min(), yy.max()
    if p.building_clusters:
        k = max(1, int(p.building_clusters * area_km2))
        centres = np.column_stack([rng.uniform(x_lo, x_hi, k), rng.uniform(y_lo, y_hi, k)])
        pick = centres[rng.integers(0, k, n)] + rng.normal(0, 60, (n, 2))
    else:
        pick = np.column_stack([rng.uniform(x_lo, x_hi, n), rng.uniform(y_lo, y_hi, n)])
    x0, y0 = xx[0, 0] - cell / 2, yy[0, 0] + cell / 2
    for cx, cy in pick:
        w, length = rng.uniform(*p.building_size_m, 2)
        angle = road_angle + rng.choice([0.0, np.pi / 2]) + rng.normal(0, 0.05)
        h = rng.uniform(*p.building_height_m)
        half = 0.5 * np.hypot(w, length)
        c0, c1 = int((cx - half - x0) / cell), int((cx + half - x0) / cell) + 1
        r0, r1 = int((y0 - cy - half) / cell), int((y0 - cy + half) / cell) + 1
        if c0 < 0 or r0 < 0 or c1 > shape[1] or r1 > shape[0]:
            continue
        sx, sy = xx[r0:r1, c0:c1] - cx, yy[r0:r1, c0:c1] - cy
        u = np.cos(angle) * sx + np.sin(angle) * sy
        v = -np.sin(angle) * sx + np.cos(angle) * sy
        inside = (np.abs(u) < length / 2) & (np.abs(v) < w / 2)
        if not inside.any() or roads[r0:r1, c0:c1][inside].mean() > 0.05:
            continue
        if height[r0:r1, c0:c1][inside].max() > 0:  # no overlapping buildings
            continue
        if rng.random() < p.gable_fraction:
            ridge = rng.uniform(2.0, 5.0)
            roof = h + ridge * (1.0 - np.abs(v) / (w / 2))
            shade = np.where(v > 0, 0.75, 0.45) + rng.uniform(-0.1, 0.1)
        else:
            roof = np.full(u.shape, h)
            shade = np.full(u.shape, rng.uniform(0.55, 0.9))
        height[r0:r1, c0:c1] = np.where(inside, roof, height[r0:r1, c0:c1])
        grey[r0:r1, c0:c1] = np.where(inside, shade, grey[r0:r1, c0:c1])
    return height, grey


def _trees(shape, cell, p: KindParameters, rng, free: np.ndarray, area_km2: float,
           parcels: np.ndarray) -> np.ndarray:
    """Canopy height above ground: paraboloid crowns, scattered trees and closed stands."""
    seeds = np.full(shape, -1e6)
    n_scatter = int(p.trees_per_km2 * area_km2)
    stands = np.zeros(shape, bool)
    if p.tree_cover > 0:  # whole parcels become woodland until the cover is reached
        ids = rng.permutation(parcels.max() + 1)
        frac = np.bincount(parcels.ravel(), minlength=ids.size) / parcels.size
        chosen = ids[np.cumsum(frac[ids]) <= p.tree_cover]
        stands = np.isin(parcels, chosen) & free
    n_stand = int(stands.sum() * cell * cell / 40.0)  # one crown per 40 m2 in closed stands
    rows = np.concatenate([rng.integers(0, shape[0], n_scatter),
                           np.flatnonzero(stands)[rng.integers(0, max(stands.sum(), 1),
                                                               n_stand)] // shape[1]])
    cols = np.concatenate([rng.integers(0, shape[1], n_scatter),
                           np.flatnonzero(stands)[rng.integers(0, max(stands.sum(), 1),
                                                               n_stand)] % shape[1]])
    if n_stand:  # the two index draws above must pick the same cells
        pick = np.flatnonzero(stands)[rng.integers(0, stands.sum(), n_stand)]
        rows[n_scatter:], cols[n_scatter:] = pick // shape[1], pick % shape[1]
    ok = free[rows, cols]
    heights = rng.uniform(8.0, 28.0, ok.sum())
    np.maximum.at(seeds, (rows[ok], cols[ok]), heights)
    canopy = np.zeros(shape)
    for radius in (3.0, 5.0, 7.0):  # crowns of three sizes: grey dilation with a paraboloid
        r = int(np.ceil(radius / cell))
        dy, dx = np.mgrid[-r : r + 1, -r : r + 1] * cell
        d2 = (dx**2 + dy**2) / radius**2
        structure = np.where(d2 <= 1.0, -4.0 * d2, -1e6)
        part = np.where(rng.random(shape) < 1 / 3, seeds, -1e6)
        canopy = np.maximum(canopy, ndimage.grey_dilation(part, structure=structure))
    canopy[canopy < 1.0] = 0.0
    return canopy * free


def find_corners(image: np.ndarray, *, threshold_rel: float = 0.005) -> tuple[np.ndarray,
                                                                              np.ndarray]:
    """Harris corners (Harris & Stephens 1988, via scikit-image) as local maxima of the response.

    The local maxima come from a 5x5 maximum filter, which finds what ``corner_peaks`` finds up to
    its distance pruning, at a fraction of the cost on large images.
    """
    skimage_feature = require("skimage.feature", extra="simulate", feature="the simulator")
    response = skimage_feature.corner_harris(image.astype(np.float64), sigma=1.0)
    peak = (response == ndimage.maximum_filter(response, size=5)) & (
        response > threshold_rel * response.max())
    peak[:2, :] = peak[-2:, :] = peak[:, :2] = peak[:, -2:] = False
    rc = np.argwhere(peak)
    return rc, response[rc[:, 0], rc[:, 1]]


def make_world(kind: str, *, size_m: float = 5000.0, cell: float = 2.0, seed: int = 0) -> World:
    """A square world of ``size_m`` metres centred on (0, 0)."""
    if kind not in KIND_PARAMETERS:
        raise ValueError(f"unknown world kind {kind!r}; choose from {KINDS}")
    p = KIND_PARAMETERS[kind]
    rng = np.random.default_rng(seed)
    n = int(round(size_m / cell))
    shape = (n, n)
    x0, y0 = -n * cell / 2, n * cell / 2
    xs = x0 + (np.arange(n) + 0.5) * cell
    ys = y0 - (np.arange(n) + 0.5) * cell
    xx, yy = np.meshgrid(xs, ys)
    area = (n * cell / 1000.0) ** 2
    dtm = _terrain(shape, cell, p, rng) + 200.0
    parcels = _parcels(xx, yy, p, rng, area)
    roads, road_angle = _roads(xx, yy, p, rng)
    b_height, b_grey = _buildings((xx, yy), shape, cell, p, rng, roads, road_angle, area)
    buildings = b_height > 0
    canopy_h = _trees(shape, cell, p, rng, ~(buildings | roads), area, parcels)
    canopy = canopy_h > 0
    dsm = dtm + np.maximum(b_height, canopy_h)

    # orthoimage: parcel reflectance with texture, roads, roofs, crowns; shaded by the relief
    reflect = rng.uniform(0.3, 0.85, parcels.max() + 1)[parcels]
    texture = 0.06 * _fractal(shape, cell, 1.0, rng, min_wavelength_m=2 * cell)
    grey = reflect + texture
    grey = np.where(roads, 0.25 + 0.03 * texture, grey)
    grey = np.where(buildings, b_grey, grey)
    gy, gx = np.gradient(dsm, cell)
    shade = np.clip(0.6 + 0.4 * (-gx - gy) / np.sqrt(2 + gx**2 + gy**2), 0.2, 1.0)
    crowns = 0.18 + 0.25 * shade + 0.03 * texture
    grey = np.where(canopy, crowns, grey * (0.75 + 0.25 * shade))
    ortho = np.clip(grey, 0.0, 1.0).astype(np.float32)
    return World(kind, cell, x0, y0, dtm, dsm, ortho, canopy, buildings, *find_corners(ortho))
