"""Readers and writers of the ASCII, PLY, COLMAP and Bundler point formats."""

from __future__ import annotations

import contextlib
import math
import struct
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tiereg.errors import FormatError, InputError
from tiereg.io import detect_format, read_points, write_points
from tiereg.io.bundler import read_bundler, read_bundler_model, write_bundler
from tiereg.io.colmap import (
    read_colmap,
    read_colmap_model,
    write_colmap_model_bin,
    write_colmap_model_txt,
    write_colmap_points_bin,
    write_colmap_points_txt,
)
from tiereg.io.ply import read_ply, write_ply
from tiereg.io.text import read_xyz, write_xyz

OFFSET = np.array([500_000.0, 5_000_000.0, 300.0])


@pytest.fixture
def xyz() -> np.ndarray:
    """Projected coordinates with millimetre digits (the hard case for text formats)."""
    rng = np.random.default_rng(42)
    return np.round(OFFSET + rng.uniform(-1000, 1000, size=(500, 3)), 3)


@contextlib.contextmanager
def unchanged(path: Path) -> Iterator[None]:
    """Assert that reading leaves the file (or every file in the folder) byte- and mtime-equal."""
    files = sorted(path.iterdir()) if path.is_dir() else [path]

    def snap() -> list[tuple[str, bytes, int]]:
        return [(f.name, f.read_bytes(), f.stat().st_mtime_ns) for f in files]

    before = snap()
    yield
    assert snap() == before
    if path.is_dir():
        assert sorted(path.iterdir()) == files


# Every writer uses float64 binary or the shortest decimal that reads back to the same float64
# (Python's repr), so all round trips below are exact, bit for bit.
ROUND_TRIPS = {
    "xyz": ("pts.xyz", write_xyz, read_xyz),
    "csv": ("pts.csv", write_xyz, read_xyz),
    "ply-binary": ("pts.ply", write_ply, read_ply),
    "ply-ascii": ("pts.ply", lambda p, a: write_ply(p, a, binary=False), read_ply),
    "colmap-txt": ("points3D.txt", write_colmap_points_txt, read_colmap),
    "colmap-bin": ("points3D.bin", write_colmap_points_bin, read_colmap),
    "bundler": ("bundle.out", write_bundler, read_bundler),
}


@pytest.mark.parametrize("kind", sorted(ROUND_TRIPS))
def test_round_trip_is_exact(tmp_path: Path, xyz: np.ndarray, kind: str) -> None:
    name, write, read = ROUND_TRIPS[kind]
    path = tmp_path / name
    write(path, xyz)
    with unchanged(path):
        points = read(path)
    assert points.xyz.dtype == np.float64
    assert np.array_equal(points.xyz, xyz)
    assert points.source == str(path)
    assert list(tmp_path.iterdir()) == [path]  # atomic writing leaves no temporary behind


@pytest.mark.parametrize("kind", sorted(ROUND_TRIPS))
def test_round_trip_without_points(tmp_path: Path, kind: str) -> None:
    name, write, read = ROUND_TRIPS[kind]
    write(tmp_path / name, np.empty((0, 3)))
    assert read(tmp_path / name).xyz.shape == (0, 3)


@pytest.mark.parametrize("kind", sorted(ROUND_TRIPS))
def test_round_trip_through_registry(tmp_path: Path, xyz: np.ndarray, kind: str) -> None:
    name, write, _ = ROUND_TRIPS[kind]
    path = tmp_path / name
    write(path, xyz)
    assert np.array_equal(read_points(path).xyz, xyz)


@pytest.mark.parametrize("name", ["out.xyz", "out.txt", "out.csv", "out.ply"])
def test_write_points_by_suffix(tmp_path: Path, xyz: np.ndarray, name: str) -> None:
    write_points(tmp_path / name, xyz)
    assert np.array_equal(read_points(tmp_path / name).xyz, xyz)


def test_csv_written_with_commas(tmp_path: Path) -> None:
    write_xyz(tmp_path / "a.csv", np.array([[500000.125, 5000000.5, 300.25]]))
    assert (tmp_path / "a.csv").read_text() == "500000.125,5000000.5,300.25\n"


