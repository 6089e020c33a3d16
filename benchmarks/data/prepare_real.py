"""Build the small real-surface files of ``benchmarks/data/`` from the original files.

Run once; the outputs are committed and ``benchmarks/real_worlds.py`` reads only them:

    .venv/bin/python benchmarks/data/prepare_real.py [--source PATH/TO/ORIGINALS]

======================== ==============================================================
muscatatuck_dsm.tif      CODEM ``dem.tif`` (1 m DSM), cropped to the columns that
                         ``pc.laz`` covers; its no-data corner filled from ``pc.laz``
muscatatuck_ortho.tif    ``pc.laz`` intensity (an aerial image's grey value), mean per 1 m cell
longyearbyen_dsm.tif     NPI 1990 DTM20, a 12 km x 12 km (600 x 600 px) mountainous window
longyearbyen_ortho.tif   synthetic grey image of that window: hillshade, height strata, slope,
                         roughness (deterministic, derived from the DTM only)
autzen_ortho.tif         ``autzen.jpg`` in grey, averaged onto a 2 m grid (EPSG:2994, feet)
autzen-thin-srs.las      copy of the thinned Autzen lidar (feet); gridded when loaded
======================== ==============================================================

See ``README.md`` here for provenance and licences.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import laspy
import numpy as np
import rasterio
from rasterio.crs import CRS
from rasterio.transform import Affine
from rasterio.warp import Resampling, reproject
from scipy import ndimage

HERE = Path(__file__).resolve().parent
FT = 0.3048  # international foot, metres

MUSCATATUCK_COLS = 310  # pc.laz covers the first 310 of the 405 DEM columns
LONGYEARBYEN_WINDOW = (25, 400, 600, 600)  # row, col, rows, cols: the steepest 12 km square
AUTZEN_CELL_M = 2.0


def _write(path: Path, array: np.ndarray, transform: Affine, crs: CRS) -> None:
    float_ = array.dtype.kind == "f"
    profile = {"driver": "GTiff", "width": array.shape[1], "height": array.shape[0], "count": 1,
               "dtype": array.dtype, "crs": crs, "transform": transform, "compress": "deflate",
               "predictor": 3 if float_ else 2, "zlevel": 9}
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(array, 1)


def _cell_mean(x, y, values, transform: Affine, shape) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``values`` per raster cell and the number of points per cell."""
    col = np.floor((x - transform.c) / transform.a).astype(np.int64)
    row = np.floor((y - transform.f) / transform.e).astype(np.int64)
    ok = (row >= 0) & (row < shape[0]) & (col >= 0) & (col < shape[1])
    idx = row[ok] * shape[1] + col[ok]
    total = np.bincount(idx, weights=values[ok], minlength=shape[0] * shape[1])
    count = np.bincount(idx, minlength=shape[0] * shape[1])
    mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return mean.reshape(shape), count.reshape(shape)


def muscatatuck(src: Path, out: Path) -> None:
    with rasterio.open(src / "codem-muscatatuck" / "dem.tif") as ds:
        dem = ds.read(1, masked=True)[:, :MUSCATATUCK_COLS]
        transform = ds.transform
    pc = laspy.read(src / "codem-muscatatuck" / "pc.laz")
    x, y = np.asarray(pc.x), np.asarray(pc.y)
    grey, count = _cell_mean(x, y, np.asarray(pc.intensity, np.float64), transform, dem.shape)
    if (count == 0).any():  # does not happen in this crop; fill from the nearest cell anyway
        idx = ndimage.distance_transform_edt(count == 0, return_distances=False,
                                             return_indices=True)
        grey = grey[tuple(idx)]
    # no-data cells of the DEM (a corner of a field): pc.laz heights, shifted onto the DEM
    z_pc, _ = _cell_mean(x, y, np.asarray(pc.z, np.float64), transform, dem.shape)
    hole = np.ma.getmaskarray(dem)
    offset = np.nanmedian(dem.filled(np.nan) - z_pc)
    dsm = np.where(hole, z_pc + offset, dem.filled(np.nan))
    crs = CRS.from_epsg(32616)
    _write(out / "muscatatuck_dsm.tif", dsm.astype(np.float32), transform, crs)
    _write(out / "muscatatuck_ortho.tif", np.clip(np.round(grey), 0, 255).astype(np.uint8),
           transform, crs)


