"""The registration report: maps, histograms, statistics, coarse evidence and control points.

``write_report(result, out_dir)`` writes into ``out_dir``:

- ``report.html``: one self-contained page (pictures embedded, readable offline);
- ``dz_before.png`` / ``dz_after.png``: height-difference maps (tie points against the lidar
  surface) before and after the fine stage, with colour and scale bars, and the same as
  ``dz_before.tif`` / ``dz_after.tif`` (median per cell, the reference's CRS);
- ``residual_histogram.png``; ``coarse_candidates.png`` and ``coarse_correlation.png`` (the
  correlation surface around the answer), when a coarse stage ran;
- ``residuals.csv``: per tie point ``x, y, z, dz_before, dz_after, weight, blunder``;
- ``control_points.csv``, ``control_points.txt`` (``name x y z sx sy sz``) and
  ``control_points_colmap.txt``: lidar control points (:mod:`tiereg.control`).

Every file is written whole or not at all.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..control import (
    ControlPoint,
    control_points_colmap,
    control_points_csv,
    control_points_list,
    select_control_points,
)
from ..errors import InputError, OutputError
from ..grid import GridSpec, rasterize
from ..io.base import atomic_output, write_text_atomic
from ..io.raster import write_geotiff
from ..quality import HeightStats, PointResiduals
from . import figures
from .html import escape, image, page, parameters_table, stats_table

__all__ = ["Report", "report_from_result_file", "write_report"]


@dataclass(frozen=True)
class Report:
    """What a report wrote: its folder, the page, and the control points it selected."""

    directory: Path
    html: Path
    files: tuple[str, ...]
    control_points: tuple[ControlPoint, ...]


def write_report(result, out_dir: str | os.PathLike[str]) -> Report:
    """Write the report of a :class:`~tiereg.RegistrationResult` into ``out_dir``."""
    if result.residuals is None:
        raise InputError("the result has no per-point residuals; register again with this "
                         "version of tiereg")
    data = result.to_dict()
    control: tuple[ControlPoint, ...] = ()
    if result.reference is not None and result.confident:
        local = result.residuals.xyz - result.reference.origin
        control = select_control_points(local, result.reference, blunder=result.residuals.blunder,
                                        sigma_xy=_sigma_xy(data["precision"]))
    return _write(data, result.residuals, control, Path(out_dir),
                  crs_wkt=result.inputs.crs_wkt, correlation=_correlation_window(result))


def _sigma_xy(precision: dict[str, Any] | None) -> float | None:
    """The registration's horizontal precision, one standard deviation per axis (the RMS of x
    and y at the block centroid), from RESULT.json's ``precision``; ``None`` without one (no
    fine stage, or a refused one)."""
    sx, sy = ((precision or {}).get("translation") or [None, None])[:2]
    return None if sx is None or sy is None else float(np.hypot(sx, sy) / np.sqrt(2))


PICTURE_CELLS = 15  # the correlation picture: shifts up to this many cells each way


def _correlation_window(result) -> np.ndarray | None:
    """The coarse score surface of the registered tie points around zero shift, or ``None``."""
    from ..coarse.scoring import score_around

    if result.coarse is None or result.reference is None or result.residuals is None:
        return None
    placed = result.residuals.xyz - result.reference.origin
    return score_around(placed, result.reference, result.cell_size, cells=PICTURE_CELLS)


def report_from_result_file(result_json: str | os.PathLike[str],
                            out_dir: str | os.PathLike[str], *, progress=None) -> Report:
    """The report of an earlier registration, from its RESULT.json and the inputs it names.

    The same files as :func:`write_report`, but for what RESULT.json does not keep: blunders are
    those more than ``BLUNDER_NMADS`` robust standard deviations off (not the fine stage's
    weights), and there is no ``coarse_correlation.png``."""
    from ..evaluate import evaluate
    from ..io import open_points
    from ..reference import prepare_reference
    from ..transform import Transform

    path = Path(result_json)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        T_final = Transform(np.asarray(data["T_ref_mov"], dtype=np.float64))
        inputs, cell = data["inputs"], float(data["cell_size"])
    except FileNotFoundError:
        raise InputError(f"{path}: no such file; give the RESULT.json of a registration") from None
    except (json.JSONDecodeError, KeyError, TypeError, ValueError):
        raise InputError(f"{path}: not a tiereg RESULT.json (T_ref_mov, inputs and cell_size are "
                         "needed); give the file `tiereg register -o` wrote") from None
    coarse = next((s for s in data.get("stages", []) if s.get("name") == "coarse"
                   and s.get("T_ref_mov")), None)
    before = coarse["T_ref_mov"] if coarse else data.get("T_initial") or data["T_ref_mov"]
    T_before = Transform(np.asarray(before, dtype=np.float64))
    given = {}
    for role in ("moving", "reference"):
        paths = [str(p) for p in inputs.get(f"{role}_paths") or []]
        missing = [p for p in paths if not Path(p).exists() and not any(c in p for c in "*?[")]
        if not paths or missing:
            name = missing[0] if missing else inputs.get(role, "none")
            raise InputError(f"{path}: the {role} input it names ({name}) is not found "
                             "(arrays are not kept); register again with --report DIR")
        given[role] = paths if len(paths) > 1 else paths[0]
    source = open_points(given["reference"], format=inputs.get("reference_format"))
    base_cell = data.get("base_cell") or cell / 4  # the same surface as the registration's
    reference = replace(prepare_reference(source, base_cell=float(base_cell), progress=progress),
                        source_args=tuple(inputs["reference_paths"]))
    # heights against the lidar's own points, as the registration measured them
    moving = open_points(given["moving"], format=inputs.get("moving_format")).read().xyz
    after = evaluate(reference, moving, T_final)
    prior = evaluate(reference, moving, T_before)
    residuals = PointResiduals.from_dz(after.xyz, prior.dz, after.dz)
    control = ()
    if data.get("confident"):
        control = select_control_points(after.xyz - reference.origin, reference,
                                        blunder=residuals.blunder,
                                        sigma_xy=_sigma_xy(data.get("precision")))
    return _write(data, residuals, control, Path(out_dir), crs_wkt=source.info.crs_wkt)


def _dz_grid(xy: np.ndarray, dz: np.ndarray, cell: float) -> tuple[np.ndarray, GridSpec] | None:
    ok = np.isfinite(dz)
    if ok.sum() == 0:
        return None
    lo, hi = xy[ok].min(axis=0), xy[ok].max(axis=0)
    spec = GridSpec.from_bounds(lo[0], lo[1], hi[0], hi[1], cell, max_cells=20_000_000)
    grid = rasterize(np.column_stack([xy[ok], dz[ok]]), spec, stats=("median",))
    return grid["median"], spec


def _write(data: dict[str, Any], residuals: PointResiduals,
           control: tuple[ControlPoint, ...], out: Path, *, crs_wkt: str | None,
           correlation: np.ndarray | None = None) -> Report:
    units = str(data.get("inputs", {}).get("units", "unknown"))
    xy = residuals.xyz[:, :2]
    after, before = residuals.stats(), residuals.stats(after=False)
    limit = _colour_limit(after, before)
    pictures: dict[str, bytes] = {
        "dz_before.png": figures.height_difference_map(
            xy, residuals.dz_before, title="before the fine stage", limit=limit, units=units),
        "dz_after.png": figures.height_difference_map(
            xy, residuals.dz_after, title="after registration", limit=limit, units=units,
            blunder=residuals.blunder),
        "residual_histogram.png": figures.residual_histogram(
            residuals.dz_before, residuals.dz_after, limit=2 * limit, units=units),
    }
    coarse = next((s for s in data.get("stages", []) if s.get("name") == "coarse"), None)
    if coarse and coarse.get("verified"):
        pictures["coarse_candidates.png"] = figures.coarse_candidates(
            coarse["verified"], coarse.get("search_best"), coarse.get("rival"))
    if correlation is not None:
        pictures["coarse_correlation.png"] = figures.correlation_surface(
            correlation, float(data.get("cell_size") or 1.0), units=units)
    try:  # the pictures are drawn first: a report that cannot be drawn leaves no folder
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{out}: cannot create the report folder ({exc.strerror}); give a "
                          "folder you can write to") from None
    files = []
    for name, png in pictures.items():
        with atomic_output(out / name) as tmp:
            tmp.write_bytes(png)
        files.append(name)
    cell = float(data.get("cell_size") or 1.0)
    for name, dz in (("dz_before.tif", residuals.dz_before), ("dz_after.tif", residuals.dz_after)):
        g = _dz_grid(xy, dz, cell)
        if g is not None:
            write_geotiff(out / name, g[0], g[1], crs_wkt=crs_wkt)
            files.append(name)
    write_text_atomic(out / "residuals.csv", residuals.to_csv())
    files.append("residuals.csv")
    if control:
        for name, text in (("control_points.csv", control_points_csv(control)),
                           ("control_points.txt", control_points_list(control)),
                           ("control_points_colmap.txt", control_points_colmap(control))):
            write_text_atomic(out / name, text)
            files.append(name)
    html_text = page(data=data, title="tiereg registration report", sections=_sections(
        data, pictures, before, after, control, limit, units, files))
    write_text_atomic(out / "report.html", html_text)
    files.append("report.html")
    return Report(out, out / "report.html", tuple(files), control)


def _colour_limit(after: HeightStats, before: HeightStats) -> float:
    """Symmetric colour limit that resolves the final residuals: three NMADs of them (blunders
    and a worse "before" saturate)."""
    for s in (after, before):
        if s.nmad_dz is not None and s.nmad_dz > 0:
            return float(3.0 * s.nmad_dz)
    return 1.0


def _sections(data, pictures, before, after, control, limit, units, files):
    sections = [("Transform (moving to reference)", parameters_table(
        data.get("parameters", {}), data.get("precision") or {}))]
    maps = "".join(image(pictures[n], n, c) for n, c in (
        ("dz_before.png", f"before the fine stage; colour limits +/-{limit:.3g} {units}"),
        ("dz_after.png", "after registration; circled: blunders set aside")))
    sections.append(("Height differences: lidar surface minus tie point",
                     f'<div class="maps">{maps}</div>'))
    sections.append(("Residual statistics", stats_table(before.to_dict(), after.to_dict(), units)
                     + image(pictures["residual_histogram.png"], "histogram",
                             "distribution of the height differences")))
    stages = data.get("stages", [])
    rows = "".join(f"<tr><td>{escape(s.get('name'))}</td><td>{escape(s.get('method'))}</td>"
                   f"<td>{float(s.get('seconds') or 0):.2f}</td></tr>" for s in stages)
    evidence = f"<table><tr><th>stage</th><th>method</th><th>seconds</th></tr>{rows}</table>"
    if "coarse_candidates.png" in pictures:
        evidence += image(pictures["coarse_candidates.png"], "coarse candidates",
                          "each hypothesis the coarse stage verified; the chosen one and the best "
                          "genuinely different rival")
    if "coarse_correlation.png" in pictures:
        evidence += image(pictures["coarse_correlation.png"], "correlation surface",
                          "the registered tie points' grid shifted against the lidar's: one "
                          "clear peak within a cell of the answer is what a reliable registration "
                          "looks like (the fine stage works below the cell)")
    sections.append(("Stages and coarse evidence", evidence))
    if control:
        kinds = {k: sum(p.kind == k for p in control) for k in ("height", "xyz")}
        head = "".join(f"<tr><td>{escape(p.name)}</td><td>{p.xyz[0]:.3f}</td>"
                       f"<td>{p.xyz[1]:.3f}</td><td>{p.xyz[2]:.3f}</td><td>{p.sigma[2]:.3f}</td><td>{escape(p.kind)}</td></tr>"
                       for p in control[:15])
        sections.append(("Lidar control points", (
            f"<p>{len(control)} tie points on planar, gently sloped, smooth lidar patches, spread "
            f"over the block ({kinds['height']} height only, {kinds['xyz']} full position); "
            "files: control_points.csv, control_points.txt, control_points_colmap.txt.</p>"
            "<table><tr><th>name</th><th>x</th><th>y</th><th>z</th><th>sz</th><th>kind</th></tr>"
            f"{head}</table>")))
    sections.append(("Files", "<ul>" + "".join(f"<li>{escape(f)}</li>" for f in files) + "</ul>"))
    return sections
