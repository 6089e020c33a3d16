"""COLMAP sparse models: ``points3D.txt``/``points3D.bin`` and the images beside them.

A path may be a points file or a model folder (``sparse/0``) holding ``points3D.bin`` or
``points3D.txt`` and ``images.bin``/``images.txt``. Layouts as in the COLMAP documentation,
"Output format": https://colmap.github.io/format.html . The binary fields are little-endian:

* ``points3D.bin``: uint64 count, then per point uint64 id, 3 double xyz, 3 uint8 rgb,
  double error, uint64 track length and that many (int32 image id, int32 point2D index);
* ``images.bin``: uint64 count, then per image int32 id, 4 double qvec (w, x, y, z),
  3 double tvec, int32 camera id, a NUL-terminated name, uint64 number of 2-D points and that
  many (double x, double y, int64 point3D id).

``qvec`` and ``tvec`` map world to camera, ``x_cam = R x + t``: the camera centre is
``-R^T t`` and the optical axis (camera +z) points along ``R^T [0, 0, 1]``.
"""

from __future__ import annotations

import os
import struct
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..points import PointSet
from .base import atomic_output, check_xyz, format_rows, freeze_arrays, open_input, read_bytes

__all__ = [
    "ColmapModel",
    "quaternion_to_rotation",
    "read_colmap",
    "read_colmap_model",
    "sniff_colmap",
    "write_colmap_model_bin",
    "write_colmap_model_txt",
    "write_colmap_points_bin",
    "write_colmap_points_txt",
]

_POINT = struct.Struct("<Q3d3BdQ")  # 51 bytes before the track
_IMAGE = struct.Struct("<i4d3di")  # 64 bytes before the name
_U64 = struct.Struct("<Q")
_NAMES = ("points3D.bin", "points3D.txt")
_FIX = "re-export the model from COLMAP (File > Export model) or check the file"


@dataclass(frozen=True, eq=False)
class ColmapModel:
    """Tie points and the registered images of a COLMAP model, in the model frame.

    ``camera_centres`` and ``viewing_directions`` (unit optical axes) are ``(M, 3)`` float64,
    one row per image in file order, named by ``image_names``.
    """

    points: PointSet
    camera_centres: np.ndarray = field(repr=False)
    viewing_directions: np.ndarray = field(repr=False)
    image_names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        freeze_arrays(self, "camera_centres", "viewing_directions")


def sniff_colmap(path: Path, head: bytes) -> bool:
    """True for ``points3D.txt``/``.bin``, a folder holding one, or COLMAP's text comment."""
    p = Path(path)
    if p.is_dir():
        return any((p / n).is_file() for n in _NAMES)
    return p.name.lower() in {n.lower() for n in _NAMES} or head.startswith(b"# 3D point list")


def _files(path: Path) -> tuple[Path, Path | None]:
    """The points file and the images file (if any) for a file or folder ``path``."""
    if path.is_dir():
        points = next((path / n for n in _NAMES if (path / n).is_file()), None)
        if points is None:
            raise InputError(
                f"{path}: the folder holds no points3D.bin or points3D.txt; "
                "point at the COLMAP model folder (e.g. sparse/0)"
            )
    elif not path.exists():
        raise InputError(f"{path}: no such file or directory; check the path")
    else:
        points = path
        if path.name.lower() not in {n.lower() for n in _NAMES}:
            return points, None
    first = "images.bin" if points.suffix.lower() == ".bin" else "images.txt"
    other = "images.txt" if first == "images.bin" else "images.bin"
    images = next((points.parent / n for n in (first, other) if (points.parent / n).is_file()),
                  None)
    return points, images


def _read_points_txt(path: Path) -> np.ndarray:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
            with open_input(path, "r", encoding="utf-8", errors="replace") as fh:
                data = np.loadtxt(fh, dtype=np.float64, comments="#", usecols=range(8), ndmin=2)
    except ValueError:
        with open(path, encoding="utf-8", errors="replace") as fh:
            for n, line in enumerate(fh, start=1):
                words = line.split()
                if not words or words[0].startswith("#"):
                    continue
                try:
                    ok = len([float(w) for w in words[:8]]) == 8
                except ValueError:
                    ok = False
                if not ok:
                    shown = line.strip()[:60]
                    raise FormatError(
                        f"{path}: line {n}: expected 'POINT3D_ID X Y Z R G B ERROR TRACK[]', "
                        f"found {shown!r}; {_FIX}"
                    ) from None
        raise FormatError(f"{path}: cannot be parsed as a COLMAP points3D.txt; {_FIX}") from None
    return np.ascontiguousarray(data[:, 1:4])


def _truncated(path: Path, what: str) -> FormatError:
    return FormatError(f"{path}: the file is truncated or corrupt ({what}); {_FIX}")


