"""GeoTIFF DSM/DEM: nodata honoured, cell centres as points, write/read round trip."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from affine import Affine

from tiereg import FormatError, InputError
from tiereg.grid import GridSpec
from tiereg.io import open_points
from tiereg.io.raster import RasterSource, write_geotiff


def make_tif(path, values, *, x0=627000.0, y0=4323900.0, cell=2.0, nodata=-9999.0):
    with rasterio.open(path, "w", driver="GTiff", height=values.shape[0], width=values.shape[1],
                       count=1, dtype="float64", nodata=nodata, crs="EPSG:32616",
                       transform=Affine(cell, 0.0, x0, 0.0, -cell, y0)) as ds:
        ds.write(values, 1)
    return path


def test_nodata_and_cell_centres(tmp_path):
    values = np.arange(12, dtype=np.float64).reshape(3, 4) + 200.0
    values[1, 2] = -9999.0
    values[2, 0] = np.nan
    src = open_points(make_tif(tmp_path / "dsm.tif", values))
    assert isinstance(src, RasterSource) and src.info.count == 10
    pts = src.read().xyz
    assert len(pts) == 10
    # cell (row 0, col 1) centre: x0 + 1.5 cell, y0 - 0.5 cell
    hit = pts[(pts[:, 0] == 627003.0) & (pts[:, 1] == 4323899.0)]
    assert hit.tolist() == [[627003.0, 4323899.0, 201.0]]
    assert not np.any(pts[:, 2] == -9999.0)
    assert "UTM zone 16N" in src.info.crs_wkt


def test_all_nodata_raster(tmp_path):
    path = make_tif(tmp_path / "void.tif", np.full((5, 5), -9999.0))
    with pytest.raises(InputError, match="void.tif.*no valid cells"):
        open_points(path)


def test_rasters_that_are_no_surface_of_heights_are_refused(tmp_path, recwarn):
    rgb = tmp_path / "ortho.tif"  # an orthophoto given by mistake
    with rasterio.open(rgb, "w", driver="GTiff", height=4, width=4, count=3, dtype="uint8",
                       crs="EPSG:32616", transform=Affine(2.0, 0, 627000.0, 0, -2.0, 4323900.0)
                       ) as ds:
        ds.write(np.full((3, 4, 4), 128, np.uint8))
    with pytest.raises(InputError, match="ortho.tif.*3 bands.*single-band DSM"):
        open_points(rgb)
    plain = tmp_path / "plain.tif"  # no CRS and no geotransform: pixel coordinates
    with rasterio.open(plain, "w", driver="GTiff", height=4, width=4, count=1,
                       dtype="float32") as ds:
        ds.write(np.full((4, 4), 200.0, np.float32), 1)
    with pytest.raises(InputError, match="plain.tif.*no georeference"):
        open_points(plain)
    assert not [w for w in recwarn if "georeferenced" in str(w.message).lower()]


def test_corrupt_tif(tmp_path):
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"II*\x00" + b"\x00" * 50)
    with pytest.raises(FormatError, match="bad.tif"):
        open_points(bad)


def test_write_geotiff_round_trip(tmp_path):
    spec = GridSpec(x0=500000.0, y0=5000000.0, cell_size=5.0, shape=(4, 6))
    values = np.random.default_rng(0).uniform(100, 300, spec.shape)
    values[0, 0] = np.nan
    out = tmp_path / "g.tif"
    write_geotiff(out, values, spec, crs_wkt=rasterio.crs.CRS.from_epsg(32633).to_wkt())
    with rasterio.open(out) as ds:
        back = ds.read(1, masked=True)
        assert ds.transform == Affine(5.0, 0.0, 500000.0, 0.0, -5.0, 5000000.0)
        assert ds.crs.to_epsg() == 32633
    assert back.mask[0, 0] and not back.mask[1:, 1:].any()
    assert np.allclose(back.filled(np.nan)[1:], values[1:], atol=1e-4)  # float32 storage
