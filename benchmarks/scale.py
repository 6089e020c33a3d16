"""Scale-out benchmark: gridding a 160-million-point archive of 256 LAZ tiles on a Dask cluster,
and finding 20 small blocks anywhere in it (a mosaic ten search grids wide).

    python benchmarks/scale.py [--phase grid|mosaic|all] [--workers 1 2] [--blocks dev|held-out|all]
                               [--only block05 ...]

A block is found correctly when the RMS of its registration's error over all its tie points is
within two tie cells (the error at its centre alone would pass a scale a few per cent off).

The archive and blocks come from benchmarks/scale_data.py (made once, kept in
benchmarks/work/scale). Figures go to benchmarks/results/scale.json, merged run by run (a phase
run alone keeps the other's figures), and scale.md is written from it. Every time is wall
clock on this machine with the load average beside it, and the CPU seconds (which another
user's load does not inflate).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
WORK = HERE / "work" / "scale"
RESULTS = HERE / "results"


def _peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM: unlike ru_maxrss, not carried over from
    the process that started it)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _cpu_s() -> float:
    return time.process_time()


def _decode_tile(path: str) -> tuple[int, float]:
    """Decode what gridding decodes (coordinates, returns, classification, flags), scaled."""
    import laspy

    from tiereg.archive import _selection

    t = time.process_time()
    n = 0
    with laspy.open(path, laz_backend=laspy.LazBackend.Lazrs,
                    decompression_selection=_selection()) as r:
        for pts in r.chunk_iterator(2_000_000):
            x, y, z = np.asarray(pts.x), np.asarray(pts.y), np.asarray(pts.z)
            n += len(x) if len(y) == len(z) == len(x) else 0
    return n, time.process_time() - t


def decode_baseline(paths: list[str], processes: int) -> dict:
    t0 = time.perf_counter()
    with Pool(processes) as pool:
        out = pool.map(_decode_tile, paths, chunksize=1)
    return {"processes": processes, "points": sum(n for n, _ in out),
            "seconds": time.perf_counter() - t0, "cpu_s": sum(c for _, c in out),
            "load": os.getloadavg()[0]}


def decode_on_cluster(paths: list[str], workers: int) -> dict:
    """:func:`_decode_tile` a tile a task on a local Dask cluster: what the cluster's harness
    costs decoding alone (against :func:`decode_baseline`'s process pool)."""
    from tiereg.distributed import cluster

    with cluster(workers=workers) as client:
        client.run(lambda: None)
        c0 = sum(client.run(_cpu_s).values())
        t0 = time.perf_counter()
        out = client.gather(client.map(_decode_tile, paths, pure=False))
        wall = time.perf_counter() - t0
        cpu = sum(client.run(_cpu_s).values()) - c0
    return {"workers": workers, "points": sum(n for n, _ in out), "seconds": wall,
            "worker_cpu_s": cpu, "task_cpu_s": sum(c for _, c in out),
            "load": os.getloadavg()[0]}


def grid_run(paths: list[str], workers: int, base_cell: float) -> dict:
    from distributed import get_task_stream

    from tiereg.archive import TileIndex
    from tiereg.distributed import cluster, prepare_archive_reference

    index = TileIndex.build(paths)
    with cluster(workers=workers) as client:
        client.run(lambda: None)
        t0 = time.perf_counter()
        with get_task_stream(client) as ts:
            ref = prepare_archive_reference(index, base_cell=base_cell, client=client)
        wall = time.perf_counter() - t0
        peak = client.run(_peak_rss_mb)
        cpu = sum(client.run(_cpu_s).values())
    tasks = [t for t in ts.data if t["key"].startswith("grid_tile")]
    compute = sum(s["stop"] - s["start"] for t in tasks for s in t["startstops"]
                  if s["action"] == "compute")
    return {"workers": workers, "tiles": len(paths), "points": index.count,
            "cells": ref.base.spec.size, "base_cell_m": ref.base_cell, "seconds": wall,
            "worker_cpu_s": cpu, "tasks": len(tasks), "task_compute_s": compute,
            "overhead_per_task_s": max(0.0, (wall * workers - compute) / max(len(tasks), 1)),
            "peak_rss_mb_per_worker": sorted(peak.values()), "load": os.getloadavg()[0]}


def task_cpu(paths: list[str], base_cell: float, repeats: int = 3) -> dict:
    """CPU seconds of decoding ``paths`` (:func:`_decode_tile`) against gridding them as the
    cluster's tasks do (:func:`tiereg.distributed.grid_tile`), both in this process, one tile
    after the other, interleaved ``repeats`` times; the least of each (what another user's
    load adds least to)."""
    from tiereg.archive import TileIndex
    from tiereg.distributed import grid_tile
    from tiereg.reference import reference_spec

    index = TileIndex.build(paths)
    origin, spec = reference_spec(*(np.asarray(b, dtype=np.float64) for b in index.bounds),
                                  base_cell)
    decode, grid = [], []
    for _ in range(repeats):
        decode.append(sum(_decode_tile(p)[1] for p in paths))
        t = time.process_time()
        for i, tile in enumerate(index.tiles):
            grid_tile(tile, spec, stats=("mean",), origin=origin, surface=True, first_only=True,
                      median_sample=15, seed=i)
        grid.append(time.process_time() - t)
    return {"tiles": len(paths), "points": index.count, "decode_cpu_s": min(decode),
            "grid_task_cpu_s": min(grid), "ratio": min(grid) / min(decode),
            "repeats": repeats, "load": os.getloadavg()[0]}


def scheduler_overhead(workers: int, n: int = 2000) -> dict:
    from tiereg.distributed import cluster

    with cluster(workers=workers) as client:
        client.gather(client.map(lambda i: i, range(50), pure=False))
        t0 = time.perf_counter()
        client.gather(client.map(lambda i: i, range(n), pure=False))
        wall = time.perf_counter() - t0
    return {"workers": workers, "tasks": n, "seconds_per_task": wall / n,
            "load": os.getloadavg()[0]}


def phase_grid(args, out: dict) -> None:
    from tiereg.archive import TileIndex
    from tiereg.batch import archive_base_cell

    paths = sorted(str(p) for p in (WORK / "tiles").glob("*.laz"))
    base = archive_base_cell(TileIndex.build(paths))
    part = paths[:80]  # about 50 million points
    g = out.setdefault("grid", {})
    runs = {
        "decode_all_2proc": lambda: decode_baseline(paths, 2),
        "decode_all_2w": lambda: decode_on_cluster(paths, 2),
        "grid_all_2w": lambda: grid_run(paths, 2, base),
        "grid_all_1w": lambda: grid_run(paths, 1, base),
        "grid_50M_2w": lambda: grid_run(part, 2, base),
        "decode_50M_2proc": lambda: decode_baseline(part, 2),
        "scheduler": lambda: scheduler_overhead(2),
        "task_cpu_16_tiles": lambda: task_cpu(paths[:16], base),
    }
    for name in args.runs or list(runs):
        g[name] = runs[name]()
        print(name, g[name], flush=True)
        _save(out)


def phase_mosaic(args, out: dict) -> None:
    from tiereg import Transform
    from tiereg.archive import TileIndex
    from tiereg.batch import archive_base_cell, load_or_prepare
    from tiereg.distributed import cluster
    from tiereg.mosaic import MAX_REFERENCE_CELLS, Overviews, find_in_mosaic
    from tiereg.progress import no_progress

    index = TileIndex.build(WORK / "tiles")
    prep = WORK / "prep"
    prep.mkdir(exist_ok=True)
    ref, _ = load_or_prepare(index, prep, base_cell=archive_base_cell(index), client=None,
                             progress=no_progress)
    names = sorted(p.stem for p in (WORK / "blocks").glob("*.xyz"))
    halves = {"dev": names[: len(names) // 2], "held-out": names[len(names) // 2:]}
    chosen = names if args.blocks == "all" else halves[args.blocks]
    chosen = [n for n in chosen if not args.only or n in args.only]
    rows = out.setdefault("mosaic", {})
    for w in args.workers:
        with cluster(workers=w) as client:
            overviews = Overviews(ref, client)
            for name in chosen:
                truth = json.loads((WORK / "blocks" / f"{name}.truth.json").read_text())
                sigma = 1.0 / truth["scale_model_per_m"]
                block = WORK / "blocks" / f"{name}.xyz"
                t0, c0 = time.perf_counter(), sum(client.run(_cpu_s).values()) + _cpu_s()
                m = find_in_mosaic(str(block), ref, client=client, overviews=overviews,
                                   sigma_range=(sigma / 1.25, sigma * 1.25))
                wall = time.perf_counter() - t0
                cpu = sum(client.run(_cpu_s).values()) + _cpu_s() - c0
                r = m.result
                xyz = np.loadtxt(block)
                centre = xyz.mean(axis=0)[None]
                T_true = Transform(np.array(truth["T_ref_mov"]))
                err = float(np.linalg.norm(r.T_ref_mov.apply(centre) - T_true.apply(centre)))
                # over the whole block: a scale or heading error shows at its edges
                rms = float(np.sqrt(np.mean(np.sum(
                    (r.T_ref_mov.apply(xyz) - T_true.apply(xyz)) ** 2, axis=1))))
                tie_m = r.cell_size
                width = max(ref.base.spec.bounds[2] - ref.base.spec.bounds[0],
                            ref.base.spec.bounds[3] - ref.base.spec.bounds[1])
                rows[f"{name}_{w}w"] = {
                    "block": name, "half": truth["half"], "workers": w, "seconds": wall,
                    "cpu_s": cpu, "windows": m.windows, "screen_s": m.screen_seconds,
                    "judge_s": m.judge_seconds, "confident": r.confident,
                    "error_m": err, "rms_m": rms, "correct": rms < 2 * tie_m, "cell_m": tie_m,
                    "T_ref_mov": r.T_ref_mov.matrix.tolist(),
                    "mosaic_search_grids": width / (MAX_REFERENCE_CELLS * tie_m),
                    "reasons": list(r.reasons), "load": os.getloadavg()[0],
                    # each worker's peak so far (it serves the blocks one after another)
                    "peak_rss_mb_per_worker": sorted(client.run(_peak_rss_mb).values())}
                print(rows[f"{name}_{w}w"], flush=True)
                _save(out)


def _save(out: dict) -> None:
    """Merge this run's phases into the results file (a phase run alone keeps the other's)."""
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / os.environ.get("SCALE_JSON", "scale.json")
    old = json.loads(path.read_text()) if path.is_file() else {}
    for key, value in out.items():
        old[key] = {**old.get(key, {}), **value} if isinstance(value, dict) else value
    path.write_text(json.dumps(old, indent=1, default=float))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--phase", choices=("grid", "mosaic", "all"), default="all")
    ap.add_argument("--workers", type=int, nargs="+", default=[2], help="mosaic phase")
    ap.add_argument("--blocks", choices=("dev", "held-out", "all"), default="all")
    ap.add_argument("--only", nargs="+", metavar="BLOCK", help="mosaic phase: these blocks only "
                    "(e.g. block05)")
    ap.add_argument("--runs", nargs="+", help="grid phase: these runs only (decode_all_2proc, "
                    "decode_all_2w, grid_all_2w, grid_all_1w, grid_50M_2w, decode_50M_2proc, "
                    "scheduler, task_cpu_16_tiles)")
    args = ap.parse_args()
    import scale_data

    scale_data.make_data(HERE / "work")
    out: dict = {}
    out["machine"] = {"cpus": os.cpu_count(), "memory_gb": round(
        os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)}
    if args.phase in ("grid", "all"):
        phase_grid(args, out)
    if args.phase in ("mosaic", "all"):
        phase_mosaic(args, out)
    _save(out)
    print(f"wrote {RESULTS / 'scale.json'}; python benchmarks/scale_report.py writes scale.md")


if __name__ == "__main__":
    main()