@pytest.mark.parametrize("writer", [write_xyz, write_ply, write_colmap_points_txt, write_bundler])
def test_writers_reject_bad_shapes(tmp_path: Path, writer: Callable[..., None]) -> None:
    with pytest.raises(InputError, match="x, y, z"):
        writer(tmp_path / "bad.out", np.zeros((4, 2)))
    assert list(tmp_path.iterdir()) == []


# --- ASCII variants ---------------------------------------------------------------------------

TEXT_VARIANTS = {
    "csv-header": "X,Y,Z,intensity\n1.5,2.5,3.5,10\n4,5,6,11\n",
    "whitespace-extra": "1.5  2.5\t3.5 200 17 0.5\n   4 5 6 201\n",
    "semicolons": "1.5;2.5;3.5;x\n4;5;6;y\n",
    "comments": "# exported\n// by hand\n\n1.5 2.5 3.5 # first\n\n# more\n4 5 6\n",
    "named-order": "id,easting,northing,height\n7,1.5,2.5,3.5\n8,4,5,6\n",
    "reversed-names": "Z Y X\n3.5 2.5 1.5\n6 5 4\n",
    "units": "X [m];Y [m];Z [m]\n1.5;2.5;3.5\n4;5;6\n",
    "cloudcompare": "//X,Y,Z,R,G,B\n1.5,2.5,3.5,0,0,0\n4,5,6,9,9,9\n",
    "leica-pts": "2\n1.5 2.5 3.5 -120 10 20 30\n4 5 6 -100 10 20 30\n",
    "crlf-bom": "\ufeffx y z\r\n1.5 2.5 3.5\r\n4 5 6\r\n",
    "text-column": "name x y z\npt1 1.5 2.5 3.5\npt2 4 5 6\n",
    "comment-mentions-axes": "# x and y in metres\n1.5 2.5 3.5\n4 5 6\n",
}


@pytest.mark.parametrize("kind", sorted(TEXT_VARIANTS))
def test_text_variants(tmp_path: Path, kind: str) -> None:
    path = tmp_path / "pts.txt"
    path.write_bytes(TEXT_VARIANTS[kind].encode("utf-8"))
    with unchanged(path):
        got = read_xyz(path).xyz
    assert np.array_equal(got, [[1.5, 2.5, 3.5], [4.0, 5.0, 6.0]])
    assert detect_format(path) == "xyz"


@pytest.mark.parametrize(
    ("text", "line", "found"),
    [
        ("1 2 3\n4 5 6\n\n# c\n7 8\n", 5, "found 2 value"),
        ("x,y,z\n1,2,3\n4,five,6\n", 3, "non-numeric"),
        ("1 2\n3 4\n", 1, "found 2 value"),
        ("1;2,5;3\n", 1, "decimal point"),
    ],
)
def test_text_errors_name_file_and_line(tmp_path: Path, text: str, line: int, found: str) -> None:
    path = tmp_path / "broken.xyz"
    path.write_text(text)
    with pytest.raises(FormatError, match=f"broken.xyz: line {line}: expected at least three") as e:
        read_xyz(path)
    assert found in str(e.value)
    assert "\n" not in str(e.value)


def test_text_header_naming_only_some_axes(tmp_path: Path) -> None:
    path = tmp_path / "partial.csv"
    path.write_text("id,x,y,value\n1,2,3,4\n")
    with pytest.raises(FormatError, match="partial.csv: the header names .* not z"):
        read_xyz(path)


def test_text_only_comments_gives_no_points(tmp_path: Path) -> None:
    path = tmp_path / "empty.xyz"
    path.write_text("# nothing here\n\n")
    assert read_xyz(path).xyz.shape == (0, 3)


# --- PLY ----------------------------------------------------------------------------------------

PLY_HEADER = """ply
format {fmt} 1.0
comment made by a scanner
element camera 1
property float view_x
property float view_y
element vertex {n}
property float x
property float y
property float z
property uchar red
property uchar green
property uchar blue
property float nx
property float ny
property float nz
element face 1
property list uchar int vertex_indices
end_header
"""


def _ply_vertices(n: int, endian: str) -> tuple[np.ndarray, np.ndarray]:
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4"), ("r", "u1"), ("g", "u1"), ("b", "u1"),
              ("nx", "f4"), ("ny", "f4"), ("nz", "f4")]
    dt = np.dtype([(name, endian + code) for name, code in fields])
    rng = np.random.default_rng(1)
    v = np.zeros(n, dtype=dt)
    for c in ("x", "y", "z"):
        v[c] = rng.uniform(-500, 500, n)
    v["r"], v["g"], v["b"], v["nz"] = 255, 7, 1, 1.0
    expected = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    return v, expected


