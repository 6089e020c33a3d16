"""Many blocks against one lidar archive: ``tiereg batch``.

The archive is indexed by its headers and gridded once (a tile a task,
:mod:`tiereg.distributed`); the prepared reference is kept in the output folder
(``reference-base.npz``, with the tile index ``tile-index.json``) so that a batch run again
neither reads headers nor grids tiles. Each block is then found anywhere in the archive
(:func:`tiereg.mosaic.find_in_mosaic`: its windows and judgements are tasks on the cluster),
and gets its folder with ``RESULT.json`` (and with ``report`` its report). ``summary.csv`` has
a row per block and ``overview.png`` shows every block on the archive's footprint. A block
whose ``RESULT.json`` exists is not registered again.
"""

from __future__ import annotations

import csv
import hashlib
import json
import logging
import math
import os
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ._optional import pyplot
from .archive import TileIndex
from .errors import InputError
from .grid import Grid, GridSpec
from .io import read_points
from .io.base import all_or_nothing, atomic_output, write_text_atomic
from .progress import ProgressFactory, no_progress
from .reference import Reference

log = logging.getLogger(__name__)

SUMMARY_FIELDS = ("block", "confident", "reasons", "scale", "omega_deg", "phi_deg",
                  "kappa_deg", "tx", "ty", "tz", "sigma_tx", "sigma_ty", "sigma_tz", "seconds")


@dataclass(frozen=True)
class BlockOutcome:
    """One block's row of ``summary.csv``, from its RESULT.json."""

    name: str
    path: str
    confident: bool
    reasons: tuple[str, ...]
    T_ref_mov: np.ndarray
    parameters: dict[str, Any]
    precision: dict[str, Any]
    seconds: float
    skipped: bool  # done by an earlier run

    @classmethod
    def from_result_file(cls, name: str, path: str, result_json: Path, *,
                         skipped: bool) -> BlockOutcome:
        d = json.loads(result_json.read_text(encoding="utf-8"))
        return cls(name, path, bool(d["confident"]), tuple(d.get("reasons", ())),
                   np.array(d["T_ref_mov"]), d["parameters"], d.get("precision") or {},
                   float(d.get("seconds", 0.0)), skipped)

    def row(self) -> dict[str, Any]:
        p, t = self.parameters, self.parameters.get("translation", [None] * 3)
        s = self.precision.get("translation") or [None] * 3
        return {"block": self.name, "confident": self.confident,
                "reasons": "; ".join(self.reasons), "scale": p.get("scale"),
                "omega_deg": p.get("omega_deg"), "phi_deg": p.get("phi_deg"),
                "kappa_deg": p.get("kappa_deg"), "tx": t[0], "ty": t[1], "tz": t[2],
                "sigma_tx": s[0], "sigma_ty": s[1], "sigma_tz": s[2],
                "seconds": round(self.seconds, 2)}


@dataclass(frozen=True)
class BatchResult:
    outcomes: tuple[BlockOutcome, ...]
    summary_csv: Path
    overview_png: Path
    reference_seconds: float
    seconds: float

    @property
    def all_confident(self) -> bool:
        return all(o.confident for o in self.outcomes)


def block_names(blocks: Sequence[str | os.PathLike[str]]) -> list[str]:
    """A folder name per block: the file's stem (a model folder's name); names must differ."""
    names = []
    for b in blocks:
        p = Path(b)
        if not p.exists():
            raise InputError(f"{p}: no such block file or folder; check the path")
        names.append(p.name if p.is_dir() else p.stem)
    seen: dict[str, str] = {}
    for name, b in zip(names, blocks):
        if name in seen:
            raise InputError(f"blocks {seen[name]} and {b} would share the folder {name}/; "
                             "rename one of them")
        seen[name] = str(b)
    return names


def _signature(index: TileIndex, base_cell: float) -> str:
    h = hashlib.sha256(repr(base_cell).encode())
    for t in index.tiles:
        h.update(f"{t.path}|{t.size}|{t.mtime_ns}".encode())
    return h.hexdigest()[:16]


def load_or_prepare(index: TileIndex, out: Path, *, base_cell: float, client: Any,
                    progress: ProgressFactory) -> tuple[Reference, float]:
    """The archive's prepared reference: from ``reference-base.npz`` in ``out`` when it was
    made from the same tiles and base cell, else gridded (and kept there). Returns the
    reference and the seconds spent gridding (0 when loaded)."""
    from .distributed import prepare_archive_reference

    path, sig = out / "reference-base.npz", _signature(index, base_cell)
    if path.is_file():
        with np.load(path) as z:
            if str(z["signature"]) == sig:
                s = z["spec"]
                spec = GridSpec(float(s[0]), float(s[1]), float(s[2]), (int(s[3]), int(s[4])))
                grid = Grid(spec, z["count"], {"mean": z["mean"]}, index.crs_wkt)
                return Reference(index.source(), z["origin"], grid, bool(z["first"]),
                                 source_args=index.paths), 0.0
    t0 = time.perf_counter()
    ref = prepare_archive_reference(index, base_cell=base_cell, client=client, progress=progress)
    seconds = time.perf_counter() - t0
    spec = ref.base.spec
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, signature=sig, origin=ref.origin, count=ref.base.count,
                     mean=ref.base["mean"], first=ref.first_returns_only,
                     spec=np.array([spec.x0, spec.y0, spec.cell_size, *spec.shape]))
    return ref, seconds


def archive_base_cell(index: TileIndex) -> float:
    """The archive's mean point spacing (the finest cell worth gridding)."""
    (x0, y0, _), (x1, y1, _) = index.bounds
    return math.sqrt(max((x1 - x0) * (y1 - y0), 1e-12) / max(index.count, 1))


