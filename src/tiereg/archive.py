"""A lidar archive as a reference: many LAS/LAZ/COPC tiles indexed once by their headers.

:class:`TileIndex` reads each tile's header (bounds, count, CRS, whether it is COPC) once and
caches the facts in a JSON file keyed by path, size and modification time, so an archive of
thousands of tiles is opened again without touching them. Points are read only where needed:
:meth:`TileIndex.tiles_near` lists the tiles whose header bounds meet a box, and
:meth:`TileIndex.points_in` reads the points inside a box from those tiles alone; a COPC tile is
read by a spatial query of its octree (laspy's ``CopcReader``), and with ``resolution`` only its
coarse levels, which serve coarse grids.

:class:`ArchiveSource` is a :class:`~tiereg.io.las.LasSource` over the whole archive or one
window of it: a :class:`~tiereg.reference.Reference` made on it (its fine stage, its report)
reads the tiles that meet the window and nothing else.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .crs import crs_label, same_crs
from .errors import FormatError, InputError
from .io.base import DEFAULT_CHUNK, SourceInfo, write_text_atomic
from .io.las import LasSource, crs_wkt_of, laz_backend, open_header, read_errors, short_error
from .reference import surface_mask

log = logging.getLogger(__name__)

INDEX_VERSION = 1
Box = tuple[float, float, float, float]  # xmin, ymin, xmax, ymax


@dataclass(frozen=True)
class Tile:
    """What a tile's header says, and the file's identity (size, modification time)."""

    path: str  # absolute
    size: int
    mtime_ns: int
    count: int
    mins: tuple[float, float, float]
    maxs: tuple[float, float, float]
    crs_wkt: str | None
    copc: bool
    point_format: int

    @property
    def box(self) -> Box:
        return (self.mins[0], self.mins[1], self.maxs[0], self.maxs[1])

    @property
    def spacing(self) -> float:
        """Mean point spacing: the square root of the header bounds' area per point."""
        area = (self.maxs[0] - self.mins[0]) * (self.maxs[1] - self.mins[1])
        return math.sqrt(max(area, 1e-12) / max(self.count, 1))

    def meets(self, box: Box) -> bool:
        """Whether the tile's header bounds meet ``box`` (edges included)."""
        return not (self.maxs[0] < box[0] or self.mins[0] > box[2]
                    or self.maxs[1] < box[1] or self.mins[1] > box[3])

    def share_in(self, box: Box) -> float:
        """The share of the tile's plan area inside ``box`` (1 for a tile of no area inside)."""
        w, h = self.maxs[0] - self.mins[0], self.maxs[1] - self.mins[1]
        ix = min(self.maxs[0], box[2]) - max(self.mins[0], box[0])
        iy = min(self.maxs[1], box[3]) - max(self.mins[1], box[1])
        if ix < 0 or iy < 0:
            return 0.0
        if w <= 0 or h <= 0:
            return 1.0
        return float(min(1.0, max(ix, 0.0) * max(iy, 0.0) / (w * h)))


def _xyz(records) -> np.ndarray:
    xyz = np.empty((len(records), 3))
    xyz[:, 0] = records.x
    xyz[:, 1] = records.y
    xyz[:, 2] = records.z
    return xyz


def _is_copc(header) -> bool:
    return any(getattr(v, "user_id", "") == "copc" for v in header.vlrs)


def _read_tile(path: Path) -> Tile:
    header = open_header(path)
    st = path.stat()
    return Tile(str(path), st.st_size, st.st_mtime_ns, int(header.point_count),
                tuple(map(float, header.mins)), tuple(map(float, header.maxs)),  # type: ignore
                crs_wkt_of(header), _is_copc(header), int(header.point_format.id))


def _selection():
    """Decompress only what gridding reads: coordinates, returns, classification, flags."""
    import laspy

    s = laspy.DecompressionSelection
    return s.XY_RETURNS_CHANNEL | s.Z | s.CLASSIFICATION | s.FLAGS


def _one_thread_backend():
    """lazrs on one thread: a tile is a task, and the tasks are the parallelism (a parallel
    decoder's threads would compete with the other tasks for the cores)."""
    import laspy

    b = laspy.LazBackend.Lazrs
    return b if b.is_available() else laz_backend()


def tile_chunks(tile: Tile, *, keep: Callable[[object], np.ndarray] | None = None,
                box: Box | None = None, resolution: float | None = None,
                chunk_size: int = DEFAULT_CHUNK) -> Iterator[np.ndarray]:
    """The ``(n, 3)`` points of one tile, chunk by chunk, as :meth:`LasSource.chunks` gives them
    (the same chunks, so grids sum alike); ``keep`` filters records (:func:`surface_mask`).

    With ``box``, a COPC tile is read by a spatial query of its octree and only points inside
    ``box`` are kept (any tile); with ``resolution``, a COPC tile gives only the octree levels
    down to that point spacing (a coarse grid's share of the points; other tiles give all).
    """
    if not (tile.copc and (box is not None or resolution is not None)):
        yield from _filtered(_records(tile, chunk_size), keep, box)
        return
    yield from _filtered(_copc_query(tile, box, resolution), keep, box)


