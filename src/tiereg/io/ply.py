"""PLY (Stanford polygon) point files: ascii, binary little- and big-endian.

Only the ``vertex`` element's ``x``, ``y`` and ``z`` are read; other vertex properties (colours,
normals, ...) and other elements (faces after the vertices) are skipped. Specification:
http://paulbourke.net/dataformats/ply/ .

Written files hold ``double`` x, y, z (binary little-endian by default) so that projected
coordinates survive unchanged; the ascii variant uses the shortest round-trip decimals.
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..points import PointSet
from .base import atomic_output, check_xyz, format_rows, open_input

__all__ = ["read_ply", "sniff_ply", "write_ply"]

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "long": "i8", "int64": "i8", "ulong": "u8", "uint64": "u8",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_ENDIAN = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": ""}
_MAX_HEADER = 1 << 20
_CHUNK = 500_000  # points formatted at a time when writing ascii
_FIX = "re-export the file or convert it with another tool"


@dataclass
class _Element:
    name: str
    count: int
    props: list[tuple[str, str]]  # (name, numpy type code)
    has_list: bool = False


def sniff_ply(path: Path, head: bytes) -> bool:
    """True when ``head`` starts with the PLY magic line."""
    return head.startswith((b"ply\n", b"ply\r\n"))


def _parse_header(path: Path, fh: io.BufferedReader) -> tuple[str, list[_Element], int]:
    """``(format, elements, offset of the body)``."""
    if not sniff_ply(path, fh.read(5)):
        raise FormatError(f"{path}: does not start with 'ply'; the file is not PLY or corrupt")
    fh.seek(0)
    fmt: str | None = None
    elements: list[_Element] = []
    fh.readline()
    while True:
        raw = fh.readline(4096)
        if not raw.endswith(b"\n") or fh.tell() > _MAX_HEADER:
            raise FormatError(f"{path}: the PLY header has no 'end_header' line; {_FIX}")
        words = raw.decode("latin-1").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        key = words[0]
        try:
            if key == "end_header":
                break
            if key == "format":
                fmt = words[1]
            elif key == "element":
                count = int(words[2])
                if count < 0:  # a count: never negative
                    raise ValueError(words[2])
                elements.append(_Element(words[1], count, []))
            elif key == "property" and elements and words[1] == "list":
                if words[2] not in _TYPES or words[3] not in _TYPES:
                    raise KeyError(words[2])
                elements[-1].props.append((words[4], "list"))
                elements[-1].has_list = True
            elif key == "property" and elements:
                elements[-1].props.append((words[2], _TYPES[words[1]]))
            else:
                raise ValueError
        except (IndexError, KeyError, ValueError):
            line = raw.decode("latin-1").strip()
            raise FormatError(f"{path}: bad PLY header line {line!r}; {_FIX}") from None
    if fmt is None:
        raise FormatError(f"{path}: the PLY header has no 'format' line; {_FIX}")
    if fmt not in _ENDIAN:
        raise FormatError(f"{path}: unknown PLY format {fmt!r}; {_FIX}")
    return fmt, elements, fh.tell()


def _vertex(path: Path, elements: list[_Element]) -> tuple[int, _Element, tuple[int, int, int]]:
    idx = next((i for i, e in enumerate(elements) if e.name == "vertex"), None)
    if idx is None:
        raise FormatError(f"{path}: the PLY file has no 'vertex' element; {_FIX}")
    vert = elements[idx]
    names = [p for p, _ in vert.props]
    missing = [a for a in "xyz" if a not in names]
    if missing:
        raise FormatError(
            f"{path}: the PLY vertices have no {', '.join(missing)} property; {_FIX}"
        )
    cols = tuple(names.index(a) for a in "xyz")
    if any(t == "list" for _, t in vert.props[: max(cols) + 1]):
        raise FormatError(
            f"{path}: a list property comes before x, y, z in the PLY vertices; {_FIX}"
        )
    return idx, vert, cols  # type: ignore[return-value]


def read_ply(path: str | os.PathLike[str]) -> PointSet:
    """Read the vertices of a PLY file.

    Parameters
    ----------
    path
        The ``.ply`` file (ascii, binary little- or big-endian).

    Returns
    -------
    PointSet
        Vertex x, y, z as float64.

    Raises
    ------
    FormatError
        Bad header, no vertex x/y/z, or the file is truncated.
    """
    p = Path(path)
    with open_input(p) as fh:
        fmt, elements, offset = _parse_header(p, fh)
        idx, vert, cols = _vertex(p, elements)
        if fmt == "ascii":
            xyz = _read_ascii(p, fh, sum(e.count for e in elements[:idx]), vert, cols)
        else:
            xyz = _read_binary(p, fh, offset, _ENDIAN[fmt], elements[:idx], vert)
    return PointSet(xyz, source=str(p))


def _read_ascii(
    path: Path, fh: io.BufferedReader, skip: int, vert: _Element, cols: tuple[int, int, int]
) -> np.ndarray:
    if vert.count == 0:
        return np.empty((0, 3))
    text = io.TextIOWrapper(fh, encoding="latin-1")
    for _ in range(skip):
        if not text.readline():
            break
    try:
        data = np.loadtxt(
            text, dtype=np.float64, comments=None, usecols=cols, max_rows=vert.count, ndmin=2
        )
    except ValueError as exc:
        raise FormatError(
            f"{path}: an ascii PLY vertex line cannot be read ({exc}); {_FIX}"
        ) from None
    if len(data) < vert.count:
        raise FormatError(
            f"{path}: the file is truncated: the header announces {vert.count} vertices, "
            f"found {len(data)}; {_FIX}"
        )
    return data


def _dtype(path: Path, element: _Element, endian: str) -> np.dtype:
    if element.has_list:
        raise FormatError(
            f"{path}: the binary PLY element {element.name!r} before or in the vertices has "
            f"list properties, which tiereg cannot skip; {_FIX} with the vertices first"
        )
    return np.dtype([(f"f{i}_{n}", endian + t) for i, (n, t) in enumerate(element.props)])


def _read_binary(
    path: Path,
    fh: io.BufferedReader,
    offset: int,
    endian: str,
    before: list[_Element],
    vert: _Element,
) -> np.ndarray:
    for e in before:
        offset += e.count * _dtype(path, e, endian).itemsize
    dtype = _dtype(path, vert, endian)
    size = os.fstat(fh.fileno()).st_size
    need = offset + vert.count * dtype.itemsize
    if size < need:
        raise FormatError(
            f"{path}: the file is truncated: {need} bytes needed for {vert.count} vertices, "
            f"the file has {size}; {_FIX}"
        )
    fh.seek(offset)
    data = np.fromfile(fh, dtype=dtype, count=vert.count)
    names = {n: f for f, (n, _) in zip(dtype.names or (), vert.props)}
    xyz = np.empty((vert.count, 3), dtype=np.float64)
    for k, axis in enumerate("xyz"):
        xyz[:, k] = data[names[axis]]
    return xyz


def write_ply(path: str | os.PathLike[str], xyz: np.ndarray, *, binary: bool = True) -> None:
    """Write points as PLY vertices with double x, y, z.

    Parameters
    ----------
    path
        Output file; written atomically.
    xyz
        ``(N, 3)`` coordinates.
    binary
        Binary little-endian (default) or ascii with round-trip decimals.
    """
    arr = check_xyz(path, xyz)
    fmt = "binary_little_endian" if binary else "ascii"
    header = (
        f"ply\nformat {fmt} 1.0\ncomment written by tiereg\nelement vertex {len(arr)}\n"
        "property double x\nproperty double y\nproperty double z\nend_header\n"
    )
    with atomic_output(path) as tmp, open(tmp, "wb") as fh:
        fh.write(header.encode("ascii"))
        if binary:
            np.ascontiguousarray(arr, dtype="<f8").tofile(fh)
        else:
            fh.writelines(
                format_rows(arr[start : start + _CHUNK]).encode("ascii")
                for start in range(0, len(arr), _CHUNK)
            )
