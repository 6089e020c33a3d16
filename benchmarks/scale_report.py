"""Write benchmarks/results/scale.md from scale.json (benchmarks/scale.py's figures)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).parent / "results"


def _grid_lines(g: dict) -> list[str]:
    out = ["## Gridding the archive (the reference's base grid, a tile a task)", "",
           "| run | tiles | points | wall s | CPU s | peak RSS per worker MB | load avg |",
           "| --- | --- | --- | --- | --- | --- | --- |"]
    for key, label in (("decode_all_2proc", "decode only, laspy/lazrs, 2 processes"),
                       ("decode_all_2w", "decode only, a tile a task, 2 Dask workers"),
                       ("grid_all_1w", "gridding, 1 worker"), ("grid_all_2w", "gridding, 2 workers"),
                       ("decode_50M_2proc", "decode only, 80 tiles, 2 processes"),
                       ("grid_50M_2w", "gridding 80 tiles, 2 workers")):
        r = g.get(key)
        if not r:
            continue
        cpu = r.get("cpu_s", r.get("worker_cpu_s", 0.0))
        rss = ", ".join(f"{v:.0f}" for v in r.get("peak_rss_mb_per_worker", [])) or "-"
        tiles = r.get("tiles", 256 if "all" in key else 80)
        out.append(f"| {label} | {tiles} | {r['points'] / 1e6:.1f} M | {r['seconds']:.0f} | "
                   f"{cpu:.0f} | {rss} | {r['load']:.1f} |")
    d, w2 = g.get("decode_all_2proc"), g.get("grid_all_2w")
    if d and w2:
        out += ["", f"Gridding with 2 workers took {w2['seconds'] / d['seconds']:.2f} times the wall "
                f"time of decoding the same tiles with 2 processes, and "
                f"{w2['worker_cpu_s'] / d['cpu_s']:.2f} times its CPU time (the CPU ratio is the "
                "one another user's load does not move)."]
    if w2:
        per = w2["task_compute_s"] / max(w2["tasks"], 1)
        out += ["", f"Tasks: {w2['tasks']} (one per tile), {per:.2f} s of compute each on "
                f"average; wall x workers - compute, per task: {w2['overhead_per_task_s']:.3f} s."]
    s = g.get("scheduler")
    if s:
        out.append(f"Scheduler round trip measured alone: {s['seconds_per_task'] * 1e3:.1f} ms "
                   f"per no-op task ({s['tasks']} tasks, 2 workers).")
    return out


def _search_grids(block: str, width_m: float = 9600.0) -> float:
    """The mosaic's width in search grids of the block: 320 of its tie cells, in metres."""
    from tiereg.grid import cell_size_from_density

    work = Path(__file__).parent / "work" / "scale" / "blocks"
    xyz = np.loadtxt(work / f"{block}.xyz")
    scale = json.loads((work / f"{block}.truth.json").read_text())["scale_model_per_m"]
    return width_m / (320 * cell_size_from_density(xyz - xyz.mean(axis=0)) / scale)


def _peak(r: dict) -> str:
    return f"{max(r['peak_rss_mb_per_worker']):.0f}" if r.get("peak_rss_mb_per_worker") else "-"