def tile_columns(tile: Tile, *, keep: Callable[[object], np.ndarray] | None = None,
                 resolution: float | None = None, chunk_size: int = DEFAULT_CHUNK,
                 ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]]:
    """The points of one tile as ``(x, y, z, kept)`` columns, chunk by chunk as
    :func:`tile_chunks` reads them (fresh arrays: change them in place); ``kept``: what ``keep``
    keeps (None without), left to the caller to apply with its own selection. With
    ``resolution`` coarser than the tile's point spacing, a COPC tile gives only its octree
    levels down to that spacing, in one chunk; other tiles give all their points."""
    levels = tile.copc and resolution is not None and resolution > tile.spacing
    chunks = _copc_query(tile, None, resolution) if levels else _records(tile, chunk_size)
    for records in chunks:
        kept = None if keep is None else np.asarray(keep(records), dtype=bool)
        yield (np.asarray(records.x, dtype=np.float64), np.asarray(records.y, dtype=np.float64),
               np.asarray(records.z, dtype=np.float64), kept)


def _copc_query(tile: Tile, box: Box | None, resolution: float | None) -> Iterator:
    """The laspy records of a COPC tile's octree nodes that meet ``box`` (all without), of its
    levels down to ``resolution`` (all without), as one chunk."""
    import laspy

    try:
        with laspy.CopcReader.open(tile.path, decompression_selection=_selection()) as reader:
            bounds = None if box is None else laspy.copc.Bounds(  # z: the whole tile
                np.array([box[0], box[1], tile.mins[2] - 1.0]),
                np.array([box[2], box[3], tile.maxs[2] + 1.0]))
            yield reader.query(bounds=bounds, resolution=resolution)
    except read_errors() as exc:
        raise _read_failed(tile, exc) from None


def _records(tile: Tile, chunk_size: int) -> Iterator:
    """The laspy record chunks of a whole tile, decoding only what gridding reads."""
    import laspy

    try:
        with laspy.open(tile.path, mode="r", laz_backend=_one_thread_backend(),
                        decompression_selection=_selection()) as reader:
            yield from reader.chunk_iterator(chunk_size)
    except read_errors() as exc:
        raise _read_failed(tile, exc) from None


def _read_failed(tile: Tile, exc: BaseException) -> FormatError:
    return FormatError(f"{Path(tile.path)}: reading the points failed ({short_error(exc)}); the "
                       "file is corrupt or truncated - re-export or re-download it")


def _filtered(chunks, keep, box: Box | None) -> Iterator[np.ndarray]:
    for records in chunks:
        xyz = _xyz(records)
        if keep is not None:
            xyz = xyz[np.asarray(keep(records), dtype=bool)]
        if box is not None:
            xyz = xyz[(xyz[:, 0] >= box[0]) & (xyz[:, 0] <= box[2])
                      & (xyz[:, 1] >= box[1]) & (xyz[:, 1] <= box[3])]
        yield xyz


