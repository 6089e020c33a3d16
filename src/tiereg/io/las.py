"""LAS/LAZ (ASPRS LAS 1.0-1.4, any point data record format) through laspy with lazrs.

Reading is chunked: :class:`LasSource` reads headers on opening and points only through
:meth:`LasSource.chunks`, one bounded chunk at a time, so memory does not grow with the file.
Several files (tiles) form one source.
"""

from __future__ import annotations

import io
import math
import os
import struct
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

from ..crs import crs_label, same_crs
from ..errors import FormatError, InputError
from .base import (
    DEFAULT_CHUNK,
    PointSource,
    SourceInfo,
    atomic_output,
    check_input_file,
    note_input,
    open_input,
)


def _laspy():  # laspy is a hard dependency; imported lazily to keep `import tiereg` light
    import laspy

    return laspy


def _meets(header, box: tuple[float, float, float, float]) -> bool:
    """Whether a file's header bounds meet ``box`` in plan."""
    (x0, y0, _), (x1, y1, _) = header.mins, header.maxs
    return not (x1 < box[0] or x0 > box[2] or y1 < box[1] or y0 > box[3])


def laz_backend():
    laspy = _laspy()
    for b in (laspy.LazBackend.LazrsParallel, laspy.LazBackend.Lazrs):
        if b.is_available():
            return b
    return None


# LAS 1.x public header block: the size of each version's, and the fields checked here
_HEADER_SIZE = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375}
_VLR_HEADER, _EVLR_HEADER = 54, 60
MAX_SCALE = 1000.0  # file units per integer step; coarser than this is no survey
MAX_RECORD_BYTES = 4 << 20  # VLRs read at most (they hold kilobytes); EVLRs read whole at most
_FIX = "the file is corrupt or truncated - re-export or re-download it"
_CORRUPT = "the file is corrupt - re-export it"


