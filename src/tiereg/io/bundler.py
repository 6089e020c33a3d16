"""Bundler ``bundle.out`` files (v0.3), also written by VisualSFM, Agisoft and others.

Layout (Bundler user's manual, "Output format": https://www.cs.cornell.edu/~snavely/bundler/
bundler-v0.4-manual.html#S6)::

    # Bundle file v0.3
    <num_cameras> <num_points>
    <camera 1: f k1 k2 / R row 1 / R row 2 / R row 3 / t>   (5 lines per camera)
    ...
    <point 1: x y z / r g b / view list>                    (3 lines per point)

A camera maps world to camera coordinates as ``x_cam = R x + t`` and looks down its *negative*
z axis: the centre is ``-R^T t`` and the viewing direction ``R^T [0, 0, -1]``. Cameras that
Bundler could not register are written with all-zero values and are skipped.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..points import PointSet
from .base import atomic_output, check_xyz, format_rows, freeze_arrays, read_bytes

__all__ = ["BundlerModel", "read_bundler", "read_bundler_model", "sniff_bundler", "write_bundler"]

_MAGIC = b"# Bundle file v0.3"
_FIX = "re-export the bundle file or check that it is complete"


@dataclass(frozen=True, eq=False)
class BundlerModel:
    """Tie points and registered cameras of a Bundler file, in the model frame.

    ``camera_centres`` and ``viewing_directions`` (unit) are ``(M, 3)`` float64, one row per
    registered camera in file order.
    """

    points: PointSet
    camera_centres: np.ndarray = field(repr=False)
    viewing_directions: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        freeze_arrays(self, "camera_centres", "viewing_directions")


def sniff_bundler(path: Path, head: bytes) -> bool:
    """True when the first line is ``# Bundle file v0.3``."""
    return head.removeprefix(b"\xef\xbb\xbf").startswith(_MAGIC)


def _numbers(path: Path, lines: list[tuple[int, str]], per: int, what: str) -> np.ndarray:
    """Parse numbered lines that must hold ``per`` numbers each into a ``(len, per)`` array."""
    if not lines:
        return np.empty((0, per))
    try:
        values = np.loadtxt([ln for _, ln in lines], dtype=np.float64, comments=None, ndmin=2)
        if values.shape == (len(lines), per):
            return values
    except ValueError:
        pass
    for n, line in lines:  # slow path: name the offending line
        try:
            ok = len([float(w) for w in line.split()]) == per
        except ValueError:
            ok = False
        if not ok:
            raise FormatError(
                f"{path}: line {n}: expected {per} numbers ({what}), found "
                f"{line.strip()[:60]!r}; {_FIX}"
            )
    raise FormatError(f"{path}: cannot parse the {what} lines; {_FIX}")


def _parse(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(points (N, 3), cameras (M, 5, 3))`` of a bundle file."""
    text = read_bytes(path).decode("latin-1").removeprefix("\xef\xbb\xbf")
    # Line numbers for messages count every line; blank lines carry no data and are dropped.
    numbered = [(n, ln) for n, ln in enumerate(text.splitlines(), start=1) if ln.strip()]
    if not numbered or not numbered[0][1].startswith(_MAGIC.decode()):
        raise FormatError(f"{path}: does not start with '# Bundle file v0.3'; not a Bundler file")
    try:
        n_cam, n_pts = (int(w) for w in numbered[1][1].split())
    except (IndexError, ValueError):
        raise FormatError(
            f"{path}: the second line must hold '<num_cameras> <num_points>'; {_FIX}"
        ) from None
    if n_cam < 0 or n_pts < 0:
        raise FormatError(f"{path}: negative camera or point count; {_FIX}")
    need = 2 + 5 * n_cam + 3 * n_pts
    if len(numbered) < need:
        raise FormatError(
            f"{path}: the file is truncated: {n_cam} cameras and {n_pts} points need {need} "
            f"non-empty lines, found {len(numbered)}; {_FIX}"
        )
    cams = _numbers(path, numbered[2 : 2 + 5 * n_cam], 3,
                    "camera f k1 k2, rotation row or translation")
    start = 2 + 5 * n_cam
    xyz = _numbers(path, numbered[start : start + 3 * n_pts : 3], 3, "point x y z")
    _numbers(path, numbered[start + 1 : start + 3 * n_pts : 3], 3, "point colour r g b")
    return xyz, cams.reshape(n_cam, 5, 3)


def read_bundler(path: str | os.PathLike[str]) -> PointSet:
    """Read the tie points of a Bundler ``bundle.out`` file."""
    p = Path(path)
    xyz, _ = _parse(p)
    return PointSet(xyz, source=str(p))


def read_bundler_model(path: str | os.PathLike[str]) -> BundlerModel:
    """Read tie points, camera centres and viewing directions of a Bundler file.

    Unregistered cameras (all-zero rotation) are left out.
    """
    p = Path(path)
    xyz, cams = _parse(p)
    rot = cams[:, 1:4, :]
    t = cams[:, 4, :]
    ok = np.any(rot != 0, axis=(1, 2))
    rot, t = rot[ok], t[ok]
    centres = -np.einsum("mji,mj->mi", rot, t)
    directions = -rot[:, 2, :]
    return BundlerModel(PointSet(xyz, source=str(p)), centres, np.ascontiguousarray(directions))


def write_bundler(
    path: str | os.PathLike[str],
    xyz: np.ndarray,
    *,
    cameras: Sequence[tuple[np.ndarray, np.ndarray]] = (),
    focal: float = 1000.0,
) -> None:
    """Write a ``bundle.out`` with round-trip decimals.

    Parameters
    ----------
    path
        Output file; written atomically.
    xyz
        ``(N, 3)`` tie points (grey, with empty view lists).
    cameras
        ``(R, t)`` per camera, world to camera (``x_cam = R x + t``); an all-zero ``R`` writes
        an unregistered camera.
    focal
        Focal length written for every registered camera.
    """
    arr = check_xyz(path, xyz)
    out = [f"{_MAGIC.decode()}\n{len(cameras)} {len(arr)}\n"]
    for rot, t in cameras:
        rot = np.asarray(rot, dtype=np.float64)
        t = np.asarray(t, dtype=np.float64)
        if rot.shape != (3, 3) or t.shape != (3,):
            raise InputError(f"{path}: each camera needs a 3x3 rotation and a 3-vector translation")
        f = focal if rot.any() else 0.0
        out.append(format_rows(np.vstack([[f, 0.0, 0.0], rot, t])))
    out.append(format_rows(arr).replace("\n", "\n128 128 128\n0\n"))
    with atomic_output(path) as tmp:
        tmp.write_text("".join(out), encoding="ascii")
