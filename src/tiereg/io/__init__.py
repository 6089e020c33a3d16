"""Reading and writing the point and raster formats users have.

One module per format family; this registry picks the format by name and content:

========== ============================================ ======================
format     files                                        module
========== ============================================ ======================
``las``    ``.las``, ``.laz`` (LAS 1.0-1.4, any PDRF)   :mod:`tiereg.io.las`
``xyz``    ``.xyz``, ``.txt``, ``.csv``, ``.pts``       :mod:`tiereg.io.text`
``ply``    ``.ply`` (ascii and binary)                  :mod:`tiereg.io.ply`
``colmap`` ``points3D.txt``/``.bin``, a model folder    :mod:`tiereg.io.colmap`
``bundler````bundle.out``                               :mod:`tiereg.io.bundler`
``geotiff````.tif``, ``.tiff`` (DSM/DEM, nodata)        :mod:`tiereg.io.raster`
========== ============================================ ======================

Several LAS/LAZ files, a glob pattern or a directory of tiles open as one source.
"""

from __future__ import annotations

import glob
import os
import stat
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..crs import refuse_geographic
from ..errors import FormatError, InputError
from ..points import PointSet
from .base import (
    ArraySource,
    PointSource,
    SourceInfo,
    all_or_nothing,
    atomic_output,
    check_input_file,
    open_input,
)

__all__ = [
    "FORMATS",
    "PointSource",
    "SourceInfo",
    "all_or_nothing",
    "as_point_source",
    "atomic_output",
    "check_not_input",
    "detect_format",
    "open_points",
    "read_points",
    "write_points",
]


@dataclass(frozen=True)
class Format:
    """One entry of the registry."""

    name: str
    suffixes: tuple[str, ...]
    sniff: Callable[[Path, bytes], bool]
    open: Callable[[Path], PointSource]
    write: Callable[..., None] | None = None


def _las_sniff(path: Path, head: bytes) -> bool:
    return head[:4] == b"LASF"


def _las_open(path: Path) -> PointSource:
    from .las import LasSource

    return LasSource([path])


def _las_write(path: Path, xyz: np.ndarray, **kw: object) -> None:
    from .las import write_las

    write_las(path, xyz, **kw)  # type: ignore[arg-type]


def _lazy(module: str, func: str) -> Callable[..., object]:
    def call(*args: object, **kw: object) -> object:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{module}"), func)(*args, **kw)

    call.__name__ = func
    return call


def _wrap_reader(module: str, func: str, fmt: str) -> Callable[[Path], PointSource]:
    reader = _lazy(module, func)

    def open_(path: Path) -> PointSource:
        points = reader(path)
        assert isinstance(points, PointSet)
        return ArraySource(points, format=fmt)

    return open_


def _raster_open(path: Path) -> PointSource:
    from .raster import RasterSource

    return RasterSource(path)


FORMATS: dict[str, Format] = {
    f.name: f
    for f in (
        Format("las", (".las", ".laz"), _las_sniff, _las_open, _las_write),
        Format(
            "ply", (".ply",), _lazy("ply", "sniff_ply"), _wrap_reader("ply", "read_ply", "ply"),
            _lazy("ply", "write_ply"),
        ),
        Format(
            "colmap", (), _lazy("colmap", "sniff_colmap"),
            _wrap_reader("colmap", "read_colmap", "colmap"),
        ),
        Format(
            "bundler", (".out",), _lazy("bundler", "sniff_bundler"),
            _wrap_reader("bundler", "read_bundler", "bundler"),
        ),
        Format(
            "geotiff", (".tif", ".tiff"), lambda p, h: h[:4] in (b"II*\x00", b"MM\x00*",
                                                               b"II+\x00", b"MM\x00+"),
            _raster_open,
        ),
        Format(
            "xyz", (".xyz", ".txt", ".csv", ".pts", ".asc"), _lazy("text", "sniff_xyz"),
            _wrap_reader("text", "read_xyz", "xyz"), _lazy("text", "write_xyz"),
        ),
    )
}

_SUPPORTED = "LAS/LAZ, XYZ/TXT/CSV, PLY, COLMAP (points3D.txt/.bin or model folder), " \
    "Bundler (.out), GeoTIFF"


def _head(path: Path) -> bytes:
    with open_input(path) as fh:
        return fh.read(4096)


