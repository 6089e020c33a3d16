"""File-level operations behind ``tiereg apply``, ``tiereg grid`` and ``tiereg info``."""

from __future__ import annotations

import json
import math
import os
import stat
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .crs import crs_label, crs_units
from .errors import InputError
from .grid import GridSpec, fill_normalized, median_sample_for, nice_size, rasterize
from .io import check_not_input, open_points, write_points
from .io.base import check_input_file, read_bytes
from .io.las import SOURCE_CRS, LasSource, transform_las
from .io.raster import RasterSource, write_geotiff
from .progress import ProgressFactory, no_progress
from .transform import Transform

PathsLike = str | os.PathLike[str] | Sequence[str | os.PathLike[str]]


MAX_TRANSFORM_BYTES = 16 << 20  # a RESULT.json or a matrix text is far smaller


def load_transform(path: str | os.PathLike[str]) -> tuple[Transform, str | None]:
    """The transform of a RESULT.json (``T_ref_mov``), a JSON with ``matrix`` or ``parameters``,
    or a text of 16 numbers (PDAL, CloudCompare), and the CRS (WKT) of the frame it maps into
    where a RESULT.json names it (its reference's), else ``None``."""
    p = Path(path)
    st = check_input_file(p)
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"{p}: is a directory; give a RESULT.json or a matrix file")
    if st.st_size > MAX_TRANSFORM_BYTES:
        raise InputError(f"{p}: is {st.st_size:,} bytes, not a transform (a RESULT.json or a "
                         "text of 16 numbers); check the order of the arguments")
    text = read_bytes(p).decode("utf-8", errors="replace")
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        if text.lstrip().startswith(("{", "[")):
            raise InputError(f"{p}: is a broken JSON file ({exc.msg} at line {exc.lineno}, "
                             f"column {exc.colno}); give the whole RESULT.json, e.g. write it "
                             "again with tiereg register") from None
        try:
            return Transform.from_text(text), None
        except InputError as exc2:
            raise InputError(f"{p}: {exc2}") from None
    if not isinstance(data, dict):
        raise InputError(f"{p}: a transform JSON must be an object with 'T_ref_mov' or 'matrix'")
    try:
        T = Transform.from_dict(data)
    except InputError as exc:
        raise InputError(f"{p}: {exc}") from None
    except (TypeError, ValueError, KeyError, AttributeError):
        raise InputError(f"{p}: its transform ('T_ref_mov' or 'matrix') is not a 4 x 4 matrix of "
                         "numbers; give the RESULT.json tiereg register wrote") from None
    inputs = data.get("inputs")
    wkt = inputs.get("crs_wkt") if isinstance(inputs, dict) else None
    return T, (wkt if isinstance(wkt, str) and wkt else None)


def apply_to_file(
    T: Transform,
    source_path: str | os.PathLike[str],
    out_path: str | os.PathLike[str],
    *,
    format: str | None = None,
    progress: ProgressFactory | None = None,
    crs_wkt: str | None = SOURCE_CRS,
) -> None:
    """Transform a point file or a DSM into ``out_path``.

    LAS/LAZ to LAS/LAZ streams chunk by chunk and keeps every point attribute. A GeoTIFF DSM is
    transformed through its cell centres and re-gridded at ``scale x`` its cell size (to a GeoTIFF
    output) or written as points (to a point format). The output names the input's CRS
    (:data:`~tiereg.io.las.SOURCE_CRS`), ``crs_wkt`` (the frame the transform maps into: the
    reference's), or none (``None``: a model's frame, which no CRS describes).
    """
    progress = progress or no_progress
    check_not_input(out_path, source_path)
    src = open_points(source_path, format=format)
    out = Path(out_path)
    suffix = out.suffix.lower()
    frame_crs = src.info.crs_wkt if crs_wkt == SOURCE_CRS else crs_wkt
    if isinstance(src, LasSource) and suffix in (".las", ".laz"):
        bar = progress(f"transforming {Path(source_path).name}", src.info.count)
        try:
            transform_las(src, out, T.apply, progress=bar.update, crs_wkt=crs_wkt)
        finally:
            bar.close()
        return
    if suffix in (".tif", ".tiff"):
        if not isinstance(src, RasterSource):
            raise InputError(f"{out}: GeoTIFF output is for DSM inputs; to grid points use "
                             "'tiereg grid' after 'tiereg apply'")
        _apply_to_raster(T, src, out, crs_wkt=frame_crs)
        return
    pts = src.read()
    write_points(out, T.apply(pts.xyz), like=src, crs_wkt=frame_crs)