def run_batch(blocks: Sequence[str | os.PathLike[str]],
              reference: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
              out: str | os.PathLike[str], *, client: Any = None, report: bool = False,
              sigma_range: tuple[float, float] = (0.25, 4.0),
              progress: ProgressFactory | None = None) -> BatchResult:
    """Register every block against the archive ``reference`` into ``out`` (module
    docstring); blocks with a RESULT.json in ``out`` are kept as they are."""
    from .distributed import n_workers
    from .mosaic import Overviews

    t0 = time.perf_counter()
    progress = progress or no_progress
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"`out` {out}: is a file; give a folder for the results")
    names = block_names(blocks)
    out.mkdir(parents=True, exist_ok=True)
    index = TileIndex.build(reference, cache=out / "tile-index.json")
    ref, ref_seconds = load_or_prepare(index, out, base_cell=archive_base_cell(index),
                                       client=client, progress=progress)
    overviews = Overviews(ref, client)
    outcomes: dict[str, BlockOutcome] = {}
    todo = []
    for name, b in zip(names, blocks):
        done = out / name / "RESULT.json"
        if done.is_file():
            outcomes[name] = BlockOutcome.from_result_file(name, str(b), done, skipped=True)
        else:
            todo.append((name, str(b)))
    bar = progress("blocks", len(blocks))
    bar.update(len(blocks) - len(todo))
    try:
        with ThreadPoolExecutor(n_workers(client) if client is not None else 1) as pool:
            futures = [pool.submit(_one_block, name, b, ref, out, client=client, report=report,
                                   sigma_range=sigma_range, overviews=overviews)
                       for name, b in todo]
            for f in as_completed(futures):
                o = f.result()
                outcomes[o.name] = o
                bar.update(1)
    finally:
        bar.close()
    ordered = tuple(outcomes[n] for n in names)
    summary = out / "summary.csv"
    with atomic_output(summary) as tmp:
        with open(tmp, "w", newline="", encoding="utf-8") as fh:
            w = csv.DictWriter(fh, fieldnames=SUMMARY_FIELDS)
            w.writeheader()
            w.writerows(o.row() for o in ordered)
    png = out / "overview.png"
    overview_map(ref, ordered, png)
    return BatchResult(ordered, summary, png, ref_seconds, time.perf_counter() - t0)


def _one_block(name: str, block: str, ref: Reference, out: Path, *, client: Any, report: bool,
               sigma_range: tuple[float, float], overviews: Any) -> BlockOutcome:
    from .mosaic import find_in_mosaic
    from .pipeline import dumps_json

    t0 = time.perf_counter()
    found = find_in_mosaic(block, ref, client=client, sigma_range=sigma_range,
                           overviews=overviews)
    folder = out / name
    folder.mkdir(exist_ok=True)
    result = found.result
    d = result.to_dict()
    d["seconds"] = round(time.perf_counter() - t0, 3)
    d["mosaic"] = {"windows": found.windows, "screen_seconds": round(found.screen_seconds, 3),
                   "judge_seconds": round(found.judge_seconds, 3),
                   "judged": [{"centre": list(map(float, c.centre)), "score": c.score,
                               "kappa_deg": c.kappa_deg, "sigma": c.sigma, "confident": k}
                              for c, k in zip(found.candidates, found.judged_confident)]}
    result_json = folder / "RESULT.json"
    with all_or_nothing(folders=[folder / "report"]):  # each block whole, as it finishes
        if report:
            from .report import write_report

            write_report(result, folder / "report")
        write_text_atomic(result_json, dumps_json(d) + "\n")  # the block counts as done
    return BlockOutcome.from_result_file(name, block, result_json, skipped=False)


def overview_map(ref: Reference, outcomes: Sequence[BlockOutcome], path: Path) -> None:
    """The archive's heights (at most 800 cells a side) and every block's outline on them:
    green where confident, red where not."""
    plt = pyplot("the batch's overview map")

    spec = ref.base.spec
    k = max(1, math.ceil(max(spec.shape) / 800))
    grid = ref.grid(k * ref.base_cell)
    x0, y0, x1, y1 = grid.spec.bounds
    o = ref.origin
    fig, ax = plt.subplots(figsize=(8, 8), dpi=110)
    ax.imshow(grid["mean"] + o[2], cmap="gray", extent=(x0 + o[0], x1 + o[0], y0 + o[1],
                                                        y1 + o[1]))
    for t in ref.source.index.tiles if hasattr(ref.source, "index") else ():
        ax.add_patch(plt.Rectangle(t.mins[:2], t.maxs[0] - t.mins[0], t.maxs[1] - t.mins[1],
                                   fill=False, lw=0.3, ec="#4477aa", alpha=0.6))
    for b in outcomes:
        xy = _outline(b)
        if xy is None:
            continue
        colour = "#22aa44" if b.confident else "#dd2222"
        ax.fill(xy[:, 0], xy[:, 1], fc=colour, ec=colour, alpha=0.5, lw=1.2)
        ax.annotate(b.name, xy.mean(axis=0), fontsize=6, color=colour, ha="center",
                    va="bottom", xytext=(0, 6), textcoords="offset points")
    ax.set_title(f"{len(outcomes)} blocks: {sum(b.confident for b in outcomes)} confident "
                 "(green), others red")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.tick_params(labelsize=7)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
    plt.close(fig)


def _outline(b: BlockOutcome) -> np.ndarray | None:
    """The block's convex hull in the reference frame, by its RESULT.json's transform."""
    from scipy.spatial import ConvexHull, QhullError

    from .transform import Transform

    try:
        xyz = read_points(b.path).xyz
        placed = Transform(b.T_ref_mov).apply(xyz)[:, :2]
        hull = ConvexHull(placed)
    except (InputError, QhullError, ValueError):
        return None
    return placed[hull.vertices]
