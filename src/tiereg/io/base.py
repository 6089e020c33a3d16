"""What every reader returns, and atomic writing.

A :class:`PointSource` is an opened point file (or a set of tiles) that can tell its count, bounds
and CRS cheaply and hand out coordinates chunk by chunk, so the dense side is never loaded whole
when a grid or a crop is all that is needed.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError, OutputError
from ..points import PointSet

DEFAULT_CHUNK = 2_000_000


@dataclass(frozen=True)
class SourceInfo:
    """Cheap facts about a point source, known without reading all points."""

    path: str
    format: str
    count: int
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    crs_wkt: str | None = field(default=None, repr=False)
    details: dict[str, Any] = field(default_factory=dict)


class PointSource:
    """A point file (or several) opened for reading; subclasses implement :meth:`chunks`."""

    info: SourceInfo

    def chunks(self, chunk_size: int = DEFAULT_CHUNK) -> Iterator[np.ndarray]:
        """Yield ``(n, 3)`` float64 arrays until all points were given."""
        raise NotImplementedError

    def read(self) -> PointSet:
        """All points at once (use for the sparse side or small files)."""
        parts = list(self.chunks())
        xyz = np.concatenate(parts) if parts else np.empty((0, 3))
        return PointSet(xyz, source=self.info.path, crs_wkt=self.info.crs_wkt)


class ArraySource(PointSource):
    """A point set already in memory, seen through the :class:`PointSource` interface."""

    def __init__(self, points: PointSet, *, format: str = "array", details: dict | None = None):
        self._points = points
        lo, hi = points.bounds if len(points) else (np.zeros(3), np.zeros(3))
        self.info = SourceInfo(
            path=points.source,
            format=format,
            count=len(points),
            bounds=(tuple(map(float, lo)), tuple(map(float, hi))),  # type: ignore[arg-type]
            crs_wkt=points.crs_wkt,
            details=details or {},
        )

    def chunks(self, chunk_size: int = DEFAULT_CHUNK) -> Iterator[np.ndarray]:
        xyz = self._points.xyz
        for start in range(0, len(xyz), chunk_size):
            yield xyz[start : start + chunk_size]

    def read(self) -> PointSet:
        return self._points


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def check_writable(path: str | os.PathLike[str]) -> None:
    """Fail early, before any work, if ``path`` could not be written; creates nothing."""
    with atomic_output(path, commit=False):
        pass


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike[str], *, commit: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success.

    A failed write leaves no partial file behind. Raises :class:`OutputError` when the target
    directory does not exist or cannot be written. With ``commit=False`` the temporary file is
    always removed (a dry run that proves the location is writable).
    """
    target = Path(path)
    parent = target.parent if str(target.parent) else Path(".")
    if target.is_dir():
        raise OutputError(f"{target}: is a directory; give a file name for the output")
    if not parent.is_dir():
        raise OutputError(
            f"{target}: the directory {parent} does not exist; create it or choose another path"
        )
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=parent)
    except OSError as exc:
        raise OutputError(
            f"{target}: cannot write in {parent} ({exc.strerror}); choose a writable location"
        ) from None
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        if commit:
            os.chmod(tmp, 0o666 & ~_umask())  # mkstemp made it 0600; use the user's umask
            os.replace(tmp, target)
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()


def write_text_atomic(path: str | os.PathLike[str], text: str) -> None:
    """Write a small text file atomically."""
    with atomic_output(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


@contextlib.contextmanager
def open_input(path: Path, mode: str = "rb", **kw: Any) -> Iterator[Any]:
    """``open(path, mode)`` for reading, with OS errors turned into one-line :class:`InputError`."""
    try:
        with open(path, mode, **kw) as fh:
            yield fh
    except IsADirectoryError:
        raise InputError(f"{path}: is a directory; give the point file itself") from None
    except FileNotFoundError:
        raise InputError(f"{path}: no such file; check the path") from None
    except PermissionError:
        raise InputError(f"{path}: permission denied; make the file readable") from None


def read_bytes(path: Path) -> bytes:
    """The whole file, or :class:`InputError` naming it when it cannot be read."""
    with open_input(path) as fh:
        return fh.read()


def format_rows(xyz: np.ndarray, *, sep: str = " ", prefix: Iterable[str] | None = None) -> str:
    """``x y z`` lines (newline-terminated) in the shortest round-trip decimal form."""
    if len(xyz) == 0:
        return ""
    it = iter(map(repr, np.asarray(xyz, dtype=np.float64).ravel().tolist()))
    rows: Iterable[str] = map(sep.join, zip(it, it, it))
    if prefix is not None:
        rows = map(sep.join, zip(prefix, rows))
    return "\n".join(rows) + "\n"


def check_xyz(path: str | os.PathLike[str], xyz: np.ndarray) -> np.ndarray:
    arr = np.asarray(xyz, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(
            f"{path}: points to write must be an (N, 3) array of x, y, z, got shape {arr.shape}"
        )
    return arr


def freeze_arrays(obj: object, *names: str) -> None:
    """Store ``obj``'s array fields as read-only ``(M, 3)`` float64 (for frozen dataclasses)."""
    for name in names:
        arr = np.array(getattr(obj, name), dtype=np.float64).reshape(-1, 3)
        arr.setflags(write=False)
        object.__setattr__(obj, name, arr)


Sniffer = Callable[[Path, bytes], bool]
