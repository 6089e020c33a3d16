"""Real surfaces as :class:`~tiereg.simulate.world.World` objects for the coarse benchmark.

Three small real datasets, prepared by ``data/prepare_real.py`` (provenance in ``data/README.md``),
become worlds on which tie points and lidar are simulated exactly as on the synthetic ones:

============= ======= ============ =================================================================
name          cell    size         surface / orthoimage
============= ======= ============ =================================================================
muscatatuck   1 m     310 x 344 m  CODEM 1 m DSM (buildings, trees) / real aerial grey values
                                   (intensity of CODEM's ``pc.laz``)
longyearbyen  20 m    12 x 12 km   NPI 1990 photogrammetric DTM of Svalbard mountains / synthetic
                                   relief image (hillshade, strata, slope, roughness)
autzen        2 m     988 x 1336 m surface linearly interpolated from 9,079 first returns of the
                                   thinned Autzen 2010 lidar / the Autzen RGB orthophoto in grey
============= ======= ============ =================================================================

Each world is in local metres centred on (0, 0); ``dtm`` is the same raster as ``dsm`` and the
canopy and building masks are empty, so the simulated lidar has single returns off that surface.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tiereg.simulate.scene import SceneSpec
from tiereg.simulate.sensors import ImageBlock, LidarSurvey
from tiereg.simulate.world import World, find_corners

DATA = Path(__file__).resolve().parent / "data"
REAL_WORLDS = ("muscatatuck", "longyearbyen", "autzen")
FT = 0.3048  # international foot, metres (Autzen: EPSG:2994, heights in feet too)
# Corners for tie points: Harris peaks down to 1e-4 of the strongest (find_corners' default, 5e-3,
# keeps a third of them on these images; weak ones are still drawn less often as tie points), on
# the orthoimage after contrast-limited adaptive histogram equalisation, so that dim fields and
# shadows get corners as a feature matcher's local contrast normalisation would give them.
CORNER_THRESHOLD = 1e-4
CLAHE_CLIP = 0.01


def _read(name: str) -> tuple[np.ndarray, float]:
    """A single-band raster of ``data/`` as float64 and its (square) cell size in CRS units."""
    import rasterio

    with rasterio.open(DATA / name) as ds:
        return ds.read(1).astype(np.float64), float(ds.transform.a)


def _autzen_dsm(shape: tuple[int, int], cell_m: float) -> np.ndarray:
    """First returns of the thinned Autzen lidar, linearly interpolated (nearest outside the hull)
    at the cell centres of the orthoimage grid; metres."""
    import laspy
    import rasterio
    from scipy.interpolate import griddata

    with rasterio.open(DATA / "autzen_ortho.tif") as ds:
        left_ft, top_ft = ds.transform.c, ds.transform.f
    las = laspy.read(DATA / "autzen-thin-srs.las")
    first = np.asarray(las.return_number) == 1
    xy = np.column_stack([(np.asarray(las.x)[first] - left_ft) * FT,
                          (top_ft - np.asarray(las.y)[first]) * FT])  # from the upper-left corner
    z = np.asarray(las.z)[first] * FT
    rows, cols = shape
    cx, cy = np.meshgrid((np.arange(cols) + 0.5) * cell_m, (np.arange(rows) + 0.5) * cell_m)
    dsm = griddata(xy, z, (cx, cy), method="linear")
    outside = np.isnan(dsm)
    dsm[outside] = griddata(xy, z, (cx[outside], cy[outside]), method="nearest")
    return dsm


def load_real_world(name: str) -> World:
    """The real world ``name`` (one of :data:`REAL_WORLDS`), read from ``benchmarks/data``."""
    if name not in REAL_WORLDS:
        raise ValueError(f"unknown real world {name!r}; choose from {REAL_WORLDS}")
    grey, cell = _read(f"{name}_ortho.tif")
    if name == "autzen":
        cell = round(cell * FT, 6)  # the grid is in feet: 2 m cells
        dsm = _autzen_dsm(grey.shape, cell)
    else:
        dsm, _ = _read(f"{name}_dsm.tif")
    if dsm.shape != grey.shape:
        raise ValueError(f"{name}: surface {dsm.shape} and orthoimage {grey.shape} differ")
    from skimage.exposure import equalize_adapthist

    ortho = equalize_adapthist(grey / 255.0, clip_limit=CLAHE_CLIP).astype(np.float32)
    rows, cols = dsm.shape
    empty = np.zeros(dsm.shape, bool)
    return World(name, cell, -cols * cell / 2, rows * cell / 2, dsm, dsm, ortho, empty,
                 empty.copy(), *find_corners(ortho, threshold_rel=CORNER_THRESHOLD))


@dataclass(frozen=True)
class _Sizing:
    size_m: float  # shorter side of the world
    cell_m: float
    lidar_m: float  # side of the lidar square, ~0.55 of the shorter side
    block_m: float  # side of the image block, ~0.5 of the shorter side
    ties_per_km2: float  # close to the orthoimage's corner density: most corners become ties
    lidar_per_m2: float
    strip_m: float
    gap_probability: float  # sensors' strip gaps are 100-400 m long: none on the small worlds


# With these sides the block stays inside the world at overlap >= 0.5 (< 3 % of its area off the
# edge on average) and loses 7-14 % at overlap 0.3. The lidar square is barely wider than the
# block, so asking for overlap 1 gives 0.88 (muscatatuck) to 0.98 (longyearbyen) on average.
_SIZING = {
    "muscatatuck": _Sizing(310.0, 1.0, 170.0, 170.0, 16_000.0, 4.0, 60.0, 0.0),
    "longyearbyen": _Sizing(12_000.0, 20.0, 6500.0, 5500.0, 30.0, 0.04, 600.0, 0.1),
    "autzen": _Sizing(988.0, 2.0, 560.0, 520.0, 2_500.0, 1.0, 200.0, 0.0),
}

# The synthetic kind closest to each real surface. ``make_scene`` builds tie worlds from
# ``spec.kind`` for negative cases (``tie_world_seed``), which a real name cannot do: use
# ``replace(spec, kind=LOOKALIKE_KIND[name], tie_world_seed=...)`` with ``world=`` the real world.
LOOKALIKE_KIND = {"muscatatuck": "urban", "longyearbyen": "mountains", "autzen": "suburban"}


def real_scene_spec(name: str, seed: int, *, overlap: float = 1.0) -> SceneSpec:
    """A scene spec sized for the small real world ``name``.

    Pass ``world=load_real_world(name)`` to :func:`~tiereg.simulate.scene.make_scene`; ``kind`` is
    the real world's name, from which no world can be made.
    """
    if name not in REAL_WORLDS:
        raise ValueError(f"unknown real world {name!r}; choose from {REAL_WORLDS}")
    z = _SIZING[name]
    return SceneSpec(
        kind=name, seed=seed, world_size_m=z.size_m, world_cell_m=z.cell_m,
        lidar_size_m=z.lidar_m,
        survey=LidarSurvey(density_per_m2=z.lidar_per_m2, strip_width_m=z.strip_m,
                           gap_probability=z.gap_probability),
        block=ImageBlock(side_m=z.block_m, image_footprint_m=z.block_m / 5,
                         tie_points_per_km2=z.ties_per_km2),
        overlap=overlap)
