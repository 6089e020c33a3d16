"""Gridding a tile archive a tile a task on a Dask cluster gives the one-process grids: counts,
minima and maxima bit for bit, means to float rounding (bit for bit where no two tiles share a
cell), and the reference that register uses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
from archive_tiles import ORIGIN, write_tiles

from tiereg.archive import TileIndex
from tiereg.distributed import cluster, grid_archive, prepare_archive_reference
from tiereg.errors import InputError
from tiereg.files import grid_to_geotiff
from tiereg.io import open_points
from tiereg.reference import prepare_reference

pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def tiles(tmp_path_factory) -> list[Path]:
    return write_tiles(tmp_path_factory.mktemp("tiles"), density=0.05)


@pytest.fixture(scope="module")
def client():
    # two workers as threads of this process: the cluster's code path (scheduling, moving the
    # tasks' arguments and results) at a test's cost
    with cluster(workers=2, processes=False) as c:
        yield c


def _read(path: Path) -> tuple[np.ndarray, tuple]:
    with rasterio.open(path) as ds:
        return ds.read(1, masked=False).astype(np.float64), tuple(ds.transform)


@pytest.mark.parametrize("cell", [7.0, 10.0])  # 7 m cells straddle the tile edges
@pytest.mark.parametrize("stat", ["count", "min", "max", "mean"])
def test_grid_on_the_cluster_is_the_one_process_grid(tiles, client, tmp_path, cell, stat):
    one, many = tmp_path / "one.tif", tmp_path / "many.tif"
    grid_to_geotiff(tiles, one, cell_size=cell, stat=stat)
    grid_archive(tiles, many, cell_size=cell, stat=stat, client=client)
    a, ta = _read(one)
    b, tb = _read(many)
    assert ta == tb and a.shape == b.shape
    if stat == "mean" and cell == 7.0:
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=0)
        assert np.array_equal(np.isnan(a), np.isnan(b))
    else:
        np.testing.assert_array_equal(b, a)


def test_median_on_the_cluster_is_exact_where_one_process_is(tiles, client, tmp_path):
    one, many = tmp_path / "one.tif", tmp_path / "many.tif"
    grid_to_geotiff(tiles, one, cell_size=10.0, stat="median")
    grid_archive(tiles, many, cell_size=10.0, stat="median", client=client)
    count = tmp_path / "count.tif"
    grid_to_geotiff(tiles, count, cell_size=10.0, stat="count")
    n, _ = _read(count)
    (a, t), b = _read(one), _read(many)[0]
    x = t[2] + (np.arange(a.shape[1]) + 0.5) * t[0] - ORIGIN[0]
    y = t[5] + (np.arange(a.shape[0]) + 0.5) * t[4] - ORIGIN[1]
    edge = (np.abs((x + 250) % 500 - 250) > 250 - 10)[None, :] | (
        np.abs(y % 500 - 250) > 250 - 10)[:, None]  # cells a tile edge may share
    small = (n > 0) & (n <= 7) & ~edge  # the sketch keeps every point of these cells
    assert small.sum() > 100
    np.testing.assert_array_equal(b[small], a[small])
    assert np.nanmax(np.abs(b - a)) < 30  # elsewhere both are a sample's median of a cell


def test_reference_on_the_cluster_is_prepare_reference(tiles, client):
    one = prepare_reference(open_points(tiles), base_cell=7.0)
    many = prepare_archive_reference(TileIndex.build(tiles), base_cell=7.0, client=client)
    here = prepare_archive_reference(TileIndex.build(tiles), base_cell=7.0)  # no cluster
    for ref in (many, here):
        assert ref.base.spec == one.base.spec
        np.testing.assert_array_equal(ref.origin, one.origin)
        np.testing.assert_array_equal(ref.base.count, one.base.count)
        np.testing.assert_allclose(ref.base["mean"], one.base["mean"], rtol=1e-12)
        assert ref.first_returns_only and one.first_returns_only
    # noise (300 m up) and the last returns (3 m down) are left out as prepare_reference does
    assert np.nanmax(many.base["mean"]) < 250 + 0 * many.origin[2]


def test_tiles_without_returns_are_gridded_as_prepare_reference_grids_them(tmp_path, client):
    tiles = write_tiles(tmp_path / "t", tiles=(2, 1), density=0.02, returns=False)
    ref = prepare_archive_reference(TileIndex.build(tiles), base_cell=10.0, client=client)
    one = prepare_reference(open_points(tiles), base_cell=10.0)
    assert ref.first_returns_only == one.first_returns_only
    np.testing.assert_array_equal(ref.base.count, one.base.count)


def test_workers_and_scheduler_together_are_refused():
    with pytest.raises(InputError, match="not both"), cluster(workers=2, scheduler="tcp://x:1"):
        pass


def test_a_tile_whose_header_understates_its_bounds_is_refused(tiles):
    """A tile's task grids only its header's window: points beyond it (a wrong header) would
    be lost silently, so the task refuses the tile, naming it."""
    from dataclasses import replace

    from tiereg.distributed import grid_tile
    from tiereg.grid import GridSpec

    tile = TileIndex.build(tiles).tiles[0]
    spec = GridSpec(ORIGIN[0] - 1000.0, ORIGIN[1] + 1000.0, 10.0, (200, 200))  # all tiles
    whole = grid_tile(tile, spec, stats=("mean",), origin=None, surface=True, first_only=True,
                      median_sample=15, seed=0)
    assert whole.points > 0
    shrunk = replace(tile, maxs=(tile.mins[0] + 100.0, *tile.maxs[1:]))  # 100 m of 500
    with pytest.raises(InputError, match="outside the tile's header bounds"):
        grid_tile(shrunk, spec, stats=("mean",), origin=None, surface=True, first_only=True,
                  median_sample=15, seed=0)


def _environ(name: str) -> str | None:
    import os

    return os.environ.get(name)


def test_local_workers_keep_glibc_malloc_tuning_and_the_rest_of_dasks_environment():
    # Dask starts worker processes with MALLOC_TRIM_THRESHOLD_, which turns off glibc's dynamic
    # mmap threshold: the tile tasks' arrays were then mapped afresh each time (15 % more CPU)
    import dask

    before = dask.config.get("distributed.nanny.pre-spawn-environ")  # Dask's default sets it
    with cluster(workers=1) as c:
        assert list(c.run(_environ, "MALLOC_TRIM_THRESHOLD_").values()) == [None]
        assert list(c.run(_environ, "OMP_NUM_THREADS").values()) == ["1"]
    assert dask.config.get("distributed.nanny.pre-spawn-environ") == before