def relief_image(z: np.ndarray, cell: float) -> np.ndarray:
    """A deterministic grey image of a bare DTM, in [0, 1].

    Reflectance of horizontal strata (40 m thick, grey level from a hash of the stratum's
    index), darkened on steep faces and lit by a hillshade from the north-west, plus the DTM's own
    fine relief as texture. The strata boundaries are contour lines: they bend at ridges and
    gullies, which gives the corner detector something to find.
    """
    gy, gx = np.gradient(z, cell)  # gy: per row, i.e. towards the south
    slope = np.hypot(gx, gy)
    sun = np.array([-1.0, 1.0, 1.0]) / np.sqrt(3.0)  # (east, north, up): north-west, 35 deg up
    normal_dot_sun = -gx * sun[0] + gy * sun[1] + sun[2]  # normal ~ (-dz/dx, -dz/dnorth, 1)
    shade = np.clip(normal_dot_sun / np.sqrt(1 + slope**2), 0.0, 1.0)
    stratum = np.floor(z / 40.0)
    reflect = 0.35 + 0.45 * (np.abs(np.sin(stratum * 12.9898) * 43758.5453) % 1.0)
    rough = z - ndimage.gaussian_filter(z, 2.0)
    grey = reflect * (0.35 + 0.65 * shade) * (1.0 - 0.25 * np.clip(slope, 0, 1))
    grey = grey + 0.08 * np.tanh(rough / 5.0)
    return np.clip(grey, 0.0, 1.0)


def longyearbyen(src: Path, out: Path) -> None:
    r0, c0, nr, nc = LONGYEARBYEN_WINDOW
    path = src / "xdem-longyearbyen-dem1990" / "DEM_1990_NPI_S0_DTM20_199095.tif"
    with rasterio.open(path) as ds:
        window = rasterio.windows.Window(c0, r0, nc, nr)
        z = ds.read(1, window=window).astype(np.float32)
        transform = ds.window_transform(window)
        crs = ds.crs
    _write(out / "longyearbyen_dsm.tif", z, transform, crs)
    grey = relief_image(z.astype(np.float64), transform.a)
    _write(out / "longyearbyen_ortho.tif", np.round(grey * 255).astype(np.uint8), transform, crs)


def autzen(src: Path, out: Path) -> None:
    folder = src / "autzen-als-2010"
    crs = CRS.from_wkt((folder / "autzen-srs.wkt").read_text())
    with rasterio.open(folder / "autzen.jpg") as ds:  # georeferenced by autzen.wld
        rgb = ds.read().astype(np.float32)
        transform = ds.transform
    grey = 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]  # ITU-R BT.601 luma
    cell_ft = AUTZEN_CELL_M / FT
    shape = (int(grey.shape[0] * transform.a * FT // AUTZEN_CELL_M),
             int(grey.shape[1] * transform.a * FT // AUTZEN_CELL_M))
    dst_transform = Affine(cell_ft, 0.0, transform.c, 0.0, -cell_ft, transform.f)
    small = np.zeros(shape, np.float32)
    reproject(grey, small, src_transform=transform, src_crs=crs, dst_transform=dst_transform,
              dst_crs=crs, resampling=Resampling.average)
    _write(out / "autzen_ortho.tif", np.clip(np.round(small), 0, 255).astype(np.uint8),
           dst_transform, crs)
    shutil.copyfile(folder / "autzen-thin-srs.las", out / "autzen-thin-srs.las")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    # default: a folder `shared/data` beside the repository, laid out as the README lists
    parser.add_argument("--source", type=Path,
                        default=Path(__file__).resolve().parents[3] / "shared" / "data")
    parser.add_argument("--out", type=Path, default=HERE)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for build in (muscatatuck, longyearbyen, autzen):
        build(args.source, args.out)
    for path in sorted(args.out.glob("*")):
        if path.suffix in (".tif", ".las"):
            print(f"{path.name:28s} {path.stat().st_size / 1e3:8.1f} kB")


if __name__ == "__main__":
    main()