def _mosaic_lines(m: dict) -> list[str]:
    rows = [r for r in m.values() if r.get("workers", 2) == 2]
    one = {r["block"]: r for r in m.values() if r.get("workers") == 1}
    for r in rows:
        r["mosaic_search_grids"] = _search_grids(r["block"])
    out = [f"## Mosaic search ({len(rows)} of the 20 blocks measured, 2 workers, after the "
           "overview is built)", "",
           "Correct: the RMS of the answer's error over the block's tie points (its scale and "
           "heading show at the edges) within two tie cells; the error at the centre beside it.",
           "",
           "| block | half | correct (RMS m) | centre m | tie cell m | confident | windows | "
           "wall s | CPU s | mosaic / search grid |",
           "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in sorted(rows, key=lambda r: r["block"]):
        rms = f"{r['rms_m']:.2f}" if "rms_m" in r else "-"
        out.append(f"| {r['block']} | {r['half']} | {'yes' if r['correct'] else 'NO'} "
                   f"({rms}) | {r['error_m']:.2f} | {r['cell_m']:.1f} | "
                   f"{'yes' if r['confident'] else 'no'} | "
                   f"{r['windows']} | {r['seconds']:.0f} | {r['cpu_s']:.0f} | "
                   f"{r['mosaic_search_grids']:.1f} |")
    out.append("")
    for half in ("dev", "held-out"):
        hs = [r for r in rows if r["half"] == half]
        if not hs:
            continue
        ok = sum(r["correct"] and r["confident"] for r in hs)
        wrong = sum(r["confident"] and not r["correct"] for r in hs)
        out.append(f"- {half}: {ok}/{len(hs)} correct and confident, {wrong} confidently wrong; "
                   f"wall median {np.median([r['seconds'] for r in hs]):.0f} s (max "
                   f"{max(r['seconds'] for r in hs):.0f}), CPU median "
                   f"{np.median([r['cpu_s'] for r in hs]):.0f} s (max "
                   f"{max(r['cpu_s'] for r in hs):.0f}), load average "
                   f"{np.median([r['load'] for r in hs]):.1f}")
    peaks = [max(r["peak_rss_mb_per_worker"]) for r in rows if r.get("peak_rss_mb_per_worker")]
    if peaks:
        out.append(f"- peak memory per worker over the batch (VmHWM): at most {max(peaks):.0f} MB")
    if one:
        two = {r["block"]: r for r in rows if r["block"] in one}
        out += ["", "The same blocks on 1 worker and on 2 (separate runs: the machine's load "
                "differs):", "",
                "| block | 1 worker: wall s | CPU s | peak MB | 2 workers: wall s | CPU s | "
                "peak MB | same answer |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        for b in sorted(one):
            a, c = one[b], two.get(b)
            if c is None:
                continue
            same = np.allclose(a["T_ref_mov"], c["T_ref_mov"], rtol=0, atol=1e-6) if (
                "T_ref_mov" in a and "T_ref_mov" in c) else "-"
            out.append(f"| {b} | {a['seconds']:.0f} | {a['cpu_s']:.0f} | {_peak(a)} | "
                       f"{c['seconds']:.0f} | {c['cpu_s']:.0f} | {_peak(c)} | "
                       f"{'yes' if same is True else 'no' if same is False else same} |")
    return out


def main() -> None:
    data = json.loads((RESULTS / "scale.json").read_text())
    for extra in sorted(RESULTS.glob("scale-*.json")):  # phases run side by side
        more = json.loads(extra.read_text())
        for key in ("grid", "mosaic"):
            data[key] = {**data.get(key, {}), **more.get(key, {})}
        data = {k: v for k, v in data.items() if v}
    lines = ["# Scale-out benchmark", "",
             "Made by `python benchmarks/scale.py` (data: `benchmarks/scale_data.py`; this page: "
             "`benchmarks/scale_report.py`). Archive: 256 LAZ tiles of 600 m (a 9.6 km square "
             "of the simulated suburban world), about 160 million points, 1.65 points per "
             "square metre, noise and second returns included; 20 blocks of 3,000 tie points "
             "(190 m squares, random places and headings, scales 0.25-4, 2 % blunders), "
             "blocks 00-09 the dev half (used to choose the screening level), 10-19 held out. "
             f"Machine: {data['machine']['cpus']} cores, {data['machine']['memory_gb']} GB, "
             "shared with other work: the load average beside each figure says how much "
             "(2 is a full machine); CPU seconds are inflated by it less than wall time.", ""]
    if "grid" in data:
        lines += _grid_lines(data["grid"]) + [""]
    if "mosaic" in data:
        lines += _mosaic_lines(data["mosaic"]) + [""]
    notes = RESULTS / "scale-notes.md"
    if notes.is_file():
        lines += [notes.read_text().rstrip(), ""]
    (RESULTS / "scale.md").write_text("\n".join(lines))
    print(f"wrote {RESULTS / 'scale.md'}")


if __name__ == "__main__":
    main()