@pytest.mark.parametrize(("fmt", "endian"), [("binary_big_endian", ">"),
                                             ("binary_little_endian", "<")])
def test_ply_float32_with_extra_properties_and_faces(tmp_path: Path, fmt: str, endian: str) -> None:
    v, expected = _ply_vertices(50, endian)
    camera = np.array([1.0, 2.0], dtype=endian + "f4").tobytes()
    face = bytes([3]) + np.array([0, 1, 2], dtype=endian + "i4").tobytes()
    path = tmp_path / "scan.ply"
    path.write_bytes(PLY_HEADER.format(fmt=fmt, n=50).encode() + camera + v.tobytes() + face)
    with unchanged(path):
        got = read_ply(path).xyz
    assert np.array_equal(got, expected)


def test_ply_ascii_with_extra_properties_and_faces(tmp_path: Path) -> None:
    body = "1 2\n1.5 2.5 3.5 255 0 0 0 0 1\n4 5 6 0 255 0 0 0 1\n3 0 1 1\n"
    path = tmp_path / "scan.ply"
    path.write_text(PLY_HEADER.format(fmt="ascii", n=2) + body)
    assert np.array_equal(read_ply(path).xyz, [[1.5, 2.5, 3.5], [4, 5, 6]])


def test_ply_integer_coordinates_crlf(tmp_path: Path) -> None:
    header = "ply\r\nformat binary_little_endian 1.0\r\nelement vertex 2\r\n" \
        "property int x\r\nproperty int y\r\nproperty short z\r\nend_header\r\n"
    dt = np.dtype([("x", "<i4"), ("y", "<i4"), ("z", "<i2")])
    v = np.array([(500000, 5000000, 300), (-1, 2, -3)], dtype=dt)
    path = tmp_path / "int.ply"
    path.write_bytes(header.encode() + v.tobytes())
    assert np.array_equal(read_ply(path).xyz, [[500000, 5000000, 300], [-1, 2, -3]])


def test_ply_truncated(tmp_path: Path, xyz: np.ndarray) -> None:
    path = tmp_path / "cut.ply"
    write_ply(path, xyz)
    path.write_bytes(path.read_bytes()[:-7])
    with pytest.raises(FormatError, match="cut.ply: the file is truncated"):
        read_ply(path)
    write_ply(path, xyz, binary=False)
    path.write_bytes(path.read_bytes()[:-200])
    with pytest.raises(FormatError, match="cut.ply: "):
        read_ply(path)


_LE = "ply\nformat binary_little_endian 1.0\n"
_DOUBLES = "element vertex 1\nproperty double x\nproperty double y\nproperty double z\n"


@pytest.mark.parametrize(
    ("header", "message"),
    [
        (_LE + "element vertex 1\nproperty float x\n", "end_header"),
        ("ply\nformat ascii 1.0\nelement vertex 1\nproperty double x\nend_header\n", "no y, z"),
        (_LE + "element face 1\nproperty list uchar int v\n" + _DOUBLES + "end_header\n",
         "list properties"),
        (_LE + "element vertex 1\nproperty quad x\nend_header\n", "header line"),
        (_LE + "element vertex -5\nproperty double x\nend_header\n", "header line"),
        ("ply\nformat binary_middle_endian 1.0\nend_header\n", "unknown PLY format"),
        (_LE + "property double x\nend_header\n", "header line"),
        (_LE + _DOUBLES.replace("vertex", "point") + "end_header\n", "no 'vertex' element"),
    ],
)
def test_ply_bad_headers(tmp_path: Path, header: str, message: str) -> None:
    path = tmp_path / "bad.ply"
    path.write_bytes(header.encode() + bytes(24))
    with pytest.raises(FormatError, match=f"bad.ply: .*{message}"):
        read_ply(path)


# --- COLMAP -------------------------------------------------------------------------------------


def _cameras(m: int) -> tuple[np.ndarray, np.ndarray]:
    rot = Rotation.random(m, random_state=3).as_matrix()
    centres = OFFSET + np.random.default_rng(3).uniform(-500, 500, (m, 3))
    return rot, centres