def _read_points_bin(path: Path) -> np.ndarray:
    buf = read_bytes(path)
    if len(buf) < 8:
        raise _truncated(path, "no point count")
    (n,) = _U64.unpack_from(buf, 0)
    if n * _POINT.size > len(buf) - 8:
        raise _truncated(path, f"{n} points announced, {len(buf)} bytes in the file")
    offsets = np.empty(n, dtype=np.int64)
    off = 8
    unpack = _U64.unpack_from
    try:
        for i in range(n):
            offsets[i] = off
            off += _POINT.size + 8 * unpack(buf, off + 43)[0]
    except struct.error:
        raise _truncated(path, f"point {i + 1} of {n} is cut off") from None
    if off != len(buf):
        what = f"point {n} is cut off" if off > len(buf) else f"{len(buf) - off} bytes left over"
        raise _truncated(path, what)
    raw = np.frombuffer(buf, dtype=np.uint8)
    xyz = np.empty((n, 3), dtype=np.float64)
    cols = np.arange(8, 32)
    for start in range(0, n, 100_000):
        idx = offsets[start : start + 100_000, None] + cols
        xyz[start : start + 100_000] = raw[idx].view("<f8").reshape(-1, 3)
    return xyz


def _read_images_txt(path: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    lines = [
        ln for ln in read_bytes(path).decode("utf-8", errors="replace").splitlines()
        if not ln.startswith("#")
    ]
    names, q, t = [], [], []
    for k in range(0, len(lines), 2):  # the 2-D point line after each image may be empty
        if not lines[k].strip() and k == len(lines) - 1:
            break
        words = lines[k].split(maxsplit=9)
        try:
            q.append([float(w) for w in words[1:5]])
            t.append([float(w) for w in words[5:8]])
            _ = (int(words[0]), int(words[8]))
            names.append(words[9].strip())
        except (IndexError, ValueError):
            raise FormatError(
                f"{path}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', found "
                f"{lines[k].strip()[:60]!r}; {_FIX}"
            ) from None
    return names, np.array(q, dtype=np.float64).reshape(-1, 4), np.array(t).reshape(-1, 3)


def _read_images_bin(path: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    buf = read_bytes(path)
    names, q, t = [], [], []
    try:
        (n,) = _U64.unpack_from(buf, 0)
        off = 8
        for _ in range(n):
            rec = _IMAGE.unpack_from(buf, off)
            q.append(rec[1:5])
            t.append(rec[5:8])
            end = buf.index(b"\x00", off + _IMAGE.size)
            names.append(buf[off + _IMAGE.size : end].decode("utf-8", errors="replace"))
            off = end + 9 + 24 * _U64.unpack_from(buf, end + 1)[0]
    except (struct.error, ValueError):
        raise _truncated(path, f"image {len(t) + 1} is cut off") from None
    if off != len(buf):
        raise _truncated(path, "the image records do not fill the file")
    return names, np.array(q, dtype=np.float64).reshape(-1, 4), np.array(t).reshape(-1, 3)


def quaternion_to_rotation(qvec: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(M, 3, 3)`` from COLMAP quaternions ``(M, 4)`` as (w, x, y, z)."""
    q = np.asarray(qvec, dtype=np.float64).reshape(-1, 4)
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)


def read_colmap(path: str | os.PathLike[str]) -> PointSet:
    """Read the tie points of a COLMAP model (``points3D.txt``/``.bin`` or the model folder)."""
    points, _ = _files(Path(path))
    binary = points.suffix.lower() == ".bin"
    xyz = _read_points_bin(points) if binary else _read_points_txt(points)
    return PointSet(xyz, source=str(points))


def read_colmap_model(path: str | os.PathLike[str]) -> ColmapModel:
    """Read tie points, camera centres and viewing directions of a COLMAP model.

    Parameters
    ----------
    path
        ``points3D.txt``/``points3D.bin`` or the model folder; ``images.bin``/``images.txt``
        beside the points file give the cameras (empty arrays when there is none).
    """
    points_file, images_file = _files(Path(path))
    points = read_colmap(points_file)
    if images_file is None:
        return ColmapModel(points, np.empty((0, 3)), np.empty((0, 3)), ())
    reader = _read_images_bin if images_file.suffix == ".bin" else _read_images_txt
    names, q, t = reader(images_file)
    rot = quaternion_to_rotation(q)
    centres = -np.einsum("mji,mj->mi", rot, t)
    return ColmapModel(points, centres, np.ascontiguousarray(rot[:, 2, :]), tuple(names))


_POINTS_COMMENT = (
    "# 3D point list with one line of data per point:\n"
    "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
    "# Number of points: {}, mean track length: 0\n"
)


def write_colmap_points_txt(path: str | os.PathLike[str], xyz: np.ndarray) -> None:
    """Write a ``points3D.txt`` (ids 1..N, grey, error 0, empty tracks); round-trip decimals."""
    arr = check_xyz(path, xyz)
    ids = map(str, range(1, len(arr) + 1))
    body = format_rows(arr, prefix=ids).replace("\n", " 128 128 128 0\n")
    with atomic_output(path) as tmp:
        tmp.write_text(_POINTS_COMMENT.format(len(arr)) + body, encoding="ascii")


def write_colmap_points_bin(
    path: str | os.PathLike[str],
    xyz: np.ndarray,
    *,
    tracks: Sequence[Sequence[tuple[int, int]]] | None = None,
) -> None:
    """Write a ``points3D.bin``; ``tracks`` optionally gives (image id, 2-D index) per point."""
    arr = check_xyz(path, xyz)
    rec = np.zeros(len(arr), dtype=[("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3),
                                    ("error", "<f8"), ("n", "<u8")])
    rec["id"] = np.arange(1, len(arr) + 1)
    rec["xyz"] = arr
    rec["rgb"] = 128
    with atomic_output(path) as tmp, open(tmp, "wb") as fh:
        fh.write(_U64.pack(len(arr)))
        if tracks is None:
            rec.tofile(fh)
            return
        if len(tracks) != len(arr):
            raise InputError(f"{path}: {len(tracks)} tracks for {len(arr)} points")
        for r, track in zip(rec, tracks):
            r["n"] = len(track)
            fh.write(r.tobytes() + np.asarray(track, dtype="<i4").reshape(-1, 2).tobytes())


def _rotation_to_quaternion(rot: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    xyzw = Rotation.from_matrix(rot).as_quat()
    return np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)


def _write_model(
    folder: Path, xyz: np.ndarray, centres: np.ndarray, rotations: np.ndarray,
    names: Sequence[str] | None, binary: bool,
) -> None:
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    rot = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    if len(rot) != len(centres):
        raise InputError(f"{folder}: {len(centres)} camera centres but {len(rot)} rotations")
    names = list(names) if names is not None else [f"img_{i:05d}.jpg" for i in range(len(rot))]
    if len(names) != len(rot):
        raise InputError(f"{folder}: {len(names)} image names for {len(rot)} cameras")
    q = _rotation_to_quaternion(rot) if len(rot) else np.empty((0, 4))
    t = -np.einsum("mij,mj->mi", rot, centres)
    folder.mkdir(parents=True, exist_ok=True)
    w, h, f = 2000, 1500, 1000.0
    if binary:
        write_colmap_points_bin(folder / "points3D.bin", xyz)
        with atomic_output(folder / "cameras.bin") as tmp:
            tmp.write_bytes(struct.pack("<QiiQQ3d", 1, 1, 0, w, h, f, w / 2, h / 2))
        images = [_U64.pack(len(rot))]
        for i, name in enumerate(names):
            images.append(_IMAGE.pack(i + 1, *q[i], *t[i], 1) + name.encode() + b"\x00")
            images.append(_U64.pack(0))
        with atomic_output(folder / "images.bin") as tmp:
            tmp.write_bytes(b"".join(images))
        return
    write_colmap_points_txt(folder / "points3D.txt", xyz)
    with atomic_output(folder / "cameras.txt") as tmp:
        tmp.write_text(f"# Camera list\n1 SIMPLE_PINHOLE {w} {h} {f!r} {w / 2!r} {h / 2!r}\n")
    lines = ["# Image list with two lines of data per image:"]
    for i, name in enumerate(names):
        lines.append(" ".join(map(repr, [i + 1, *q[i].tolist(), *t[i].tolist(), 1])) + f" {name}")
        lines.append("")
    with atomic_output(folder / "images.txt") as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")


def write_colmap_model_txt(
    folder: str | os.PathLike[str], xyz: np.ndarray, camera_centres: np.ndarray,
    rotations_world_to_cam: np.ndarray, *, names: Sequence[str] | None = None,
) -> None:
    """Write a text model (points3D.txt, images.txt, cameras.txt with one SIMPLE_PINHOLE).

    ``camera_centres`` ``(M, 3)`` and ``rotations_world_to_cam`` ``(M, 3, 3)`` give ``t = -R C``.
    """
    _write_model(Path(folder), xyz, camera_centres, rotations_world_to_cam, names, False)


def write_colmap_model_bin(
    folder: str | os.PathLike[str], xyz: np.ndarray, camera_centres: np.ndarray,
    rotations_world_to_cam: np.ndarray, *, names: Sequence[str] | None = None,
) -> None:
    """Like :func:`write_colmap_model_txt` but with points3D.bin, images.bin, cameras.bin."""
    _write_model(Path(folder), xyz, camera_centres, rotations_world_to_cam, names, True)
