"""Verdict benchmark: is tiereg right when it says it is confident, on scenes its simulator did not
make?

Cases (``verdict_cases.py``, fixed in code): 248 scenes in a *dev* half (seeds 0-123: settings may
be chosen on it) and a *held-out* half (seeds 1000-1123: only reported). Synthetic worlds of five
families from tiereg's simulator and from an independent generator (``worlds_alt.py``,
``sensors_alt.py``), about half each; lidar with 0.5-2 % unclassified spikes; three real surfaces
(``real_worlds.py``); negatives whose tie points come from another world or from beside the lidar.
Blocks of 300-6,000 tie points asked for (a world with fewer corners in the block gives fewer),
lidar at 0.5-8 points per m^2 (at most 1.5 million points, 1.15-3.5 times as wide as the block;
the 20 m Longyearbyen surface at 0.03-0.07), tie noise 0.1-0.5 m vertical (half that
horizontally), 0-5 % blunders of up to 5-20 m, 50-100 % of the block over the lidar, any heading,
scale 0.25-4 (0.3048 and 3.2808: feet), tilt ~0.3 deg.

    python benchmarks/verdict.py               # all cases -> benchmarks/results/verdict.{md,json}
    python benchmarks/verdict.py --quick       # a handful of dev cases -> benchmarks/work/
    python benchmarks/verdict.py --half dev --jobs 2
    python benchmarks/verdict.py --half dev --upside-down   # the same cases turned over

``--upside-down`` turns every case's tie points over (180 degrees about the x axis through
their centre) before registering them: level data upside down, as the points of a
structure-from-motion model whose first camera looked down come out. The true pose then
includes the turn; the cases are otherwise the same (results ``verdict-upside-down.*``).

Each case runs ``tiereg.register(moving, "reference.laz")`` with default options in a process of
its own, under a time limit and a memory limit (a case that breaks either, or raises, is a
failure, recorded with the exception's type). Scenes are generated once and cached under
``benchmarks/work/verdict/``; a re-run only registers again.

*Correct* (a positive case): heading within 2 deg, scale within 2 %, block centre within one
coarse cell (the cell tiereg derives from the tie points' density, in reference units: RESULT.json
``cell_size`` is that number in the moving points' units, so it shrinks with the scale; the error
in those cells is recorded too), and where
the fine stage ran and its answer was taken, the RMS over the tie points of
``|T_est p - T_true p|`` within 1.5 x the tie points' vertical noise (only the vertical RMS where
the fine stage held parameters the ground does not determine: those keep the coarse answer). A
negative case is correct when it is not confident. *Confidently wrong*: confident and not correct.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from verdict_cases import WORK, Case, all_cases, make_case_scene, scene_ready  # noqa: E402

RESULTS = HERE / "results"
HEADING_TOL_DEG, SCALE_TOL, CENTRE_TOL_CELLS, FINE_TOL_NOISE = 2.0, 0.02, 1.0, 1.5
TIMEOUT_GENERATE_S, TIMEOUT_REGISTER_S = 1200.0, 900.0
MAX_RSS_BYTES = 9e9  # a case's process tree above this is stopped (the machine has 24 GB)
QUICK_CASES = 6


# ------------------------------------------------------------------------- child processes
def _tree_rss(proc) -> int:
    try:
        procs = [proc] + proc.children(recursive=True)
        return sum(p.memory_info().rss for p in procs)
    except Exception:  # noqa: BLE001 -- the process ended meanwhile
        return 0


def run_child(args: list[str], timeout_s: float, log: Path) -> tuple[str, float]:
    """This script with ``args`` in a new process group; ``("ok" | "exit N" | "timeout" |
    "memory", seconds)``. The group is killed on a timeout or when it uses too much memory."""
    import psutil

    t0 = time.perf_counter()
    with open(log, "a") as fh:
        proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), *args],
                                stdout=fh, stderr=fh, start_new_session=True,
                                env=dict(os.environ, PYTHONHASHSEED="0"))
        ps = psutil.Process(proc.pid)
        status = None
        while proc.poll() is None:
            if time.perf_counter() - t0 > timeout_s:
                status = "timeout"
            elif _tree_rss(ps) > MAX_RSS_BYTES:
                status = "memory"
            if status:
                os.killpg(proc.pid, 9)
                proc.wait()
                break
            time.sleep(0.5)
    if status is None:
        status = "ok" if proc.returncode == 0 else f"exit {proc.returncode}"
    return status, time.perf_counter() - t0


def case_by_id(case_id: str) -> Case:
    for case in all_cases():
        if case.case_id == case_id:
            return case
    raise SystemExit(f"no case {case_id!r}")


def _variant_inputs(case: Case, truth: dict, variant: str) -> tuple[dict, np.ndarray]:
    """The truth and the tie points of the case as ``variant`` gives them."""
    moving = np.load(case.directory / "moving.npy")
    if variant != "upside-down":
        return truth, moving
    from tiereg.level import turned_over  # half a turn about x through the centre

    F = turned_over(moving.mean(axis=0)).matrix  # its own inverse
    moving = moving @ F[:3, :3].T + F[:3, 3]
    return {**truth, "T_ref_mov": (np.asarray(truth["T_ref_mov"]) @ F).tolist()}, moving


def register_one(case_id: str, out: Path, variant: str = "") -> None:
    """Child: register the cached scene and write the outcome (or the exception) to ``out``."""
    case = case_by_id(case_id)
    truth, moving = _variant_inputs(
        case, json.loads((case.directory / "truth.json").read_text()), variant)
    row = describe(case, truth)
    try:
        import tiereg

        t0 = time.perf_counter()
        result = tiereg.register(moving, str(case.directory / "reference.laz"))
        row["seconds"] = time.perf_counter() - t0
        (case.directory / _name("RESULT", variant)).write_text(result.to_json())
        row.update(evaluate(case, truth, result.to_dict(), moving))
    except Exception as exc:  # noqa: BLE001 -- recorded as a failure of the case
        row.update(status="failed", error=f"{type(exc).__name__}: {str(exc)[:300]}")
    out.write_text(json.dumps(row, default=float) + "\n")


# ------------------------------------------------------------------------------- evaluation
def describe(case: Case, truth: dict) -> dict:
    return {"case": case.case_id, "half": case.half, "family": case.family,
            "generator": case.generator, "world_family": case.world_family,
            "negative": case.negative, "n_tie_points": truth["n_tie_points"],
            "n_blunders": truth["n_blunders"], "n_lidar_points": truth["n_lidar_points"],
            "lidar_density": case.lidar_density, "lidar_m": case.lidar_m,
            "block_m": case.block_m, "noise_z_m": case.noise_z_m,
            "blunder_fraction": case.blunder_fraction, "blunder_max_m": case.blunder_max_m,
            "overlap": truth["overlap_measured"], "heading_deg": case.heading_deg,
            "scale": case.scale, "spikes_fraction": case.spikes_fraction}


def _fine_state(stage: dict) -> str:
    if stage.get("method") in (None, "none"):
        return "not run"
    if stage.get("refused"):
        return "refused"
    return "accepted, held " + "+".join(stage["held"]) if stage.get("held") else "accepted"


@dataclass(frozen=True)
class _Saved:
    """A registration as RESULT.json keeps it (what ``fine.precision_honest`` reads)."""

    d: dict

    @property
    def T_ref_mov(self):
        from tiereg.transform import Transform

        return Transform(np.asarray(self.d["T_ref_mov"]))

    def to_dict(self) -> dict:
        return self.d


def evaluate(case: Case, truth: dict, d: dict, moving: np.ndarray) -> dict:
    """The case's errors and verdict from its RESULT.json ``d``."""
    from fine import errors_at, precision_honest

    from tiereg.grid import cell_size_from_density
    from tiereg.transform import Transform

    result = _Saved(d)
    T_true = Transform(np.asarray(truth["T_ref_mov"]))
    T_est = result.T_ref_mov
    pe, pt = T_est.parameters(), T_true.parameters()
    heading_err = float((np.degrees(pe.kappa - pt.kappa) + 180.0) % 360.0 - 180.0)
    scale_err = float(pe.scale / pt.scale - 1.0)
    centre = moving.mean(axis=0, keepdims=True)
    centre_err_m = float(np.hypot(*(T_est.apply(centre) - T_true.apply(centre))[0, :2]))
    cell_ref = cell_size_from_density(T_true.apply(moving))
    rms, rms_xy, rms_z = errors_at(T_est, T_true, moving)
    stage = next((s for s in d["stages"] if s.get("name") == "fine"), {})
    state = _fine_state(stage)
    coarse_ok = (abs(heading_err) <= HEADING_TOL_DEG and abs(scale_err) <= SCALE_TOL
                 and centre_err_m <= CENTRE_TOL_CELLS * cell_ref)
    bound = FINE_TOL_NOISE * case.noise_z_m
    fine_ok = True
    if state == "accepted":
        fine_ok = rms <= bound
    elif state.startswith("accepted, held"):
        fine_ok = rms_z <= bound
    correct = (not d["confident"]) if case.negative else (coarse_ok and fine_ok)
    honest = precision_honest(result, T_true, moving) if state.startswith("accepted") else None
    return {"status": "ok", "T_ref_mov": d["T_ref_mov"],
            "confident": bool(d["confident"]), "reasons": list(d["reasons"]),
            "correct": bool(correct), "coarse_ok": bool(coarse_ok), "fine_ok": bool(fine_ok),
            "heading_err_deg": heading_err, "scale_err": scale_err,
            "centre_err_m": centre_err_m, "centre_err_cells": centre_err_m / cell_ref,
            "cell_ref_m": cell_ref, "result_cell_size": d["cell_size"],
            "centre_err_result_cells": centre_err_m / d["cell_size"],
            "rms_m": rms, "rms_xy_m": rms_xy, "rms_z_m": rms_z, "fine_bound_m": bound,
            "fine_state": state, "fine_refused": stage.get("refused"),
            "fine_converged": stage.get("converged"),
            "sigma0": stage.get("sigma0"), "fine_n_used": stage.get("n_used"),
            "fine_n_observed": stage.get("n_observed"), "precision_honest": honest,
            "nmad_dz": d["quality"].get("nmad_dz"),
            "nmad_over_noise": (d["quality"]["nmad_dz"] / case.noise_z_m
                                if d["quality"].get("nmad_dz") is not None else None),
            "overlap_estimated": d["quality"].get("overlap_fraction")}