@pytest.mark.parametrize("writer", [write_colmap_model_txt, write_colmap_model_bin])
def test_colmap_model_cameras(
    tmp_path: Path, xyz: np.ndarray, writer: Callable[..., None]
) -> None:
    rot, centres = _cameras(6)
    names = [f"DSC_{i:04d} copy.JPG" for i in range(6)]
    writer(tmp_path / "sparse", xyz, centres, rot, names=names)
    with unchanged(tmp_path / "sparse"):
        model = read_colmap_model(tmp_path / "sparse")
    assert np.array_equal(model.points.xyz, xyz)
    assert model.image_names == tuple(names)
    np.testing.assert_allclose(model.camera_centres, centres, rtol=0, atol=1e-6)
    # the optical axis (camera +z) in the model frame is the third row of R
    np.testing.assert_allclose(model.viewing_directions, rot[:, 2, :], rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(model.viewing_directions, axis=1), 1.0)


def test_colmap_images_txt_known_answer(tmp_path: Path) -> None:
    """A hand-written model: 90 degrees about z maps camera +z to world +z, C = -R^T t."""
    write_colmap_points_txt(tmp_path / "points3D.txt", np.array([[1.0, 2.0, 3.0]]))
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    (tmp_path / "images.txt").write_text(
        "# Image list with two lines of data per image:\n"
        f"1 {c!r} 0 0 {s!r} 10 20 30 1 left.jpg\n"
        "100.5 200.5 1 300.5 400.5 -1\n"
        "2 1 0 0 0 -1 -2 -3 1 right.jpg\n"
        "\n"
    )
    model = read_colmap_model(tmp_path / "points3D.txt")
    # R = [[0,-1,0],[1,0,0],[0,0,1]]; C = -R^T t = -(20, -10, 30)
    np.testing.assert_allclose(model.camera_centres, [[-20, 10, -30], [1, 2, 3]], atol=1e-12)
    np.testing.assert_allclose(model.viewing_directions, [[0, 0, 1], [0, 0, 1]], atol=1e-12)
    assert model.image_names == ("left.jpg", "right.jpg")


def test_colmap_without_images(tmp_path: Path, xyz: np.ndarray) -> None:
    write_colmap_points_bin(tmp_path / "points3D.bin", xyz)
    model = read_colmap_model(tmp_path)
    assert np.array_equal(model.points.xyz, xyz)
    assert model.camera_centres.shape == (0, 3) and model.viewing_directions.shape == (0, 3)
    assert model.image_names == ()


def test_colmap_bin_with_tracks(tmp_path: Path, xyz: np.ndarray) -> None:
    tracks = [[(i % 7 + 1, k) for k in range(i % 5)] for i in range(len(xyz))]
    path = tmp_path / "points3D.bin"
    write_colmap_points_bin(path, xyz, tracks=tracks)
    assert path.stat().st_size == 8 + 51 * len(xyz) + 8 * sum(map(len, tracks))
    assert np.array_equal(read_colmap(path).xyz, xyz)
    path.write_bytes(path.read_bytes()[:-4])
    with pytest.raises(FormatError, match="points3D.bin: the file is truncated"):
        read_colmap(path)


def test_colmap_txt_with_tracks_and_malformed_line(tmp_path: Path) -> None:
    path = tmp_path / "points3D.txt"
    path.write_text("# 3D point list\n1 1.5 2.5 3.5 10 20 30 0.5 1 4 2 9 3 7\n2 4 5 6 1 1 1 0.1 \n")
    assert np.array_equal(read_colmap(path).xyz, [[1.5, 2.5, 3.5], [4, 5, 6]])
    path.write_text("# 3D point list\n1 1.5 2.5 3.5 10 20 30 0.5\n2 4 5 6 1 1\n")
    with pytest.raises(FormatError, match="points3D.txt: line 3: expected 'POINT3D_ID X Y Z"):
        read_colmap(path)


def test_colmap_truncated_images_bin(tmp_path: Path, xyz: np.ndarray) -> None:
    rot, centres = _cameras(3)
    write_colmap_model_bin(tmp_path, xyz, centres, rot)
    images = tmp_path / "images.bin"
    images.write_bytes(images.read_bytes()[:-30])
    with pytest.raises(FormatError, match="images.bin: the file is truncated"):
        read_colmap_model(tmp_path)