def _is_text(head: bytes) -> bool:
    """Whether the file's first bytes read as text: no NUL byte, and at least 95 % printable
    characters when read as latin-1 (which UTF-8 text passes too)."""
    if b"\x00" in head:
        return False
    text = head.decode("latin-1")
    printable = sum(c.isprintable() or c in "\r\n\t" for c in text)
    return printable >= 0.95 * len(text)


def detect_format(path: str | os.PathLike[str], *, format: str | None = None) -> str:
    """The registry name of ``path``'s format, by content first and then by name."""
    p = Path(path)
    if format is not None:
        if format not in FORMATS:
            raise InputError(
                f"unknown format {format!r}; choose one of: {', '.join(sorted(FORMATS))}"
            )
        return format
    if stat.S_ISDIR(check_input_file(p).st_mode):
        if FORMATS["colmap"].sniff(p, b""):
            return "colmap"
        raise InputError(
            f"{p}: is a directory without point files (.las/.laz tiles) or a COLMAP model "
            "(points3D.bin/.txt); give the files themselves or the right folder"
        )
    head = _head(p)
    if not head:
        raise FormatError(f"{p}: the file is empty; give a file with points in it")
    for fmt in ("las", "geotiff", "ply", "bundler", "colmap"):
        if FORMATS[fmt].sniff(p, head):
            return fmt
    suffix = p.suffix.lower()
    if suffix in (".las", ".laz"):
        raise FormatError(
            f"{p}: does not start with the LAS signature 'LASF' - the file is corrupt or not "
            "LAS/LAZ; re-export it or name its real format with `format`"
        )
    if FORMATS["xyz"].sniff(p, head) or (suffix in FORMATS["xyz"].suffixes
                                          and _is_text(head)):
        return "xyz"  # a text file by its name: its reader says what it cannot read, and why
    raise FormatError(
        f"{p}: unknown point format (suffix {suffix or 'none'!r}); tiereg reads {_SUPPORTED} - "
        "convert the file or name its format with `format`"
    )


def check_not_input(out: str | os.PathLike[str], *inputs: object) -> None:
    """Refuse an output path that names one of the ``inputs`` (paths, globs, folders of tiles or
    COLMAP models, or lists of them; arrays are skipped): writing it would destroy the input.
    Links count: the test is whether the two names are one file."""
    target = Path(out)
    if not target.is_file():
        return
    for item in inputs:
        items = [item] if isinstance(item, (str, os.PathLike)) else (
            list(item) if isinstance(item, (list, tuple)) else [])
        for s in map(os.fspath, items):
            p = Path(s)
            files = ([Path(m) for m in glob.glob(s)] if not p.exists()
                     else [q for q in p.iterdir() if q.is_file()] if p.is_dir() else [p])
            for f in files:
                if f.is_file() and os.path.samefile(f, target):
                    raise InputError(f"{out}: the output would overwrite the input {f}; "
                                     "choose another output name")


def expand_paths(paths: str | os.PathLike[str] | Sequence[str | os.PathLike[str]]) -> list[Path]:
    """Turn a path, a glob pattern, a directory of tiles or a list of these into files."""
    if not _is_paths(paths):
        raise InputError(_not_points(paths, ""))
    items = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    out: list[Path] = []
    for item in items:
        s = os.fspath(item)
        if any(c in s for c in "*?[") and not Path(s).exists():
            matches = sorted(glob.glob(s))
            if not matches:
                raise InputError(f"{s}: the pattern matches no file; check the pattern")
            out.extend(Path(m) for m in matches)
            continue
        p = Path(s)
        if p.is_dir() and not FORMATS["colmap"].sniff(p, b""):
            tiles = sorted(
                q for q in p.iterdir() if q.is_file() and q.suffix.lower() in (".las", ".laz")
            )
            if not tiles:
                raise InputError(
                    f"{p}: the directory holds no point files (.las/.laz) and no COLMAP model; "
                    "point at the tiles' folder or at a file"
                )
            out.extend(tiles)
            continue
        out.append(p)
    return out


def open_points(
    paths: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    *,
    format: str | None = None,
) -> PointSource:
    """Open a point file, several tiles or a raster as a chunked :class:`PointSource`.

    Nothing but headers is read here; the points come through ``source.chunks()`` or
    ``source.read()``.
    """
    files = expand_paths(paths)
    if len(files) > 1:
        fmts = {detect_format(f, format=format) for f in files}
        if fmts != {"las"}:
            raise InputError(
                "several inputs count as one reference only when they are all LAS/LAZ tiles; "
                f"got formats {sorted(fmts)}"
            )
        from .las import LasSource

        return LasSource(files)
    fmt = detect_format(files[0], format=format)
    return FORMATS[fmt].open(files[0])


