"""What every reader returns, and atomic writing.

A :class:`PointSource` is an opened point file (or a set of tiles) that can tell its count, bounds
and CRS cheaply and hand out coordinates chunk by chunk, so the dense side is never loaded whole
when a grid or a crop is all that is needed.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import tempfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..crs import refuse_geographic
from ..errors import InputError, OutputError, TieregError
from ..points import PointSet, check_finite

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
        check_finite(points)
        refuse_geographic(points.crs_wkt, where=points.source)  # as a file in them would be
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


_KINDS = ((stat.S_ISFIFO, "FIFO (named pipe)"), (stat.S_ISCHR, "character device"),
          (stat.S_ISBLK, "block device"), (stat.S_ISSOCK, "socket"))


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "special file")


def check_input_file(path: str | os.PathLike[str]) -> os.stat_result:
    """The ``stat`` of an input that exists and is a file or a directory; :class:`InputError`
    saying what is wrong otherwise: missing, a broken or looping symbolic link, unreadable, or a
    FIFO or device (tiereg reads its inputs more than once, which a pipe cannot give). Nothing
    is opened, so a FIFO is refused rather than waited on."""
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        if os.path.islink(p):
            raise InputError(f"{p}: is a symbolic link to {os.readlink(p)}, which does not "
                             "exist; fix the link or give the file itself") from None
        raise InputError(f"{p}: no such file or directory; check the path") from None
    except OSError as exc:
        why = {errno.ELOOP: "is a loop of symbolic links (or a chain too long to follow); give "
                            "the file itself",
               errno.EACCES: "permission denied; make the file readable",
               errno.ENOTDIR: "a part of the path is a file, not a directory; check the path",
               errno.ENAMETOOLONG: "the path is too long; check it"}
        raise InputError(f"{p}: {why.get(exc.errno, f'cannot be read ({exc.strerror})')}"
                         ) from None
    if not (stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode)):
        raise InputError(f"{p}: is a {_kind(st.st_mode)}, not a regular file; tiereg reads its "
                         "inputs more than once - save the data to a file first")
    return st


# ----------------------------------------------------------------------------------- writing
@dataclass
class _Staged:
    """The outputs of an :func:`all_or_nothing` block: written, not yet renamed into place."""

    outputs: list[tuple[Path, Path]] = field(default_factory=list)  # (temporary, target)
    inputs: list[Path] = field(default_factory=list)  # every file read in the block


_staged: list[_Staged] = []  # the open block (a list: threads of one command share it)


def note_input(path: str | os.PathLike[str]) -> None:
    """Record a file read inside an :func:`all_or_nothing` block: no output may replace it."""
    if _staged:
        _staged[-1].inputs.append(Path(path))


def _top_missing(path: Path) -> Path | None:
    """The outermost folder of ``path`` (itself included) that does not exist yet."""
    top = None
    for p in (path, *path.parents):
        if os.path.lexists(p):
            break
        top = p
    return top


@contextlib.contextmanager
def all_or_nothing(*, folders: Iterable[str | os.PathLike[str]] = ()) -> Iterator[None]:
    """Write every output of the block, or none.

    Inside the block :func:`atomic_output` writes each file whole to its temporary name and
    leaves it there; when the block ends without an error, all are renamed into place (a rename
    neither fails for want of space nor leaves half a file), after checking that none of them
    replaces a file read in the block (:func:`check_not_input`). On any error - a full disk,
    bad input, an interrupt or a signal turned into an exception - every temporary file is
    removed, and so are those of ``folders`` (output folders the block may create) that did
    not exist before and are left empty. Blocks do not nest: an inner one joins the outer.
    """
    if _staged:
        yield
        return
    created = [top for top in (_top_missing(Path(f)) for f in folders) if top is not None]
    block = _Staged()
    _staged.append(block)
    try:
        yield
        _staged.pop()
        from . import check_not_input  # the one home of the check

        for _, target in block.outputs:
            check_not_input(target, block.inputs)
        for tmp, target in block.outputs:
            os.replace(tmp, target)
    except BaseException:
        if _staged and _staged[-1] is block:
            _staged.pop()
        for tmp, _ in block.outputs:
            with contextlib.suppress(OSError):
                tmp.unlink()
        for top in created:
            _remove_empty_tree(top)
        raise


def _remove_empty_tree(top: Path) -> None:
    """Remove ``top`` and the folders in it, if no file is anywhere below it."""
    if not top.is_dir() or top.is_symlink():
        return
    for root, dirs, files in os.walk(top, topdown=False):
        if files:
            return
        with contextlib.suppress(OSError):
            os.rmdir(root)


def _check_target(target: Path, parent: Path) -> None:
    """Refuse outputs that a rename onto ``target`` would destroy or that cannot be written."""
    try:
        st = os.stat(target)
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise OutputError(f"{target}: cannot be written ({exc.strerror}); choose another path"
                          ) from None
    if st is not None and stat.S_ISDIR(st.st_mode):
        raise OutputError(f"{target}: is a directory; give a file name for the output")
    if st is not None and not stat.S_ISREG(st.st_mode):
        raise OutputError(f"{target}: is a {_kind(st.st_mode)}, not a regular file; outputs are "
                          "written to a new file renamed onto the name, which would replace it - "
                          "give the name of a file")
    if not parent.is_dir():
        raise OutputError(
            f"{target}: the directory {parent} does not exist; create it or choose another path"
        )


DISK_FULL_BYTES = 1 << 20  # less free space than this (or 5 % of a small disk): full


def _disk_full(folder: Path) -> bool:
    try:
        fs = os.statvfs(folder)
    except OSError:
        return False
    free = (fs.f_bfree if os.geteuid() == 0 else fs.f_bavail) * fs.f_frsize
    return free < min(DISK_FULL_BYTES, fs.f_blocks * fs.f_frsize / 20)


def _write_error(target: Path, exc: BaseException) -> OutputError | None:
    """The one-line error for a failed write (a full disk, a failing device), or ``None`` for an
    exception that is not about writing (it is raised as it is)."""
    parent = target.parent if str(target.parent) else Path(".")
    code = getattr(exc, "errno", None)
    if code in (errno.ENOSPC, errno.EDQUOT) or (
            isinstance(exc, (OSError, RuntimeError)) and _disk_full(parent)):
        return OutputError(f"{target}: the disk is full; free some space or write elsewhere "
                           "(nothing was written)")
    if code == errno.EFBIG:
        return OutputError(f"{target}: the file is too large for this file system; write "
                           "elsewhere (nothing was written)")
    if isinstance(exc, OSError):
        why = exc.strerror or (str(exc).strip().splitlines() or [type(exc).__name__])[0][:160]
        return OutputError(f"{target}: writing failed ({why}); check the disk and the location "
                           "(nothing was written)")
    return None


def check_writable(path: str | os.PathLike[str]) -> None:
    """Fail early, before any work, if ``path`` could not be written; creates nothing."""
    with atomic_output(path, commit=False):
        pass


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike[str], *, commit: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success.

    A failed write leaves no partial file behind. Raises :class:`OutputError` when the target
    directory does not exist or cannot be written, when ``path`` is a directory, a device or a
    FIFO (a rename would replace it), and when writing fails (a full disk). With
    ``commit=False`` the temporary file is always removed (a dry run that proves the location
    is writable). Inside :func:`all_or_nothing` the rename waits for the end of the block.
    """
    target = Path(path)
    parent = target.parent if str(target.parent) else Path(".")
    _check_target(target, parent)
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=parent)
    except OSError as exc:
        raise OutputError(
            f"{target}: cannot write in {parent} ({exc.strerror}); choose a writable location"
        ) from None
    os.close(fd)
    tmp = Path(tmp_name)
    kept = False
    try:
        try:
            yield tmp
            if commit:
                os.chmod(tmp, 0o666 & ~_umask())  # mkstemp made it 0600; use the user's umask
                if _staged:
                    _staged[-1].outputs.append((tmp, target))
                    kept = True
                else:
                    os.replace(tmp, target)
        except TieregError:
            raise
        except Exception as exc:
            error = _write_error(target, exc)
            if error is None:
                raise
            raise error from None
    finally:
        if not kept:
            with contextlib.suppress(OSError):
                tmp.unlink()


def write_text_atomic(path: str | os.PathLike[str], text: str) -> None:
    """Write a small text file atomically."""
    with atomic_output(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


@contextlib.contextmanager
def open_input(path: Path, mode: str = "rb", **kw: Any) -> Iterator[Any]:
    """``open(path, mode)`` for reading, with OS errors turned into one-line :class:`InputError`
    (:func:`check_input_file`); a FIFO or a device is refused, not opened."""
    if stat.S_ISDIR(check_input_file(path).st_mode):
        raise InputError(f"{path}: is a directory; give the point file itself")
    note_input(path)
    try:
        with open(path, mode, **kw) as fh:
            yield fh
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