# ------------------------------------------------------------------------------------- runs
def _name(stem: str, variant: str) -> str:
    return f"{stem}-{variant}.json" if variant else f"{stem}.json"


def rescore(case: Case, variant: str = "") -> dict | None:
    """The outcome again from the case's saved RESULT.json (no registration), or None."""
    out = case.directory / _name("outcome", variant)
    saved = case.directory / _name("RESULT", variant)
    if not (out.exists() and saved.exists()):
        return None
    row = json.loads(out.read_text())
    if row.get("status") != "ok":
        return row
    truth, moving = _variant_inputs(
        case, json.loads((case.directory / "truth.json").read_text()), variant)
    row.update(describe(case, truth))
    row.update(evaluate(case, truth, json.loads(saved.read_text()), moving))
    return row


def run_case(case: Case, logs: Path, variant: str = "") -> dict:
    log = logs / f"{case.case_id}.log"
    if not scene_ready(case):
        status, secs = run_child(["--generate-one", case.case_id], TIMEOUT_GENERATE_S, log)
        if status != "ok" or not scene_ready(case):
            return {"case": case.case_id, "half": case.half, "family": case.family,
                    "generator": case.generator, "negative": case.negative,
                    "status": "failed", "error": f"scene generation: {status}"}
    out = case.directory / _name("outcome", variant)
    out.unlink(missing_ok=True)
    (case.directory / _name("RESULT", variant)).unlink(missing_ok=True)
    args = ["--register-one", case.case_id, str(out)] + ([variant] if variant else [])
    status, secs = run_child(args, TIMEOUT_REGISTER_S, log)
    if status == "ok" and out.exists():
        return json.loads(out.read_text())
    truth = json.loads((case.directory / "truth.json").read_text())
    row = describe(case, truth)
    row.update(status="failed", seconds=secs,
               error={"timeout": f"TimeoutError: over {TIMEOUT_REGISTER_S:.0f} s",
                      "memory": f"MemoryError: over {MAX_RSS_BYTES / 1e9:.0f} GB"}.get(
                          status, f"process {status}"))
    return row