class TileIndex:
    """The tiles of an archive by their headers (see the module docstring)."""

    def __init__(self, tiles: Sequence[Tile]):
        if not tiles:
            raise InputError("the archive holds no LAS/LAZ tile; give tiles, a folder or a glob")
        self.tiles = tuple(tiles)
        crs = next((t.crs_wkt for t in self.tiles if t.crs_wkt), None)
        for t in self.tiles:
            if not same_crs(crs, t.crs_wkt):
                raise InputError(f"{t.path}: its CRS ({crs_label(t.crs_wkt)}) is not that of the "
                                 f"other tiles ({crs_label(crs)}); reproject the tiles to one "
                                 "CRS first")
        self.crs_wkt = crs
        self._mins = np.array([t.mins for t in self.tiles])
        self._maxs = np.array([t.maxs for t in self.tiles])

    @classmethod
    def build(cls, paths: str | os.PathLike[str] | Sequence[str | os.PathLike[str]], *,
              cache: str | os.PathLike[str] | None = None) -> TileIndex:
        """Index tiles (files, folders of ``.las``/``.laz``, globs); headers already in
        ``cache`` (same path, size and modification time) are not read again, and the cache is
        rewritten when anything was read."""
        from .io import expand_paths

        files = [Path(os.path.abspath(p)) for p in expand_paths(paths)]
        known = _load_cache(cache)
        tiles, read = [], 0
        for f in files:
            try:
                st = f.stat()
            except FileNotFoundError:
                raise InputError(f"{f}: no such file; check the path") from None
            hit = known.get(str(f))
            if hit is not None and hit.size == st.st_size and hit.mtime_ns == st.st_mtime_ns:
                tiles.append(hit)
                continue
            tiles.append(_read_tile(f))
            read += 1
        if cache is not None and (read or len(known) != len(tiles)):
            write_text_atomic(cache, json.dumps({"version": INDEX_VERSION,
                                                 "tiles": [asdict(t) for t in tiles]}))
        log.info("tile index: %d tiles, %d headers read", len(tiles), read)
        return cls(tiles)

    @property
    def count(self) -> int:
        return int(sum(t.count for t in self.tiles))

    @property
    def bounds(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        return (tuple(map(float, self._mins.min(axis=0))),  # type: ignore[return-value]
                tuple(map(float, self._maxs.max(axis=0))))

    @property
    def paths(self) -> tuple[str, ...]:
        return tuple(t.path for t in self.tiles)

    def tiles_near(self, box: Box, *, margin: float = 0.0) -> list[Tile]:
        """The tiles whose header bounds meet ``box`` grown by ``margin``, in index order."""
        b = (box[0] - margin, box[1] - margin, box[2] + margin, box[3] + margin)
        hit = ((self._maxs[:, 0] >= b[0]) & (self._mins[:, 0] <= b[2])
               & (self._maxs[:, 1] >= b[1]) & (self._mins[:, 1] <= b[3]))
        return [self.tiles[i] for i in np.flatnonzero(hit)]

    def points_in(self, box: Box, *, surface: bool = True, first_only: bool = False,
                  resolution: float | None = None) -> np.ndarray:
        """The points inside ``box`` (edges included), read from the tiles that meet it only;
        ``surface``: as :mod:`tiereg.reference` grids them (:func:`surface_mask`)."""
        keep = (lambda r: surface_mask(r, first_only)) if surface else None
        parts = [c for t in self.tiles_near(box)
                 for c in tile_chunks(t, keep=keep, box=box, resolution=resolution)]
        return np.concatenate(parts) if parts else np.empty((0, 3))

    def source(self, box: Box | None = None) -> ArchiveSource:
        """The archive (or the part of it inside ``box``) as one point source."""
        return ArchiveSource(self, box)


def _load_cache(cache: str | os.PathLike[str] | None) -> dict[str, Tile]:
    if cache is None or not Path(cache).is_file():
        return {}
    try:
        data = json.loads(Path(cache).read_text(encoding="utf-8"))
        if data.get("version") != INDEX_VERSION:
            return {}
        tiles = [Tile(**{**t, "mins": tuple(t["mins"]), "maxs": tuple(t["maxs"])})
                 for t in data["tiles"]]
    except (ValueError, KeyError, TypeError, AttributeError):
        log.warning("%s: the tile index cache is unreadable; the headers are read again", cache)
        return {}
    return {t.path: t for t in tiles}


class ArchiveSource(LasSource):
    """An archive, or its part inside ``box``, as a :class:`~tiereg.io.las.LasSource`: its
    chunks come from the tiles that meet ``box`` only, clipped to it. ``info.count`` of a window
    is the tiles' counts by the share of their area inside it (an estimate; the spacing)."""

    def __init__(self, index: TileIndex, box: Box | None = None):  # noqa: D107 - no header reads
        self.index, self.box = index, box
        tiles = list(index.tiles) if box is None else index.tiles_near(box)
        self.tiles = tiles
        self.paths = [Path(t.path) for t in tiles]
        (lo, hi) = index.bounds
        if box is None:
            count, b = index.count, (lo, hi)
        else:
            count = int(round(sum(t.count * t.share_in(box) for t in tiles)))
            b = ((max(lo[0], box[0]), max(lo[1], box[1]), lo[2]),
                 (min(hi[0], box[2]), min(hi[1], box[3]), hi[2]))
        first = index.tiles[0]
        label = first.path if len(index.tiles) == 1 else (
            f"{Path(first.path).parent}/ ({len(index.tiles)} tiles)")
        self.info = SourceInfo(path=label, format="las", count=count, bounds=b,
                               crs_wkt=index.crs_wkt,
                               details={"files": len(index.tiles),
                                        "copc": sum(t.copc for t in index.tiles),
                                        "point_format": first.point_format})

    @property
    def headers(self) -> list:  # type: ignore[override]
        """The headers of the window's tiles, read when asked (writing LAS like this source)."""
        return [open_header(p) for p in self.paths[:1]]

    def chunks(self, chunk_size: int = DEFAULT_CHUNK, *,
               keep: Callable[[object], np.ndarray] | None = None,
               box: Box | None = None) -> Iterator[np.ndarray]:
        """The points of the tiles that meet the window (and ``box``), clipped to the window."""
        both = self.box if box is None else box if self.box is None else (
            max(box[0], self.box[0]), max(box[1], self.box[1]),
            min(box[2], self.box[2]), min(box[3], self.box[3]))
        for tile in (self.index.tiles_near(both) if both is not None else self.tiles):
            yield from tile_chunks(tile, keep=keep, box=both, chunk_size=chunk_size)

    def _records(self, chunk_size: int, *, box: Box | None = None) -> Iterator:
        if self.box is not None:
            raise InputError("a window of an archive cannot be rewritten; apply to its tiles")
        yield from super()._records(chunk_size, box=box)

    def __getstate__(self) -> dict:
        return {"index": self.index, "box": self.box}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["index"], state["box"])  # type: ignore[misc]