PointsArg = str | os.PathLike[str] | Sequence[str | os.PathLike[str]] | PointSet | np.ndarray


def as_point_source(obj: PointsArg | PointSource, *, role: str,
                    format: str | None = None) -> PointSource:
    """What a registration accepts as its ``role`` (``"moving"`` or ``"reference"``) points,
    opened: a path, a glob, a folder of tiles or a list of paths (read with ``format`` when
    given), a :class:`~tiereg.PointSet`, an ``(N, 3)`` array of numbers, or a
    :class:`PointSource`.

    Anything else, coordinates that are not finite, and coordinates in longitude and latitude
    (a geographic CRS: cells, shifts and scales in degrees mean nothing) raise
    :class:`InputError` naming ``role``; a format error names the ``<role>_format`` parameter.
    """
    if isinstance(obj, PointSource):
        source = obj
    elif isinstance(obj, PointSet):
        refuse_geographic(obj.crs_wkt, where=obj.source, role=role)
        source = ArraySource(obj)
    elif isinstance(obj, np.ndarray):
        if obj.dtype.kind not in "iuf":
            raise InputError(f"the {role} array holds {obj.dtype} values, not numbers; give an "
                             "(N, 3) array of x, y, z")
        source = ArraySource(PointSet(obj, source=f"<{role} array>"))
    elif _is_paths(obj):
        if obj == "" or (isinstance(obj, (list, tuple)) and "" in obj):
            raise InputError(f"the {role} path is empty; give a file, a folder or a pattern")
        try:
            source = open_points(obj, format=format)  # type: ignore[arg-type]
        except InputError as exc:
            raise type(exc)(str(exc).replace("`format`", f"`{role}_format`")) from None
    else:
        raise InputError(_not_points(obj, role))
    refuse_geographic(source.info.crs_wkt, where=source.info.path, role=role)
    return source


def _not_points(obj: object, role: str) -> str:
    """What was given in place of points, and what to give."""
    kind = type(obj).__name__
    a = "an" if kind[0] in "aeiou" else "a"
    what = "an empty list" if isinstance(obj, (list, tuple)) and not obj else (
        f"{a} {kind} of lists (give np.asarray(points), an (N, 3) array)"
        if isinstance(obj, (list, tuple)) else "None" if obj is None
        else f"{a} {kind} ({str(obj)[:40]!r})")
    return (f"the {role + ' ' if role else ''}points are {what}; give a path, a list of paths, "
            "a PointSet or an (N, 3) array of x, y, z")


def _is_paths(obj: object) -> bool:
    return isinstance(obj, (str, os.PathLike)) or (
        isinstance(obj, (list, tuple)) and len(obj) > 0
        and all(isinstance(p, (str, os.PathLike)) for p in obj))


def read_points(
    paths: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    *,
    format: str | None = None,
) -> PointSet:
    """Read all points of a file (or tiles) into memory."""
    return open_points(paths, format=format).read()


def write_points(
    path: str | os.PathLike[str],
    xyz: np.ndarray,
    *,
    format: str | None = None,
    like: PointSource | None = None,
    crs_wkt: str | None = None,
) -> None:
    """Write points atomically; the format comes from ``format`` or the file name.

    For LAS/LAZ, ``like`` (an opened LAS source) lends its header: version, point format, scale,
    offset and CRS are kept where the new coordinates allow it.
    """
    p = Path(path)
    name = format
    if name is None:
        suffix = p.suffix.lower()
        name = next((f.name for f in FORMATS.values() if suffix in f.suffixes), None)
    if name is None or FORMATS.get(name) is None or FORMATS[name].write is None:
        writable = sorted(f"{f.name}" for f in FORMATS.values() if f.write is not None)
        raise InputError(
            f"{p}: cannot write points in this format; use a name ending in .las, .laz, .xyz, "
            f".txt, .csv or .ply (writable formats: {', '.join(writable)})"
        )
    xyz = np.asarray(xyz, dtype=np.float64)
    writer = FORMATS[name].write
    assert writer is not None
    if name == "las":
        writer(p, xyz, like=like, crs_wkt=crs_wkt)
    else:
        writer(p, xyz)