def run(cases: list[Case], jobs: int, variant: str = "") -> list[dict]:
    logs = WORK / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []

    def one(case: Case) -> dict:
        t0 = time.perf_counter()
        row = run_case(case, logs, variant)
        verdict = ("FAILED " + row.get("error", "")) if row.get("status") != "ok" else \
            f"confident={row['confident']} correct={row['correct']}"
        print(f"[{len(rows) + 1}/{len(cases)}] {case.case_id}: {verdict} "
              f"({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
        rows.append(row)
        return row

    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        done = list(pool.map(one, cases))
    return done


def _interleaved(cases: list[Case]) -> list[Case]:
    """Dev and held-out cases in turn, so that a run cut short still covers both halves."""
    dev = [c for c in cases if c.half == "dev"]
    held = [c for c in cases if c.half != "dev"]
    out = [c for pair in zip(dev, held) for c in pair]
    return out + dev[len(held):] + held[len(dev):]


def quick_cases() -> list[Case]:
    """A handful of dev cases of different families, the smallest lidars first."""
    dev = [c for c in all_cases() if c.half == "dev"]
    dev.sort(key=lambda c: c.lidar_density * c.lidar_m**2)
    chosen, seen = [], set()
    for c in dev:
        key = (c.family, bool(c.negative))
        if key not in seen:
            chosen.append(c)
            seen.add(key)
        if len(chosen) == QUICK_CASES:
            break
    return chosen


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a handful of dev cases -> work/")
    parser.add_argument("--half", choices=("dev", "heldout", "both"), default="both")
    parser.add_argument("--jobs", type=int, default=1, help="cases run at the same time")
    parser.add_argument("--only", nargs="*", help="these case ids only (results to work/)")
    parser.add_argument("--every", type=int, default=1,
                        help="every K-th case only, numbers 1, K + 1, ... (results to work/)")
    parser.add_argument("--generate-only", action="store_true", help="make the scenes, no runs")
    parser.add_argument("--rescore", action="store_true",
                        help="score the saved RESULT.json files again (no registration)")
    parser.add_argument("--generate-one", help=argparse.SUPPRESS)
    parser.add_argument("--upside-down", action="store_true",
                        help="turn each case's tie points over first (results verdict-upside-down)")
    parser.add_argument("--register-one", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.generate_one:
        make_case_scene(case_by_id(args.generate_one))
        return
    if args.register_one:
        register_one(args.register_one[0], Path(args.register_one[1]), *args.register_one[2:])
        return
    cases = quick_cases() if args.quick else all_cases()
    if args.half != "both":
        cases = [c for c in cases if c.half == args.half]
    if args.only:
        cases = [c for c in cases if c.case_id in set(args.only)]
    if args.every > 1:
        cases = [c for c in cases if int(c.case_id.split("-")[1]) % args.every == 1]
    if args.generate_only:
        logs = WORK / "logs"
        logs.mkdir(parents=True, exist_ok=True)

        def gen(case):
            if not scene_ready(case):
                status, secs = run_child(["--generate-one", case.case_id], TIMEOUT_GENERATE_S,
                                         logs / f"{case.case_id}.log")
                print(f"{case.case_id}: {status} ({secs:.0f} s)", file=sys.stderr, flush=True)

        with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            list(pool.map(gen, cases))
        return
    t0 = time.perf_counter()
    saved_meta: dict = {}
    variant = "upside-down" if args.upside_down else ""
    name = "verdict-quick" if args.quick else "verdict" + (f"-{variant}" if variant else "")
    if args.rescore:
        rows = [r for r in (rescore(c, variant) for c in cases) if r is not None]
        if (RESULTS / f"{name}.json").exists():  # the run's own date, jobs and wall time
            saved_meta = json.loads((RESULTS / f"{name}.json").read_text())["meta"]
        seconds = float(saved_meta.get("wall_seconds", 0.0))
    else:
        from coarse import machine_speed

        speed_before = machine_speed().removeprefix("machine speed: ")
        rows = run(_interleaved(cases), args.jobs, variant)
        seconds = time.perf_counter() - t0
        saved_meta["machine_speed"] = [speed_before,
                                       machine_speed().removeprefix("machine speed: ")]
    from verdict_report import write_report

    partial = (args.quick or args.only or args.every > 1 or args.half != "both"
               or len(rows) < len(cases))
    out_dir = HERE / "work" if partial else RESULTS
    meta = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python "
                       f"{platform.python_version()}",
            "tiereg": _tiereg_commit(), "jobs": args.jobs, "wall_seconds": seconds,
            "cases": len(rows), "selection": "quick" if args.quick else args.half
            + (f", every {args.every}th case" if args.every > 1 else "")
            + (", tie points upside down" if variant else "")}
    meta.update({k: saved_meta[k] for k in ("date", "jobs", "machine_speed")
                 if k in saved_meta})
    path = write_report(rows, meta, out_dir, name=name)
    print(path)


def _tiereg_commit() -> str:
    try:
        return subprocess.run(["git", "-C", str(HERE), "log", "-1", "--format=%h", "--",
                               str(HERE.parent / "src")],
                              capture_output=True, text=True, check=True).stdout.strip()
    except Exception:  # noqa: BLE001 -- not a git checkout
        import tiereg

        return tiereg.__version__


if __name__ == "__main__":
    main()
