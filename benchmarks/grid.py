"""Benchmark: gridding a 20-million-point LAZ with tiereg, against just decoding it.

Target: gridding a LAZ of at least 20 million points keeps peak memory under 1 GB,
and its time is within 1.5x of decoding the same file with laspy/lazrs in the same run.

    python benchmarks/grid.py            # full run: 20 M points, 3 repeats -> results/
    python benchmarks/grid.py --quick    # 2 M points, 1 repeat -> work/ (for development)

A synthetic airborne-lidar LAZ (see ``lidar_synth.py``) is generated once into
``benchmarks/work/`` (git-ignored). Every measurement runs in a fresh interpreter (this script
with ``--worker``), so the peak RSS is that task's own; repeats are interleaved across tasks.
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path

from lidar_synth import ensure_laz  # benchmarks/ is on sys.path when run as a script

HERE = Path(__file__).resolve().parent
GRID_STATS = (("mean",), ("min", "max"), ("median",), ("min", "max", "mean", "median"))


# --- one measurement, in a fresh process ---------------------------------------------------------

def _self_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6  # KiB on Linux


def worker(task: dict) -> dict:
    """Run one task in this process; return its time and the peak RSS of the working process."""
    path, kind = task["path"], task["kind"]
    if kind in ("cli", "pdal"):  # another program: its wall time and (only child's) peak RSS
        start = time.perf_counter()
        subprocess.run(task["cmd"], check=True, stdout=subprocess.DEVNULL)
        seconds = time.perf_counter() - start
        rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024 / 1e6
        return {"seconds": seconds, "peak_rss_mb": rss}
    if kind.startswith("decode"):
        import laspy

        from tiereg.io.las import _backend

        start, points = time.perf_counter(), 0
        with laspy.open(path, laz_backend=_backend()) as reader:
            for chunk in reader.chunk_iterator(2_000_000):
                if kind == "decode":  # scaled coordinates, as any use of the points needs
                    _x, _y, _z = chunk.x, chunk.y, chunk.z
                points += len(chunk)
        seconds = time.perf_counter() - start
        return {"seconds": seconds, "peak_rss_mb": _self_rss_mb(), "points": points}
    from tiereg.grid import GridSpec, median_sample_for, rasterize
    from tiereg.io import open_points

    start = time.perf_counter()
    src = open_points(path)
    (x0, y0, _), (x1, y1, _) = src.info.bounds
    spec = GridSpec.from_bounds(x0, y0, x1, y1, task["cell"])
    # the median sketch sized as `tiereg grid` sizes it, from the expected points per cell
    grid = rasterize(src.chunks(), spec, stats=tuple(task["stats"]),
                     median_sample=median_sample_for(src.info.count / spec.size))
    seconds = time.perf_counter() - start
    return {"seconds": seconds, "peak_rss_mb": _self_rss_mb(), "points": int(grid.count.sum()),
            "cells": spec.size, "occupancy": round(grid.occupancy, 4)}


def measure(task: dict) -> dict:
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, __file__, "--worker", json.dumps(task)],
                          check=False, capture_output=True, text=True)
    if proc.returncode:
        raise RuntimeError(f"task {task['name']!r} failed:\n{proc.stderr}")
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    result["process_wall_s"] = time.perf_counter() - start
    if result.get("points", task["expect"]) != task["expect"]:
        raise RuntimeError(f"task {task['name']!r} saw {result['points']} points")
    return result


def make_tasks(path: Path, count: int, tif: Path) -> list[dict]:
    grid = {"name": "tiereg rasterize", "kind": "grid"}
    tasks = [{"name": "decode (laspy, scaled x/y/z)", "kind": "decode"},
             {"name": "decode (laspy, no scaling)", "kind": "decode-raw"},
             {**grid, "cell": 10.0, "stats": ["mean"]}]
    tasks += [{**grid, "cell": 1.0, "stats": list(s)} for s in GRID_STATS]
    tasks.append({"name": "tiereg grid (CLI process)", "kind": "cli", "cell": 1.0,
                  "stats": ["mean"], "cmd": [str(Path(sys.executable).with_name("tiereg")),
                                             "grid", str(path), str(tif), "--cell-size", "1",
                                             "--stat", "mean", "-q"]})
    if shutil.which("pdal"):
        tasks.append({"name": "pdal translate (writers.gdal)", "kind": "pdal", "cell": 1.0,
                      "stats": ["mean"], "cmd": ["pdal", "translate", str(path), str(tif),
                                                 "--writers.gdal.resolution=1",
                                                 "--writers.gdal.output_type=mean"]})
    return [{**t, "path": str(path), "expect": count} for t in tasks]


# --- the run and the report ----------------------------------------------------------------------

def code_state() -> dict:
    """Which tiereg code a run measures (others may edit src/ while it runs), and the load."""
    git = subprocess.run(["git", "-C", str(HERE.parent), "describe", "--always", "--dirty"],
                         check=False, capture_output=True, text=True).stdout.strip()
    files = [HERE.parent / "src/tiereg" / f for f in ("grid.py", "io/las.py", "files.py")]
    digest = hashlib.sha256(b"".join(f.read_bytes() for f in files)).hexdigest()[:12]
    return {"git": git, "sources_sha256": digest, "loadavg": os.getloadavg()[0]}


def pdal_note() -> str:
    if shutil.which("pdal"):
        return "measured as a peer (row above)"
    listed = shutil.which("apt-cache") and subprocess.run(
        ["apt-cache", "show", "pdal"], check=False, capture_output=True).returncode == 0
    return "not installed, so no peer row" + ("" if listed else (
        " (`apt-get install pdal`: no such package in this machine's Debian archive)"))


def environment(path: Path) -> dict:
    import laspy

    from tiereg.io.las import _backend

    cpuinfo = Path("/proc/cpuinfo").read_text().splitlines()
    cpu = next((s.split(":", 1)[1].strip() for s in cpuinfo if s.startswith("model name")),
               platform.processor())
    with laspy.open(path) as reader:
        h = reader.header
    (x0, y0, z0), (x1, y1, z1) = h.mins, h.maxs
    return {
        "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "nproc": os.cpu_count(), "cpu": cpu, "python": platform.python_version(),
        **{name: metadata.version(name) for name in ("numpy", "laspy", "lazrs", "tiereg")},
        "laz_backend": str(_backend()), "pdal": pdal_note(),
        "file": str(path.relative_to(HERE.parent)), "points": int(h.point_count),
        "size_mb": round(path.stat().st_size / 1e6, 1),
        "extent": [round(v, 2) for v in (x0, y0, z0, x1, y1, z1)],
        "density_per_m2": round(h.point_count / ((x1 - x0) * (y1 - y0)), 3),
    }


def summarize(tasks: list[dict], runs: list[list[dict]]) -> list[dict]:
    base = statistics.median(r["seconds"] for r in runs[0])
    rows = []
    for task, results in zip(tasks, runs):
        times = [r["seconds"] for r in results]
        rows.append({k: v for k, v in task.items() if k not in ("path", "cmd", "expect")} | {
            "median_s": statistics.median(times), "min_s": min(times),
            "ratio_to_decode": statistics.median(times) / base,
            "peak_rss_mb": max(r["peak_rss_mb"] for r in results), "runs": results})
    return rows


def report(env: dict, gen: dict, code: list[dict], rows: list[dict], repeat: int) -> str:
    e, ext = env, env["extent"]
    changed = code[0]["sources_sha256"] != code[1]["sources_sha256"]
    key = next(r for r in rows if r["kind"] == "grid" and r["cell"] == 1 and r["stats"] == ["mean"])
    cli = next(r for r in rows if r["kind"] == "cli")
    ok = key["ratio_to_decode"] <= 1.5 and key["peak_rss_mb"] < 1000
    heavy = [f"{r['cell']:g} m {','.join(r['stats'])} ({r['peak_rss_mb']:.0f} MB)"
             for r in rows if r["kind"] == "grid" and r["peak_rss_mb"] >= 1000]
    lines = [
        "# Gridding benchmark", "",
        f"- date: {e['date']}; tiereg {e['tiereg']} (git {code[0]['git']}"
        + ("; **src/ changed during the run**)" if changed else ")"),
        (f"- machine: {e['nproc']} CPUs ({e['cpu']}); Python {e['python']}, numpy "
         f"{e['numpy']}, laspy {e['laspy']}, lazrs {e['lazrs']} (backend {e['laz_backend']})"),
        (f"- file: `{e['file']}`: {e['points']:,} points, LAS 1.4 PDRF 6, {e['size_mb']} MB; "
         f"extent {ext[3] - ext[0]:.0f} m x {ext[4] - ext[1]:.0f} m from ({ext[0]:.0f}, "
         f"{ext[1]:.0f}); {e['density_per_m2']} pts/m^2 (generated in {gen['generation_s']} s, "
         "not counted)"),
        (f"- {repeat} runs per task, each in a fresh process, interleaved. Time is the work in "
         "the process (open to last chunk, imports excluded), for the CLI the whole process "
         "(start-up, imports, GeoTIFF writing). Peak RSS is the process's maximum RSS (1 MB = "
         "10^6 bytes). The file is in the page cache. Load average at start/end: "
         f"{code[0]['loadavg']:.2f}/{code[1]['loadavg']:.2f}."),
        "", "| task | cell | stats | median s | min s | ratio to decode | peak RSS MB |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        cell = f"{r['cell']:g} m" if "cell" in r else "-"
        lines.append(f"| {r['name']} | {cell} | {','.join(r.get('stats', [])) or '-'} | "
                     f"{r['median_s']:.2f} | {r['min_s']:.2f} | {r['ratio_to_decode']:.2f} | "
                     f"{r['peak_rss_mb']:.0f} |")
    lines += [
        "", "## Conclusions", "",
        (f"- Target (1 m mean grid, {e['points']:,} points): "
         f"**{'met' if ok else 'NOT met'}**: {key['ratio_to_decode']:.2f}x the decode time "
         f"(limit 1.5x), peak RSS {key['peak_rss_mb']:.0f} MB (limit 1000 MB)."),
        (f"- The CLI (`tiereg grid --stat mean`, whole process) takes "
         f"{cli['ratio_to_decode']:.2f}x the decode time at {cli['peak_rss_mb']:.0f} MB."),
        "- Grids over 1 GB: " + ("; ".join(heavy) if heavy else "none") + ".",
        f"- PDAL: {e['pdal']}.",
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, help="points in the synthetic LAZ (default 20 million)")
    ap.add_argument("--repeat", type=int, help="runs per task (default 3)")
    ap.add_argument("--quick", action="store_true", help="2 M points, 1 run, results to work/")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))))
        return 0
    points = args.points or (2_000_000 if args.quick else 20_000_000)
    repeat = args.repeat or (1 if args.quick else 3)
    path, gen = ensure_laz(HERE / "work", points)
    code = [code_state()]
    tasks = make_tasks(path, gen["points"], HERE / "work" / "bench-out.tif")
    runs: list[list[dict]] = [[] for _ in tasks]
    for rep in range(repeat):
        for task, results in zip(tasks, runs):
            results.append(r := measure(task))
            print(f"[{rep + 1}/{repeat}] {task['name']} {task.get('cell', '')} "
                  f"{task.get('stats', '')}: {r['seconds']:.2f} s, {r['peak_rss_mb']:.0f} MB")
    code.append(code_state())
    env, rows = environment(path), summarize(tasks, runs)
    out_dir, stem = (HERE / "work", "grid-quick") if args.quick else (HERE / "results", "grid")
    out_dir.mkdir(exist_ok=True)
    (out_dir / f"{stem}.json").write_text(json.dumps(
        {"environment": env, "code": code, "generation": gen, "repeat": repeat, "tasks": rows},
        indent=1) + "\n")
    text = report(env, gen, code, rows, repeat)
    (out_dir / f"{stem}.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
