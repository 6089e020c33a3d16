"""The tile archive: headers indexed once and cached, tiles and points read only where needed,
COPC tiles by spatial query."""

from __future__ import annotations

import json
import os
from pathlib import Path

import laspy
import numpy as np
import pytest
from archive_tiles import ORIGIN, write_tiles

from tiereg import archive
from tiereg.archive import TileIndex, surface_mask
from tiereg.errors import InputError

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def tiles(tmp_path_factory) -> list[Path]:
    return write_tiles(tmp_path_factory.mktemp("archive"), density=0.02)


def _all_points(paths, *, surface: bool) -> np.ndarray:
    parts = []
    for p in paths:
        las = laspy.read(p)
        keep = surface_mask(las.points, False) if surface else np.ones(len(las.points), bool)
        parts.append(np.column_stack([las.x, las.y, las.z])[keep])
    return np.concatenate(parts)


def _sorted(xyz: np.ndarray) -> np.ndarray:
    return xyz[np.lexsort(xyz.T[::-1])]


def test_index_reads_headers_once_and_again_only_for_changed_tiles(tiles, tmp_path,
                                                                   monkeypatch):
    cache = tmp_path / "tile-index.json"
    index = TileIndex.build(tiles, cache=cache)
    assert len(index.tiles) == 6
    assert index.count == sum(laspy.open(p).header.point_count for p in tiles)
    assert json.loads(cache.read_text())["tiles"][0]["path"] == str(tiles[0])
    read = []
    real = archive._read_tile
    monkeypatch.setattr(archive, "_read_tile", lambda p: read.append(p) or real(p))
    again = TileIndex.build(tiles, cache=cache)
    assert read == [] and again.tiles == index.tiles
    st = tiles[2].stat()
    os.utime(tiles[2], ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    TileIndex.build(tiles, cache=cache)
    assert read == [tiles[2]]


def test_tiles_near_are_those_whose_bounds_meet_the_box(tiles):
    index = TileIndex.build(tiles)
    x, y = ORIGIN
    # the middle column's tiles (x from -250 to 250), lower row only (y from -500 to 0)
    box = (x - 100, y - 400, x + 100, y - 50)
    assert [Path(t.path).name for t in index.tiles_near(box)] == ["tile_0_1.laz"]
    assert len(index.tiles_near(box, margin=200)) == 6
    assert index.tiles_near((x + 5000, y, x + 6000, y + 10)) == []


def test_points_in_reads_only_the_tiles_that_meet_the_box(tiles, monkeypatch):
    index = TileIndex.build(tiles)
    x, y = ORIGIN
    box = (x - 300, y - 120, x - 200, y + 80)  # across the corner of four tiles
    opened = []
    real = archive.tile_chunks
    monkeypatch.setattr(archive, "tile_chunks",
                        lambda t, **kw: opened.append(Path(t.path).name) or real(t, **kw))
    got = index.points_in(box)
    assert sorted(opened) == ["tile_0_0.laz", "tile_0_1.laz", "tile_1_0.laz", "tile_1_1.laz"]
    every = _all_points(tiles, surface=True)
    inside = ((every[:, 0] >= box[0]) & (every[:, 0] <= box[2]) & (every[:, 1] >= box[1])
              & (every[:, 1] <= box[3]))
    assert len(got) > 100
    np.testing.assert_array_equal(_sorted(got), _sorted(every[inside]))
    assert got[:, 2].max() < 250  # the noise class (300 m up) is left out


def test_window_source_is_a_las_source_over_the_window(tiles):
    index = TileIndex.build(tiles)
    x, y = ORIGIN
    box = (x - 600, y - 400, x - 300, y - 100)  # inside the lower-left tile only
    src = index.source(box)
    assert [p.name for p in src.paths] == ["tile_0_0.laz"]
    assert src.info.count == pytest.approx(index.tiles[0].count * 0.36, rel=0.01)
    pts = np.concatenate(list(src.chunks()))
    assert pts[:, 0].min() >= box[0] and pts[:, 0].max() <= box[2]


def test_copc_tiles_are_read_by_spatial_query():
    path = DATA / "simple.copc.laz"
    index = TileIndex.build([path])
    assert index.tiles[0].copc
    las = laspy.read(path)
    every = np.column_stack([las.x, las.y, las.z])
    (x0, y0, _), (x1, y1, _) = index.bounds
    box = (x0, y0, (x0 + x1) / 2, (y0 + y1) / 2)
    got = index.points_in(box, surface=False)
    inside = ((every[:, 0] >= box[0]) & (every[:, 0] <= box[2]) & (every[:, 1] >= box[1])
              & (every[:, 1] <= box[3]))
    assert 0 < len(got) < len(every)
    np.testing.assert_allclose(_sorted(got), _sorted(every[inside]), atol=1e-9)
    coarse = index.points_in((x0, y0, x1, y1), surface=False, resolution=50.0)
    assert 0 < len(coarse) < len(every)  # the octree's coarse levels only


def _cell_means(xyz: np.ndarray, ref) -> tuple[np.ndarray, np.ndarray]:
    """Counts and mean heights of ``xyz`` (file coordinates) in ``ref``'s base cells, the slow
    obvious way: a dictionary of cells."""
    spec, o = ref.base.spec, ref.origin
    cells: dict[tuple[int, int], list[float]] = {}
    for x, y, z in xyz - o:
        row, col = spec.cell_coordinates(x, y)
        cells.setdefault((int(np.floor(row)), int(np.floor(col))), []).append(z)
    count, mean = np.zeros(spec.shape, np.int64), np.full(spec.shape, np.nan)
    for (r, c), zs in cells.items():
        count[r, c], mean[r, c] = len(zs), np.mean(zs)
    return count, mean


@pytest.mark.parametrize("base_cell, levels", [(100.0, False), (800.0, True)])
def test_copc_tiles_grid_a_coarse_base_from_their_octree_levels(base_cell, levels):
    from tiereg.distributed import COPC_POINTS_PER_CELL_SIDE, prepare_archive_reference

    path = DATA / "simple.copc.laz"
    index = TileIndex.build([path])
    ref = prepare_archive_reference(index, base_cell=base_cell)
    resolution = ref.base.spec.cell_size / COPC_POINTS_PER_CELL_SIDE
    assert (resolution > index.tiles[0].spacing) == levels  # 121 m between points
    with laspy.CopcReader.open(path) as reader:
        records = reader.query(resolution=resolution) if levels else reader.query()
    keep = surface_mask(records, ref.first_returns_only)
    xyz = np.column_stack([records.x, records.y, records.z])[keep]
    count, mean = _cell_means(xyz, ref)
    np.testing.assert_array_equal(ref.base.count, count)
    np.testing.assert_allclose(ref.base["mean"], mean, rtol=0, atol=1e-9, equal_nan=True)
    every = len(laspy.read(path).points)
    # at 800 m cells the root level alone (18 surface points of 1,065), at 100 m every point
    assert (count.sum() < every / 10) if levels else (count.sum() >= every / 2)


def test_no_tiles_and_mixed_crs_are_one_line_errors(tiles, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no point files"):
        TileIndex.build(empty)
    import pyproj

    other = tmp_path / "other.laz"
    las = laspy.read(tiles[0])
    las.header.add_crs(pyproj.CRS.from_epsg(32633))
    las.write(str(other))
    first = tmp_path / "first.laz"
    las = laspy.read(tiles[1])
    las.header.add_crs(pyproj.CRS.from_epsg(32632))
    las.write(str(first))
    with pytest.raises(InputError, match="reproject the tiles to one CRS"):
        TileIndex.build([first, other])