# --- Bundler ------------------------------------------------------------------------------------


def test_bundler_model_cameras(tmp_path: Path, xyz: np.ndarray) -> None:
    rot, centres = _cameras(4)
    cams = [(r, -r @ c) for r, c in zip(rot, centres)]
    cams.insert(2, (np.zeros((3, 3)), np.zeros(3)))  # unregistered: skipped on reading
    path = tmp_path / "bundle.out"
    write_bundler(path, xyz, cameras=cams)
    with unchanged(path):
        model = read_bundler_model(path)
    assert np.array_equal(model.points.xyz, xyz)
    np.testing.assert_allclose(model.camera_centres, centres, rtol=0, atol=1e-6)
    # Bundler cameras look down their negative z axis
    np.testing.assert_allclose(model.viewing_directions, -rot[:, 2, :], rtol=0, atol=1e-12)


def test_bundler_known_answer(tmp_path: Path) -> None:
    path = tmp_path / "bundle.out"
    path.write_text(
        "# Bundle file v0.3\n2 2\n"
        "800 -0.1 0.01\n1 0 0\n0 1 0\n0 0 1\n0 0 -10\n"  # at (0, 0, 10) looking down
        "800 0 0\n1 0 0\n0 0 1\n0 -1 0\n1 2 3\n"  # 90 deg about x
        "1.5 2.5 3.5\n255 0 0\n2 0 5 10.5 -3.25 1 7 -1.0 2.0\n"
        "4 5 6\n0 255 0\n2 0 6 1 1 1 8 2 2\n"
    )
    model = read_bundler_model(path)
    assert np.array_equal(model.points.xyz, [[1.5, 2.5, 3.5], [4, 5, 6]])
    np.testing.assert_allclose(model.camera_centres, [[0, 0, 10], [-1, 3, -2]], atol=1e-12)
    np.testing.assert_allclose(model.viewing_directions, [[0, 0, -1], [0, 1, 0]], atol=1e-12)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("# Bundle file v0.3\n1 2\n0 0 0\n", "truncated"),
        ("# Bundle file v0.3\nmany\n", "num_cameras"),
        ("# Bundle file v0.3\n0 2\n1 2 3\n0 0 0\n0\n1 2 x\n0 0 0\n0\n", "line 6: expected 3"),
        ("# Bundle file v0.3\n0 2\n1 2 3\n0 0 0\n0\n1 2 3\n0 0 0 0\n0\n", "line 7: expected 3"),
    ],
)
def test_bundler_malformed(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bundle.out"
    path.write_text(text)
    with pytest.raises(FormatError, match=f"bundle.out: .*{message}"):
        read_bundler(path)


# --- detection by content -----------------------------------------------------------------------


def test_detect_by_content(tmp_path: Path, xyz: np.ndarray) -> None:
    cases: dict[str, Path] = {}
    write_ply(tmp_path / "points.dat", xyz)
    cases["ply"] = tmp_path / "points.dat"
    write_ply(tmp_path / "ascii_ply.txt", xyz, binary=False)
    cases["ply-ascii"] = tmp_path / "ascii_ply.txt"
    write_bundler(tmp_path / "bundle.out", xyz)
    cases["bundler"] = tmp_path / "bundle.out"
    write_bundler(tmp_path / "scene.txt", xyz)
    cases["bundler-txt"] = tmp_path / "scene.txt"
    (tmp_path / "model").mkdir()
    write_colmap_points_bin(tmp_path / "model" / "points3D.bin", xyz)
    cases["colmap"] = tmp_path / "model"
    write_colmap_points_txt(tmp_path / "tiepoints.txt", xyz)
    cases["colmap-renamed"] = tmp_path / "tiepoints.txt"
    write_xyz(tmp_path / "noext", xyz)
    cases["xyz"] = tmp_path / "noext"
    for kind, path in cases.items():
        with unchanged(path):
            assert detect_format(path) == kind.split("-")[0], kind
            assert np.array_equal(read_points(path).xyz, xyz), kind


def test_unknown_content_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "notes.dat"
    path.write_bytes(struct.pack("<4d", 1, 2, 3, 4) + b"\x00binary")
    with pytest.raises(FormatError, match="notes.dat: unknown point format"):
        detect_format(path)
