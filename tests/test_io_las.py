"""LAS/LAZ: versions and point formats, chunked reading, tiles, round trips, corrupt files."""

from __future__ import annotations

import shutil

import laspy
import numpy as np
import pytest

from tiereg import FormatError, InputError, Transform
from tiereg.io import open_points, read_points, write_points
from tiereg.io.las import LasSource, transform_las


def make_las(path, xyz, *, version="1.4", point_format=6, scale=0.001, compress=None, **dims):
    header = laspy.LasHeader(version=version, point_format=point_format)
    header.scales = np.array([scale] * 3)
    header.offsets = np.floor(xyz.min(axis=0)) if len(xyz) else np.zeros(3)
    data = laspy.LasData(header)
    data.x, data.y, data.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    for k, v in dims.items():
        setattr(data, k, v)
    data.write(str(path))
    return path


@pytest.fixture
def utm_points(rng):
    return np.column_stack([500_000 + rng.uniform(0, 1000, 5000),
                            5_000_000 + rng.uniform(0, 1000, 5000), rng.uniform(100, 200, 5000)])


def test_real_las14_with_crs(bmx_las):
    src = open_points(bmx_las)
    assert src.info.format == "las" and src.info.count == 829
    assert src.info.details["version"] == "1.4" and src.info.details["point_format"] == 7
    assert "Oregon" in src.info.crs_wkt
    pts = src.read().xyz
    lo, hi = src.info.bounds
    assert np.allclose(pts.min(axis=0), lo, atol=1e-6) and np.allclose(pts.max(axis=0), hi, atol=1e-6)


def test_chunked_reading_equals_whole(autzen_laz):
    src = open_points(autzen_laz)
    chunks = list(src.chunks(chunk_size=7000))
    assert len(chunks) == 16 and max(len(c) for c in chunks) <= 7000
    whole = laspy.read(autzen_laz)
    assert np.array_equal(np.vstack(chunks), np.column_stack([whole.x, whole.y, whole.z]))


@pytest.mark.parametrize("version, point_format", [
    ("1.1", 0), ("1.1", 1), ("1.2", 2), ("1.2", 3), ("1.3", 1), ("1.4", 0), ("1.4", 3),
    ("1.4", 6), ("1.4", 7), ("1.4", 8), ("1.4", 10),
])
def test_versions_and_point_formats(tmp_path, utm_points, version, point_format):
    path = make_las(tmp_path / "a.las", utm_points, version=version, point_format=point_format)
    got = read_points(path).xyz
    # coordinates survive to the file's resolution (scale 0.001)
    assert np.abs(got - utm_points).max() <= 0.0005 + 1e-9


def test_las_1_0_reads_and_writes_as_1_1(tmp_path, utm_points):
    path = make_las(tmp_path / "v11.las", utm_points, version="1.1", point_format=1)
    raw = bytearray(path.read_bytes())
    raw[25] = 0  # version minor: LAS 1.0
    v10 = tmp_path / "v10.las"
    v10.write_bytes(bytes(raw))
    src = open_points(v10)
    assert src.info.details["version"] == "1.0"
    out = tmp_path / "out.las"
    write_points(out, src.read().xyz, like=src)
    assert laspy.read(out).header.version == "1.1"
    assert np.abs(read_points(out).xyz - utm_points).max() <= 0.0005 + 1e-9


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_round_trip_keeps_scale_offset_crs(tmp_path, bmx_las, suffix):
    src = open_points(bmx_las)
    out = tmp_path / f"copy{suffix}"
    write_points(out, src.read().xyz, like=src)
    back = open_points(out)
    assert np.array_equal(back.read().xyz, src.read().xyz)  # exact: same scale and offset
    assert back.info.details["scales"] == src.info.details["scales"]
    assert back.info.details["offsets"] == src.info.details["offsets"]
    assert back.info.crs_wkt == src.info.crs_wkt
    assert back.info.details["compressed"] == (suffix == ".laz")


def test_offsets_move_only_when_coordinates_would_overflow(tmp_path, bmx_las):
    src = open_points(bmx_las)
    far = src.read().xyz + [3e7, 0, 0]  # beyond int32 at scale 0.001 from the old offset
    out = tmp_path / "far.las"
    write_points(out, far, like=src)
    back = open_points(out)
    assert back.info.details["scales"] == src.info.details["scales"]
    assert np.abs(back.read().xyz - far).max() <= 0.0005 + 1e-9


def test_tiles_directory_and_glob_form_one_source(tmp_path, utm_points):
    tiles = tmp_path / "tiles"
    tiles.mkdir()
    for i, part in enumerate(np.array_split(utm_points, 3)):
        make_las(tiles / f"t{i}.laz", part)
    (tiles / "readme.txt").write_text("not a tile")
    for spec in (tiles, str(tiles / "*.laz"), sorted(tiles.glob("*.laz"))):
        src = open_points(spec)
        assert isinstance(src, LasSource) and src.info.count == len(utm_points)
        assert np.abs(src.read().xyz - utm_points).max() <= 0.0005 + 1e-9


def test_transform_las_streams_and_keeps_attributes(tmp_path, utm_points, rng):
    n = len(utm_points)
    path = make_las(tmp_path / "in.laz", utm_points, intensity=rng.integers(0, 5000, n),
                    classification=rng.integers(1, 7, n), gps_time=np.arange(n) * 0.1)
    T = Transform.from_parameters(kappa=0.2, translation=(10.5, -3.25, 2.0))
    out = tmp_path / "out.laz"
    transform_las(open_points(path), out, T.apply, chunk_size=1000)
    a, b = laspy.read(path), laspy.read(out)
    for dim in ("intensity", "classification", "gps_time", "return_number"):
        assert np.array_equal(np.asarray(a[dim]), np.asarray(b[dim]))
    expected = T.apply(np.column_stack([a.x, a.y, a.z]))
    assert np.abs(np.column_stack([b.x, b.y, b.z]) - expected).max() <= 0.0005 + 1e-9


def test_truncated_las(tmp_path, bmx_las):
    bad = tmp_path / "cut.las"
    bad.write_bytes(bmx_las.read_bytes()[:20000])
    with pytest.raises(FormatError, match="cut.las.*truncated"):
        open_points(bad)


def test_truncated_laz_fails_while_reading(tmp_path, autzen_laz):
    bad = tmp_path / "cut.laz"
    bad.write_bytes(autzen_laz.read_bytes()[:300_000])
    with pytest.raises(FormatError, match="cut.laz"):
        read_points(bad)


def test_garbage_with_las_suffix(tmp_path):
    bad = tmp_path / "noise.las"
    bad.write_bytes(b"\x00garbage" * 100)
    with pytest.raises(FormatError, match="noise.las.*LASF"):
        open_points(bad)


def test_header_only_file_is_empty(tmp_path):
    path = make_las(tmp_path / "empty.las", np.zeros((0, 3)))
    src = open_points(path)
    assert src.info.count == 0 and len(src.read()) == 0


def test_empty_directory(tmp_path):
    with pytest.raises(InputError, match="no point files"):
        open_points(tmp_path)


def test_reading_never_modifies_the_input(tmp_path, bmx_las):
    copy = tmp_path / "in.las"
    shutil.copy(bmx_las, copy)
    before = (copy.read_bytes(), copy.stat().st_mtime_ns)
    read_points(copy)
    assert (copy.read_bytes(), copy.stat().st_mtime_ns) == before
