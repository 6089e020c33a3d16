"""COPC benchmark: an archive reference's base grid from its COPC tiles' coarse octree levels
against the same grid from every point.

The first 64 tiles of the scale benchmark's archive (40 million points, a 2.4 x 9.6 km strip)
as LAZ and as COPC copies of the same points (benchmarks/copc_data.py). The base grid an
archive reference is prepared on (:func:`tiereg.distributed.prepare_archive_reference`: mean
heights of the surface points) is made three ways, in one process: from the LAZ tiles, from the
COPC tiles read whole, and from the COPC tiles' octree levels down to a quarter of a cell (what
tiereg does), at the cell this archive's reference takes (capped at 1,024 cells a side: 9.86 m,
as the whole 256-tile archive's 9.9 m). Reported: seconds (wall and CPU; laspy decodes a COPC
query's nodes on several threads), points gridded, and how the levels' grid differs from every
point's: cells that lose their data, and the differences of the cell means (median, NMAD, 99th
percentile, largest).

    python benchmarks/copc.py      -> benchmarks/results/copc.md and copc.json
"""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
RESULTS = HERE / "results"


def _grid(tiles, spec, origin, resolution):
    from tiereg.distributed import grid_tiles

    t, c = time.perf_counter(), time.process_time()
    grid = grid_tiles(tiles, spec, stats=("mean",), origin=origin, surface=True, first_only=True,
                      resolution=resolution)
    return grid, time.perf_counter() - t, time.process_time() - c


def compare(levels, every) -> dict:
    from tiereg.robust import nmad

    both = levels.mask & every.mask
    d = (levels["mean"] - every["mean"])[both]
    return {"cells_with_data": int(every.mask.sum()),
            "cells_lost": int((every.mask & ~levels.mask).sum()),
            "median_m": float(np.median(d)), "nmad_m": float(nmad(d)),
            "p99_abs_m": float(np.quantile(np.abs(d), 0.99)),
            "max_abs_m": float(np.abs(d).max())}


def run_cell(laz, copc) -> dict:
    """The three grids at the archive reference's own base cell."""
    from tiereg.batch import archive_base_cell
    from tiereg.distributed import COPC_POINTS_PER_CELL_SIDE
    from tiereg.reference import reference_spec

    lo, hi = (np.asarray(b, dtype=np.float64) for b in copc.bounds)
    origin, spec = reference_spec(lo, hi, archive_base_cell(copc))
    row = {"cell_m": spec.cell_size, "shape": list(spec.shape),
           "resolution_m": spec.cell_size / COPC_POINTS_PER_CELL_SIDE}
    runs = {"laz_every_point": (laz.tiles, None), "copc_every_point": (copc.tiles, None),
            "copc_levels": (copc.tiles, row["resolution_m"])}
    grids = {}
    for name, (tiles, resolution) in runs.items():
        grid, wall, cpu = _grid(tiles, spec, origin, resolution)
        grids[name] = grid
        row[name] = {"wall_s": wall, "cpu_s": cpu, "points": int(grid.count.sum())}
        print(f"cell {spec.cell_size:.2f} m, {name}: {wall:.1f} s, "
              f"{row[name]['points']:,} points", flush=True)
    row["levels_vs_every_point"] = compare(grids["copc_levels"], grids["copc_every_point"])
    row["copc_vs_laz_same"] = bool(np.array_equal(grids["copc_every_point"].count,
                                                  grids["laz_every_point"].count))
    return row


def write_md(out: dict) -> Path:
    lines = ["# COPC: an archive reference's base grid from the octree's coarse levels", "",
             f"{out['meta']['date']}, {out['meta']['machine']}, tiereg {out['meta']['tiereg']}; "
             f"{out['tiles']} tiles of the scale benchmark's archive, {out['points']:,} points "
             "(one process; `python benchmarks/copc.py`).", "",
             "| cell | read | seconds (CPU) | points gridded | vs every point |",
             "| --- | --- | --- | --- | --- |"]
    for r in out["cells"]:
        c = r["levels_vs_every_point"]
        for name in ("laz_every_point", "copc_every_point", "copc_levels"):
            v = r[name]
            vs = "" if name != "copc_levels" else (
                f"{c['cells_lost']} of {c['cells_with_data']:,} cells lost; mean heights "
                f"{c['median_m']:+.3f} m, NMAD {c['nmad_m']:.3f} m, 99 % within "
                f"{c['p99_abs_m']:.2f} m, max {c['max_abs_m']:.1f} m")
            label = {"laz_every_point": "LAZ, every point", "copc_every_point":
                     "COPC, every point", "copc_levels":
                     f"COPC, levels to {r['resolution_m']:.2f} m"}[name]
            lines.append(f"| {r['cell_m']:.2f} m ({r['shape'][0]} x {r['shape'][1]}) | {label} "
                         f"| {v['wall_s']:.1f} ({v['cpu_s']:.1f}) | {v['points']:,} | {vs} |")
    same = all(r["copc_vs_laz_same"] for r in out["cells"])
    lines += ["", f"Every point of the COPC copies gridded as the LAZ tiles: "
              f"{'the same counts in every cell' if same else 'counts differ'}.", "",
              "Reading a COPC tile whole costs more than reading the same points as LAZ "
              "here because benchmarks/copc_data.py writes small nodes (about 600 points on "
              "average, 1,028 nodes a tile, each its own LAZ chunk); the levels read are the "
              "few large nodes at the top. tiereg reads COPC tiles whole through the plain LAZ "
              "reader, as it reads LAZ.", ""]
    path = RESULTS / "copc.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def main() -> None:
    import subprocess

    from copc_data import make_copc

    from tiereg.archive import TileIndex

    copc_paths = make_copc(64)
    laz_paths = [HERE / "work" / "scale" / "tiles" / p.name.replace(".copc.laz", ".laz")
                 for p in copc_paths]
    laz, copc = TileIndex.build(laz_paths), TileIndex.build(copc_paths)
    assert all(t.copc for t in copc.tiles)
    commit = subprocess.run(["git", "-C", str(HERE), "log", "-1", "--format=%h", "--",
                             str(HERE.parent / "src")], capture_output=True, text=True).stdout
    out = {"meta": {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                    "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python "
                               f"{platform.python_version()}", "tiereg": commit.strip()},
           "tiles": len(copc.tiles), "points": copc.count,
           "cells": [run_cell(laz, copc)]}
    (RESULTS / "copc.json").write_text(json.dumps(out, indent=1))
    print(write_md(out))


if __name__ == "__main__":
    main()