def _apply_to_raster(T: Transform, src: RasterSource, out: Path, *, crs_wkt: str | None) -> None:
    cell = float(src.info.details["cell_size"][0]) * T.scale
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for chunk in src.chunks():  # first pass: the footprint after the transform
        moved = T.apply(chunk)
        lo, hi = np.minimum(lo, moved[:, :2].min(0)), np.maximum(hi, moved[:, :2].max(0))
    spec = GridSpec.from_bounds(lo[0], lo[1], hi[0], hi[1], cell)
    grid = rasterize((T.apply(c) for c in src.chunks()), spec, stats=("mean",))
    # a rotation leaves single empty cells between moved centres: fill those, not the outside
    filled, support = fill_normalized(grid["mean"], grid.mask, sigma_cells=0.7, min_support=0.5)
    values = np.where(grid.mask, grid["mean"], np.where(support, filled, np.nan))
    write_geotiff(out, values, spec, crs_wkt=crs_wkt)


def grid_to_geotiff(
    paths: PathsLike,
    out_path: str | os.PathLike[str],
    *,
    cell_size: float | None = None,
    stat: str = "mean",
    format: str | None = None,
    progress: ProgressFactory | None = None,
) -> GridSpec:
    """Rasterize points into a GeoTIFF in one streaming pass; returns the grid spec."""
    progress = progress or no_progress
    check_not_input(out_path, paths)
    src = open_points(paths, format=format)
    if src.info.count == 0:
        raise InputError(f"{src.info.path}: the point set is empty; nothing to grid")
    assert src.info.bounds is not None
    (x0, y0, _), (x1, y1, _) = src.info.bounds
    if cell_size is None:
        area = max((x1 - x0) * (y1 - y0), 1e-12)
        cell_size = nice_size(math.sqrt(4.0 * area / src.info.count))
    spec = GridSpec.from_bounds(x0, y0, x1, y1, cell_size)
    per_cell = src.info.count / max(spec.size, 1)
    bar = progress(f"gridding {Path(src.info.path).name}", src.info.count)
    try:
        grid = rasterize(src.chunks(), spec, stats=(stat,), progress=bar.update,
                         median_sample=median_sample_for(per_cell))
    finally:
        bar.close()
    if not grid.mask.any():  # every height NaN, or the header's bounds miss the points
        raise InputError(f"{src.info.path}: no point with a finite height falls inside the "
                         "bounds its header declares, so the grid would be empty; fix the file")
    values = grid.count.astype(np.float64) if stat == "count" else grid[stat]
    write_geotiff(out_path, values, spec, crs_wkt=src.info.crs_wkt)
    return spec


def describe(paths: PathsLike, *, format: str | None = None) -> dict[str, Any]:
    """Facts about a point file, tile set or DSM, read from headers where possible."""
    src = open_points(paths, format=format)
    info = src.info
    out: dict[str, Any] = {"path": info.path, "format": info.format, "points": info.count}
    if info.bounds is not None:
        lo, hi = info.bounds
        out["x_range"] = f"{lo[0]:.3f} .. {hi[0]:.3f}"
        out["y_range"] = f"{lo[1]:.3f} .. {hi[1]:.3f}"
        out["z_range"] = f"{lo[2]:.3f} .. {hi[2]:.3f}"
        area = (hi[0] - lo[0]) * (hi[1] - lo[1])
        if not math.isfinite(area):
            out["warning"] = "some coordinates are not finite (inf or NaN): fix the file"
        elif area > 0 and info.format != "geotiff":
            out["density_per_unit2"] = round(info.count / area, 6)
            out["suggested_cell_size"] = nice_size(math.sqrt(0.64 * area / max(info.count, 1)))
    out["crs"] = crs_label(info.crs_wkt)
    out["units"] = crs_units(info.crs_wkt)
    out.update({k: v for k, v in info.details.items()})
    return out