def check_header(path: Path) -> list[bytes] | None:
    """Refuse a LAS/LAZ file whose header does not fit the file, before laspy reads it.

    laspy trusts the header's counts: 2^32 - 1 VLRs after a short header take it hours and
    gigabytes, and a LAZ chunk table announcing 2^32 chunks asks for 64 GB. Checked here
    against the file's size: header size, offset to the points, every VLR and EVLR, the LAZ
    chunk table, and scales, offsets and bounds (finite; scales positive and at most
    :data:`MAX_SCALE`). VLRs may take :data:`MAX_RECORD_BYTES` in all (they hold kilobytes).

    Returns ``None``, or, when the EVLRs take more than :data:`MAX_RECORD_BYTES` (waveforms),
    the raw bytes of those that may hold a CRS: only they are read.
    """
    size = check_input_file(path).st_size
    with open_input(path) as fh:
        head = fh.read(375)
        if len(head) < 227:
            raise FormatError(f"{path}: the LAS header is cut short ({len(head)} bytes); {_FIX}")
        major, minor = head[24], head[25]
        header_size, offset, n_vlrs = struct.unpack_from("<HII", head, 94)
        if major != 1 or not _HEADER_SIZE.get(minor, 375) <= header_size <= min(size, offset):
            raise FormatError(f"{path}: the LAS header is not valid (version {major}.{minor}, "
                              f"header size {header_size}, point data at {offset}); {_FIX}")
        if offset > size:
            raise FormatError(f"{path}: the point data would start at byte {offset}, past the "
                              f"end of the file ({size} bytes); {_FIX}")
        if offset - header_size > MAX_RECORD_BYTES:
            raise FormatError(f"{path}: its VLRs would take {offset - header_size:,} bytes, more "
                              f"than the {MAX_RECORD_BYTES:,} tiereg reads (they hold kilobytes); "
                              f"{_CORRUPT}")
        _check_records(path, fh, header_size, offset, n_vlrs, extended=False)
        count = struct.unpack_from("<I", head, 107)[0]
        crs_evlrs = None
        if minor >= 4 and len(head) >= 255:
            first, n_evlrs, count64 = struct.unpack_from("<QIQ", head, 235)
            count = count or count64
            if n_evlrs:
                if not offset <= first <= size:
                    raise FormatError(f"{path}: the extended VLRs would start past the end of "
                                      f"the file; {_FIX}")
                crs = _check_records(path, fh, first, size, n_evlrs, extended=True)
                if size - first > MAX_RECORD_BYTES:
                    crs_evlrs = crs
        _check_numbers(path, head)
        if head[104] & 0xC0 and count:  # the compressed bits of the point format: LAZ
            record = struct.unpack_from("<H", head, 105)[0]
            _check_chunk_table(path, fh, offset, size, max_chunks=min(
                count, (size - offset) // max(record, 1)))
    return crs_evlrs


def _check_records(path: Path, fh, start: int, end: int, count: int, *,
                   extended: bool) -> list[bytes]:
    """Every one of ``count`` (E)VLRs, header and payload, lies between ``start`` and ``end``.
    Returns the raw records of a CRS (user ID :data:`CRS_VLR_USER`) of up to 1 MB."""
    what = "extended VLRs (EVLRs)" if extended else "VLRs"
    step = _EVLR_HEADER if extended else _VLR_HEADER
    if count * step > end - start:
        raise FormatError(f"{path}: the header announces {count} {what}, more than the "
                          f"{end - start} bytes for them can hold; {_FIX}")
    crs: list[bytes] = []
    pos = start
    for _ in range(count):  # at most (end - start) / step records
        fh.seek(pos)
        head = fh.read(step)
        length = struct.unpack_from("<Q" if extended else "<H", head, 20)[0]
        if pos + step + length > end:
            raise FormatError(f"{path}: one of its {what} runs past the bytes it has; {_FIX}")
        if head[2:18].rstrip(b"\0") == CRS_VLR_USER.encode() and length <= 1 << 20:
            crs.append(head + fh.read(length))
        pos += step + length
    return crs


def _check_numbers(path: Path, head: bytes) -> None:
    scales = struct.unpack_from("<3d", head, 131)
    offsets = struct.unpack_from("<3d", head, 155)
    bounds = struct.unpack_from("<6d", head, 179)
    if not all(math.isfinite(v) and 0 < v <= MAX_SCALE for v in scales):
        raise FormatError(f"{path}: the header's scale factors {list(scales)} are not usable "
                          f"(positive numbers of at most {MAX_SCALE:g} are); {_CORRUPT}")
    if not all(map(math.isfinite, offsets)):
        raise FormatError(f"{path}: the header's offsets {list(offsets)} are not finite; "
                          f"{_CORRUPT}")
    if not all(map(math.isfinite, bounds)):
        raise FormatError(f"{path}: the header's bounds {list(bounds)} are not finite; "
                          f"{_CORRUPT}")


def _check_chunk_table(path: Path, fh, start: int, size: int, *, max_chunks: int) -> None:
    """The LAZ chunk table (its offset is the first 8 bytes of the point data, or, written
    as -1, the last 8 of the file) lies in the file and counts at most ``max_chunks`` chunks
    (each holds a point, and its first point uncompressed)."""
    fh.seek(start)
    raw = fh.read(8)
    table = struct.unpack("<q", raw)[0] if len(raw) == 8 else size
    if table == -1 and size >= 16:
        fh.seek(size - 8)
        table = struct.unpack("<q", fh.read(8))[0]
    if not start + 8 <= table <= size - 8:
        raise FormatError(f"{path}: truncated LAZ file (its chunk table would be at byte "
                          f"{table}, the file has {size}); re-export or re-download it")
    fh.seek(table + 4)
    chunks = struct.unpack("<I", fh.read(4))[0]
    if chunks > max_chunks:
        raise FormatError(f"{path}: the LAZ chunk table announces {chunks} chunks, more than "
                          f"the points and bytes of the file allow ({max_chunks}); {_FIX}")


def open_header(path: Path):
    laspy = _laspy()
    crs_evlrs = check_header(path)
    note_input(path)
    try:
        with laspy.open(path, mode="r", laz_backend=laz_backend(),
                        read_evlrs=crs_evlrs is None) as reader:
            header = reader.header
        if crs_evlrs is not None:  # large EVLRs (waveforms) stay on disk; their CRS is read
            from laspy.vlrs.vlrlist import VLRList

            header.evlrs = VLRList.read_from(io.BytesIO(b"".join(crs_evlrs)), len(crs_evlrs),
                                             extended=True)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file; check the path") from None
    except read_errors() as exc:
        raise FormatError(
            f"{path}: not a readable LAS/LAZ file ({short_error(exc)}); the file is corrupt or "
            "truncated - re-export or re-download it"
        ) from None
    if header.point_count and not header.are_points_compressed:
        need = header.offset_to_point_data + header.point_count * header.point_format.size
        have = path.stat().st_size
        if have < need:
            raise FormatError(
                f"{path}: truncated LAS file ({have} bytes, the header announces {need}); "
                "re-export or re-download it"
            )
    return header


def read_errors() -> tuple[type[BaseException], ...]:
    """The exceptions laspy and its LAZ backend raise on corrupt or truncated data."""
    laspy = _laspy()
    errors: list[type[BaseException]] = [laspy.errors.LaspyException, ValueError, EOFError,
                                         OSError]
    try:
        import lazrs

        errors.append(lazrs.LazrsError)
    except (ImportError, AttributeError):
        pass
    return tuple(errors)


def short_error(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:160]


def crs_wkt_of(header) -> str | None:
    try:
        crs = header.parse_crs()
    except Exception:  # a malformed CRS record must not stop a registration
        return None
    return crs.to_wkt() if crs is not None else None


class LasSource(PointSource):
    """One or several LAS/LAZ files read as one point source."""

    def __init__(self, paths: Sequence[str | os.PathLike[str]]):
        self.paths = [Path(p) for p in paths]
        if not self.paths:
            raise InputError("no LAS/LAZ file given")
        self.headers = [open_header(p) for p in self.paths]
        count = int(sum(h.point_count for h in self.headers))
        lo = np.min([h.mins for h in self.headers], axis=0)
        hi = np.max([h.maxs for h in self.headers], axis=0)
        first = self.headers[0]
        wkts = [crs_wkt_of(h) for h in self.headers]
        crs_wkt = next((w for w in wkts if w), None)  # tiles without a CRS record take it
        for path, wkt in zip(self.paths, wkts):
            if not same_crs(crs_wkt, wkt):
                raise InputError(
                    f"{path}: its CRS ({crs_label(wkt)}) is not that of the other tiles "
                    f"({crs_label(crs_wkt)}); reproject the tiles to one CRS first")
        label = str(self.paths[0]) if len(self.paths) == 1 else (
            f"{self.paths[0].parent}/ ({len(self.paths)} tiles)"
        )
        self.info = SourceInfo(
            path=label,
            format="las",
            count=count,
            bounds=(tuple(map(float, lo)), tuple(map(float, hi))),  # type: ignore[arg-type]
            crs_wkt=crs_wkt,
            details={
                "version": str(first.version),
                "point_format": int(first.point_format.id),
                "scales": [float(v) for v in first.scales],
                "offsets": [float(v) for v in first.offsets],
                "compressed": bool(first.are_points_compressed),
                "files": len(self.paths),
            },
        )

    def chunks(
        self,
        chunk_size: int = DEFAULT_CHUNK,
        *,
        keep: Callable[[object], np.ndarray] | None = None,
        box: tuple[float, float, float, float] | None = None,
    ) -> Iterator[np.ndarray]:
        """Yield ``(n, 3)`` float64 coordinates chunk by chunk.

        ``keep`` optionally takes a laspy point record chunk and returns a boolean mask of the
        points to keep (e.g. first returns only). ``box`` ``(xmin, ymin, xmax, ymax)``: the
        files whose header bounds do not meet it are not read (the points of those that do
        are all given).
        """
        for arr in self._records(chunk_size, box=box):
            xyz = np.empty((len(arr), 3))
            xyz[:, 0] = arr.x
            xyz[:, 1] = arr.y
            xyz[:, 2] = arr.z
            if keep is not None:
                xyz = xyz[np.asarray(keep(arr), dtype=bool)]
            yield xyz

    def _records(self, chunk_size: int, *,
                 box: tuple[float, float, float, float] | None = None) -> Iterator:
        laspy = _laspy()
        for path, header in zip(self.paths, self.headers):
            if box is not None and not _meets(header, box):
                continue
            # records of up to 64 kB (extra bytes): a chunk's buffer stays within CHUNK_BYTES
            n = max(1, min(chunk_size, CHUNK_BYTES // header.point_format.size))
            try:
                with laspy.open(path, mode="r", laz_backend=laz_backend(),
                                read_evlrs=False) as reader:
                    for arr in reader.chunk_iterator(n):
                        yield arr
            except read_errors() as exc:
                raise FormatError(
                    f"{path}: reading the points failed ({short_error(exc)}); the file is "
                    "corrupt or truncated - re-export or re-download it"
                ) from None


CHUNK_BYTES = 256 << 20
CRS_VLR_USER = "LASF_Projection"  # the user ID of the records that hold a CRS (GeoTIFF keys, WKT)
SOURCE_CRS = "source"  # as a ``crs_wkt`` argument: the source's own CRS records, as they are


def _header_like(src_header, *, crs_wkt: str | None = SOURCE_CRS):
    """A new header with the source's version, point format, scales, offsets and VLRs; its CRS
    records are kept (:data:`SOURCE_CRS`), or replaced by ``crs_wkt`` (``None``: no CRS).

    laspy writes LAS 1.1-1.4; a LAS 1.0 source is written as 1.1, whose records are the same.
    """
    laspy = _laspy()
    version = "1.1" if str(src_header.version) == "1.0" else src_header.version
    header = laspy.LasHeader(version=version, point_format=src_header.point_format)
    header.scales = np.array(src_header.scales)
    header.offsets = np.array(src_header.offsets)
    for vlr in src_header.vlrs:
        if crs_wkt == SOURCE_CRS or vlr.user_id != CRS_VLR_USER:
            header.vlrs.append(vlr)
    if crs_wkt not in (None, SOURCE_CRS):
        _add_crs(header, crs_wkt)
    return header


def _add_crs(header, crs_wkt: str) -> None:
    import pyproj

    header.add_crs(pyproj.CRS.from_wkt(crs_wkt))


def _fit_offsets(header, lo: np.ndarray, hi: np.ndarray) -> None:
    """Keep the header's scales; move the offsets only if the coordinates would overflow int32."""
    scales = np.asarray(header.scales, dtype=np.float64)
    offsets = np.asarray(header.offsets, dtype=np.float64)
    limit = 2**31 - 2
    ok = np.all(np.abs((lo - offsets) / scales) < limit) and np.all(
        np.abs((hi - offsets) / scales) < limit
    )
    if not ok:
        centre = (lo + hi) / 2
        header.offsets = np.round(centre / scales) * scales
        if np.any((hi - lo) / scales / 2 >= limit):
            raise InputError(
                "the transformed points span more than the LAS integer range at the source "
                f"scale {scales.tolist()}; write to .ply or .xyz instead"
            )


def _set_coordinates(arr, xyz: np.ndarray, header, path: Path) -> None:
    """Store ``xyz`` in a point record as the integers of ``header``'s scales and offsets; a
    point the integers cannot hold (the file's points lie outside its header's bounds, from
    which the offsets were chosen) is an error, not a wrapped-around coordinate."""
    scales = np.asarray(header.scales, dtype=np.float64)
    offsets = np.asarray(header.offsets, dtype=np.float64)
    ints = np.rint((xyz - offsets) / scales)
    if not np.all(np.abs(ints) <= 2**31 - 1):  # NaN fails too
        raise FormatError(
            f"{path}: some points lie far outside the bounds its header declares, so their "
            "transformed coordinates do not fit the LAS integers; fix the header (e.g. rewrite "
            "the file with PDAL or lasinfo -repair) or write to .ply or .xyz")
    for k, name in enumerate("XYZ"):
        arr[name] = ints[:, k].astype(np.int32)
    arr.scales, arr.offsets = scales, offsets


def write_las(
    path: str | os.PathLike[str],
    xyz: np.ndarray,
    *,
    like: PointSource | None = None,
    crs_wkt: str | None = None,
) -> None:
    """Write ``xyz`` to LAS or LAZ (by suffix), atomically.

    With ``like`` (a :class:`LasSource`), its version, point format, scales and CRS are kept
    (the CRS unless ``crs_wkt`` names another); without it, LAS 1.4 point format 6 with 1 mm
    scales is written, in ``crs_wkt``.
    """
    laspy = _laspy()
    path = Path(path)
    xyz = np.asarray(xyz, dtype=np.float64)
    if isinstance(like, LasSource):
        header = _header_like(like.headers[0], crs_wkt=crs_wkt or SOURCE_CRS)
    else:
        header = laspy.LasHeader(version="1.4", point_format=6)
        header.scales = np.array([0.001, 0.001, 0.001])
        header.offsets = np.floor(xyz.min(axis=0)) if len(xyz) else np.zeros(3)
        if crs_wkt:
            _add_crs(header, crs_wkt)
    if len(xyz):
        _fit_offsets(header, xyz.min(axis=0), xyz.max(axis=0))
    data = laspy.LasData(header)
    data.x = xyz[:, 0]
    data.y = xyz[:, 1]
    data.z = xyz[:, 2]
    compress = path.suffix.lower() == ".laz"
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as fh:
            data.write(fh, do_compress=compress, laz_backend=laz_backend() if compress else None)


def transform_las(
    source: LasSource,
    out_path: str | os.PathLike[str],
    apply: Callable[[np.ndarray], np.ndarray],
    *,
    chunk_size: int = DEFAULT_CHUNK,
    progress: Callable[[int], None] | None = None,
    crs_wkt: str | None = SOURCE_CRS,
) -> None:
    """Stream every point of ``source`` through ``apply`` into a new LAS/LAZ file, in the
    source's CRS or in ``crs_wkt`` (``None``: no CRS; the output is in a frame none describes).

    All point attributes are kept; the header keeps version, point format, scales, VLRs and CRS,
    with offsets moved only if needed. Memory stays at one chunk. Only a single-file source can be
    rewritten this way.
    """
    laspy = _laspy()
    if len(source.paths) != 1:
        raise InputError("apply rewrites one LAS/LAZ file at a time; run it once per tile")
    out_path = Path(out_path)
    src_header = source.headers[0]
    lo, hi = np.array(src_header.mins), np.array(src_header.maxs)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    moved = apply(corners)
    header = _header_like(src_header, crs_wkt=crs_wkt)
    _fit_offsets(header, moved.min(axis=0), moved.max(axis=0))
    compress = out_path.suffix.lower() == ".laz"
    with atomic_output(out_path) as tmp:
        with laspy.open(tmp, mode="w", header=header, do_compress=compress,
                        laz_backend=laz_backend() if compress else None) as writer:
            for arr in source._records(chunk_size):
                xyz = np.column_stack([arr.x, arr.y, arr.z])
                _set_coordinates(arr, apply(xyz), header, source.paths[0])
                writer.write_points(arr)
                if progress is not None:
                    progress(len(arr))
