"""GeoTIFF DSM/DEM through rasterio: read as a reference surface, write grids.

A raster reads as a point source of its valid cell centres, window by window, so the same
gridding code serves lidar and DSMs and memory stays bounded. Nodata cells are skipped.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import tempfile
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import FormatError, InputError
from .base import (
    DEFAULT_CHUNK,
    PointSource,
    SourceInfo,
    atomic_output,
    check_input_file,
    note_input,
)

if TYPE_CHECKING:
    from ..grid import GridSpec


log = logging.getLogger(__name__)
MAX_CELLS = 2_000_000_000  # a 45 km square at 1 m; every cell is read once on opening
MAX_SIDE = 1_000_000  # a row is read whole
SCAN_CELLS = 1 << 18  # cells read at a time to count the valid ones


def _rasterio():
    import rasterio

    return rasterio


class RasterSource(PointSource):
    """The valid cells of a single-band GeoTIFF as points ``(x_centre, y_centre, value)``."""

    def __init__(self, path: str | os.PathLike[str]):
        rasterio = _rasterio()
        self.path = Path(path)
        check_input_file(self.path)
        note_input(self.path)
        try:
            with warnings.catch_warnings():  # said below, in one line, as an error
                warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
                with rasterio.open(self.path) as ds:
                    self.transform = ds.transform
                    self.shape = (ds.height, ds.width)
                    self.nodata = ds.nodata
                    crs = ds.crs.to_wkt() if ds.crs else None
                    bounds = ds.bounds
                    self.block_rows = max(1, DEFAULT_CHUNK // max(ds.width, 1))
                    bands, dtype = ds.count, ds.dtypes[0]
        except rasterio.errors.RasterioIOError as exc:
            raise FormatError(
                f"{self.path}: not a readable GeoTIFF ({str(exc).splitlines()[0][:160]}); "
                "check the file"
            ) from None
        rows, cols = self.shape
        if rows * cols > MAX_CELLS or cols > MAX_SIDE:
            raise InputError(
                f"{self.path}: the raster has {rows:,} x {cols:,} cells, more than tiereg reads "
                f"as a surface ({MAX_CELLS:,} cells, {MAX_SIDE:,} a row); crop it or coarsen "
                "it (gdalwarp -te / -tr) first")
        if bands != 1:  # an orthophoto (RGB, RGBA): no heights
            raise InputError(
                f"{self.path}: a raster of {bands} bands ({dtype}) is not a surface of heights; "
                "give a single-band DSM/DEM")
        if crs is None and self.transform.is_identity:
            raise InputError(
                f"{self.path}: the raster has no georeference (no CRS, no geotransform), so its "
                "cells have no place on the ground; export it as a GeoTIFF with both")
        if abs(self.transform.b) > 0 or abs(self.transform.d) > 0:
            raise InputError(
                f"{self.path}: rotated rasters are not supported; warp it north-up first "
                "(gdalwarp)"
            )
        count, (lo_z, hi_z) = self._scan()
        if count == 0:
            raise InputError(
                f"{self.path}: the raster has no valid cells (all nodata or NaN); "
                "give a DSM/DEM with data"
            )
        self.info = SourceInfo(
            path=str(self.path),
            format="geotiff",
            count=count,
            bounds=(
                (min(bounds.left, bounds.right), min(bounds.bottom, bounds.top), lo_z),
                (max(bounds.left, bounds.right), max(bounds.bottom, bounds.top), hi_z),
            ),
            crs_wkt=crs,
            details={
                "width": self.shape[1],
                "height": self.shape[0],
                "cell_size": [abs(self.transform.a), abs(self.transform.e)],
                "nodata": self.nodata,
                "bounds_xy": [bounds.left, bounds.bottom, bounds.right, bounds.top],
            },
        )

    def _windows(self, block_rows: int | None = None) -> Iterator[tuple[int, np.ndarray]]:
        rasterio = _rasterio()
        from rasterio.windows import Window

        with rasterio.open(self.path) as ds:
            step = block_rows or self.block_rows
            for row0 in range(0, self.shape[0], step):
                h = min(step, self.shape[0] - row0)
                try:
                    band = ds.read(1, window=Window(0, row0, self.shape[1], h), masked=True)
                except rasterio.errors.RasterioIOError as exc:
                    raise FormatError(
                        f"{self.path}: reading the raster failed ({str(exc)[:120]}); the file is "
                        "corrupt or truncated"
                    ) from None
                values = np.ma.filled(band.astype(np.float64), np.nan)
                yield row0, values

    def _scan(self) -> tuple[int, tuple[float, float]]:
        """Count the valid cells and find their value range (one pass over the raster)."""
        n = 0
        lo, hi = np.inf, -np.inf
        # small windows: opening (tiereg info) stays light whatever the raster's size
        for _, v in self._windows(max(1, SCAN_CELLS // max(self.shape[1], 1))):
            ok = np.isfinite(v)
            n += int(ok.sum())
            if ok.any():
                lo, hi = min(lo, float(v[ok].min())), max(hi, float(v[ok].max()))
        return n, (lo, hi)

    def chunks(self, chunk_size: int = DEFAULT_CHUNK) -> Iterator[np.ndarray]:
        t = self.transform
        for row0, values in self._windows():
            rows, cols = np.nonzero(np.isfinite(values))
            x = t.c + (cols + 0.5) * t.a
            y = t.f + (rows + row0 + 0.5) * t.e
            yield np.column_stack([x, y, values[rows, cols]])


def write_geotiff(
    path: str | os.PathLike[str],
    values: np.ndarray,
    spec: GridSpec,
    *,
    crs_wkt: str | None = None,
    nodata: float = -9999.0,
) -> None:
    """Write a (rows, cols) grid, NaN = no data, as a float32 (float64 if needed) GeoTIFF."""
    rasterio = _rasterio()
    from affine import Affine

    values = np.asarray(values, dtype=np.float64)
    if values.shape != spec.shape:
        raise InputError(f"grid values have shape {values.shape}, the grid spec {spec.shape}")
    out = np.where(np.isfinite(values), values, nodata)
    finite = values[np.isfinite(values)]
    # float32 keeps ~7 digits: enough for heights below 10 km at mm level; otherwise float64
    dtype = "float32" if finite.size == 0 or np.abs(finite).max() < 1e4 else "float64"
    profile = {
        "driver": "GTiff",
        "height": spec.shape[0],
        "width": spec.shape[1],
        "count": 1,
        "dtype": dtype,
        "nodata": nodata,
        "transform": Affine(spec.cell_size, 0.0, spec.x0, 0.0, -spec.cell_size, spec.y0),
        "compress": "deflate",
    }
    if crs_wkt:
        profile["crs"] = crs_wkt
    with atomic_output(path) as tmp, _c_stderr_to_log(), rasterio.open(tmp, "w", **profile) as ds:
        ds.write(out.astype(dtype), 1)


@contextlib.contextmanager
def _c_stderr_to_log() -> Iterator[None]:
    """GDAL's libtiff prints I/O errors (a full disk) straight to the process's stderr, past
    Python: they are logged at debug level instead (the error itself arrives as an exception)."""
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, ValueError, OSError):  # no real stderr (captured)
        yield
        return
    sys.stderr.flush()
    with tempfile.TemporaryFile() as spool:
        saved = os.dup(fd)
        os.dup2(spool.fileno(), fd)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, fd)
            os.close(saved)
            spool.seek(0)
            text = spool.read().decode("utf-8", errors="replace").strip()
            if text:
                log.debug("GDAL: %s", " | ".join(text.splitlines()))
