"""ASCII point files: XYZ, TXT, CSV and PTS.

One point per line, values separated by whitespace, commas or semicolons. An optional header line
names the columns (``X,Y,Z,intensity``, ``id easting northing height``; CloudCompare's ``//X,Y,Z``
comment header counts too); without one the first three columns are x, y and z. Extra columns are
ignored, lines starting with ``#`` or ``//`` and blank lines are skipped, and a Leica PTS point
count on the first line is recognised. There is no formal specification; see e.g. the CloudCompare
ASCII documentation, https://www.cloudcompare.org/doc/wiki/index.php/FILE_I/O .

Written files hold ``x y z`` per line with the shortest decimal that gives back the same float64
(Python's ``repr``), so ``read_xyz(write_xyz(xyz))`` returns ``xyz`` bit for bit.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..points import PointSet
from .base import atomic_output, check_xyz, format_rows, open_input

__all__ = ["read_xyz", "sniff_xyz", "write_xyz"]

_COMMENTS = ("#", "//")
# Header names accepted for each axis, compared after lower-casing and dropping units: "X [m]".
_AXIS_NAMES = (
    ("x", "easting", "east", "lon", "longitude", "x_coord", "xcoord"),
    ("y", "northing", "north", "lat", "latitude", "y_coord", "ycoord"),
    ("z", "height", "elevation", "elev", "altitude", "alt", "h", "z_coord", "zcoord"),
)
_WRITE_CHUNK = 500_000










def _is_comment(s: str) -> bool:
    return not s or s.startswith(_COMMENTS)


def _delimiter(line: str) -> str | None:
    if ";" in line:
        return ";"
    if "," in line:
        return ","
    return None


def _split(line: str, delimiter: str | None) -> list[str]:
    line = line.split("#", 1)[0]
    if delimiter is None:
        return line.split()
    return [t.strip() for t in line.split(delimiter)]


def _numbers(tokens: list[str], cols: tuple[int, ...]) -> bool:
    try:
        for c in cols:
            float(tokens[c])
    except (IndexError, ValueError):
        return False
    return True


def _axis_columns(names: list[str], path: Path) -> tuple[int, int, int] | None:
    """Columns of x, y, z named by a header, or ``None`` when it names none of them."""
    norm = [re.sub(r"[\[(].*$", "", n.strip().strip("\"'/").lower()).strip() for n in names]
    found = [next((i for i, n in enumerate(norm) if n in axis), None) for axis in _AXIS_NAMES]
    if all(f is None for f in found):
        return None
    if any(f is None for f in found):
        missing = [a[0] for a, f in zip(_AXIS_NAMES, found) if f is None]
        raise FormatError(
            f"{path}: the header names some coordinate columns but not {', '.join(missing)} "
            f"(header: {', '.join(names)}); name the columns x, y, z (or easting, northing, "
            "height) or remove the header"
        )
    return tuple(found)  # type: ignore[return-value]


def _bad_line(path: Path, n: int, line: str, need: int, delimiter: str | None) -> FormatError:
    tokens = _split(line, delimiter)
    shown = line.strip()
    shown = shown if len(shown) <= 60 else shown[:57] + "..."
    what = f"{len(tokens)} value(s)" if len(tokens) < need else "non-numeric values"
    hint = "; use a decimal point, not a comma" if delimiter == ";" and "," in line else ""
    return FormatError(
        f"{path}: line {n}: expected at least three numbers x y z, found {what} ({shown!r})"
        f"{hint}; fix the file or name its real format with `format`"
    )


def _scan(lines: Iterable[str], path: Path) -> tuple[int, str | None, tuple[int, ...]] | None:
    """``(first data line, delimiter, x/y/z columns)``, or ``None`` when no data line came.

    ``first`` is 1-based; the lines before it are comments, blank, a header or a PTS count.
    """
    header: list[str] | None = None
    header_cols: tuple[int, ...] = (0, 1, 2)
    comment: str | None = None
    count_line = False
    for n, raw in enumerate(lines, start=1):
        s = raw.strip()
        if _is_comment(s):
            if s:
                comment = s.lstrip("#/ ")
            continue
        delimiter = _delimiter(s)
        tokens = _split(s, delimiter)
        if _numbers(tokens, header_cols):
            cols = header_cols
            if header is None and comment is not None:  # CloudCompare: "//X,Y,Z,R,G,B"
                names = _split(comment, _delimiter(comment))
                if len(names) == len(tokens):
                    try:
                        cols = _axis_columns(names, path) or cols
                    except FormatError:
                        pass  # an ordinary comment that happens to mention x or y
                    if not _numbers(tokens, cols):
                        raise _bad_line(path, n, raw, max(cols) + 1, delimiter)
            return n, delimiter, cols
        if header is None and not count_line:
            if len(tokens) == 1 and tokens[0].isdigit():
                count_line = True  # Leica PTS: the number of points comes first
                continue
            if any(c.isalpha() for c in s):
                header = _split(s, delimiter)
                header_cols = _axis_columns(header, path) or header_cols
                continue
        raise _bad_line(path, n, raw, max(header_cols) + 1, delimiter)
    return None


def read_xyz(path: str | os.PathLike[str]) -> PointSet:
    """Read an ASCII point file.

    Parameters
    ----------
    path
        The ``.xyz``/``.txt``/``.csv``/``.pts`` file.

    Returns
    -------
    PointSet
        The x, y, z columns as float64.

    Raises
    ------
    FormatError
        A line holds fewer than three numbers or non-numeric coordinates.
    """
    p = Path(path)
    with open_input(p, "r", encoding="utf-8-sig", errors="replace") as fh:
        found = _scan(fh, p)
        if found is None:
            return PointSet(np.empty((0, 3)), source=str(p))
        first, delimiter, cols = found
        fh.seek(0)
        try:
            data = np.loadtxt(
                fh, dtype=np.float64, delimiter=delimiter, comments=list(_COMMENTS),
                skiprows=first - 1, usecols=cols, ndmin=2,
            )
        except ValueError as exc:
            raise _locate_error(p, first, delimiter, cols, str(exc)) from None
    return PointSet(data, source=str(p))


def _locate_error(
    path: Path, first: int, delimiter: str | None, cols: tuple[int, ...], detail: str
) -> FormatError:
    """Find the first offending line (slow path, only taken when parsing failed)."""
    with open(path, encoding="utf-8-sig", errors="replace") as fh:
        for n, raw in enumerate(fh, start=1):
            if n < first or _is_comment(raw.strip()):
                continue
            tokens = _split(raw, delimiter)
            if tokens and not _numbers(tokens, cols):
                return _bad_line(path, n, raw, max(cols) + 1, delimiter)
    return FormatError(f"{path}: cannot be parsed as x y z columns ({detail}); fix the file")


def write_xyz(
    path: str | os.PathLike[str], xyz: np.ndarray, *, delimiter: str | None = None
) -> None:
    """Write ``x y z`` lines that read back bit for bit.

    Parameters
    ----------
    path
        Output file; written atomically.
    xyz
        ``(N, 3)`` coordinates.
    delimiter
        Column separator; default ``","`` for ``.csv`` names and a space otherwise.
    """
    arr = check_xyz(path, xyz)
    sep = delimiter if delimiter is not None else ("," if str(path).lower().endswith(".csv")
                                                   else " ")
    with atomic_output(path) as tmp, open(tmp, "w", encoding="ascii", newline="\n") as fh:
        fh.writelines(
            format_rows(arr[start : start + _WRITE_CHUNK], sep=sep)
            for start in range(0, len(arr), _WRITE_CHUNK)
        )


def sniff_xyz(path: Path, head: bytes) -> bool:
    """True when the first data line of ``head`` (after comments and a header) has 3 numbers."""
    if not head or b"\x00" in head:
        return False
    text = head.decode("latin-1").removeprefix("\xef\xbb\xbf")
    lines = text.splitlines()
    if len(head) >= 4096 and not text.endswith(("\n", "\r")):
        lines = lines[:-1]  # the last line may be cut off
    try:
        return _scan(lines, path) is not None
    except FormatError:
        return False
