"""Structure-from-motion benchmark: tiereg on the models COLMAP makes of rendered aerial blocks.

Each scene is an aerial block rendered from a surface (five simulator world kinds and the three
real surfaces of ``real_worlds.py``; ``sfm_render.py``), reconstructed by pycolmap as a user would
on a CPU (``sfm_reconstruct.py``), with its truth (the model -> reference similarity fitted to
where the observations' true rays meet the true surface) and lidar of the block and of 50-70 %
of it (``sfm_scenes.py``). The models keep COLMAP's gauge: tens to hundreds of metres per model
unit, often upside down. Cases per scene:

=========== ==================================================================================
model       the COLMAP model folder (cameras.bin, images.bin, points3D.bin, ...) vs the lidar
points-thin a ``points3D.txt`` alone, thinned to 300-3,000 points, vs the lidar
points-full every model point as XYZ text, vs the lidar
partial     the model folder vs the lidar of 50-70 % of the block
negative    the model folder vs another scene's lidar (another place): correct when not confident
=========== ==================================================================================

plus, where ``src/tiereg/data/autzen_colmap`` exists, that model (real lidar in feet) with its
cameras and as bare points. Each case runs the installed command line, ``tiereg register
MOVING LIDAR -o RESULT.json``, in a child process with a time limit (:data:`TIMEOUT_S`) and an
address-space limit (:data:`MEMORY_LIMIT_BYTES`); its wall time, peak memory (the larger of the
kernel's ``ru_maxrss`` for the child and the polled resident memory of its process tree), exit
code and whether stderr holds a traceback are recorded.

Correct: rotation about the vertical ("heading") within 2 deg and tilt within 2 deg (of
``R_est R_true^T``), scale within 2 %, the model's centroid within one coarse cell (RESULT.json
``cell_size``) horizontally, and, when the fine stage ran, the RMS over the model's points of
``|T_est p - T_true p|`` within 1.5 GSD, or within the truth fit's own RMS residual where that is
larger (a COLMAP model is not rigid: where its points depart from the best similarity by 2-3 GSD,
no similarity is closer to the truth than that, and the truth itself is uncertain by about as
much). Confidently wrong: ``confident`` and not correct.
Scenes with an even seed form the development half, odd seeds the held-out half (fixed in
``sfm_scenes.SCENES`` before any result).

    python benchmarks/sfm.py            # all scenes -> benchmarks/results/sfm.{md,json}
    python benchmarks/sfm.py --quick    # two scenes -> benchmarks/work/sfm/quick/
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import os
import resource
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from coarse import machine_speed  # noqa: E402
from sfm_scenes import QUICK, SCENES, WORK, BuiltScene, build_scene  # noqa: E402

from tiereg.io.colmap import write_colmap_points_txt  # noqa: E402
from tiereg.io.text import write_xyz  # noqa: E402
from tiereg.transform import Transform  # noqa: E402

log = logging.getLogger("sfm")

RESULTS = HERE / "results"
PACKAGE_DATA = HERE.parent / "src" / "tiereg" / "data"
TIMEOUT_S = 900.0
MEMORY_LIMIT_BYTES = 6 * 1024**3
HEADING_TOL_DEG = TILT_TOL_DEG = 2.0
SCALE_TOL = 0.02
RMS_TOL_GSD = 1.5
THIN_RANGE = (300, 3000)
# negatives: the model of the first scene against the lidar of the second (another place)
NEGATIVES = (("farmland-10", "farmland-11"), ("suburban-12", "urban-15"),
             ("urban-14", "suburban-13"), ("forest-16", "forest-17"),
             ("mountains-18", "longyearbyen-23"), ("muscatatuck-20", "autzen-25"),
             ("longyearbyen-22", "mountains-19"), ("autzen-24", "suburban-13"),
             ("suburban-13", "suburban-12"), ("mountains-19", "mountains-18"))
QUICK_NEGATIVES = (("suburban-12", "autzen-24"),)


@dataclass(frozen=True)
class Case:
    name: str
    scene: str  # the scene the moving side comes from
    half: str
    variant: str
    moving: str
    reference: str
    n_points: int
    truth: str | None  # truth.json; None for a negative
    gsd: float  # reference units
    lidar_scene: str


@dataclass(frozen=True)
class Run:
    seconds: float
    peak_mb: float
    exit_code: int
    timed_out: bool
    traceback: bool
    stderr_tail: str


@dataclass(frozen=True)
class Row:
    case: Case
    run: Run
    true_scale: float  # reference units per model unit (NaN for a negative)
    confident: bool | None
    correct: bool
    heading_err_deg: float
    tilt_err_deg: float
    scale_err: float  # relative
    position_err_cells: float
    cell_size: float
    rms_gsd: float  # at the model's points, when the fine stage ran (else NaN)
    max_gsd: float
    fine_ran: bool
    note: str


def tiereg_command() -> str:
    exe = Path(sys.executable).parent / "tiereg"
    return str(exe) if exe.exists() else "tiereg"


def _limit_memory() -> None:  # runs in the child before exec
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT_BYTES, MEMORY_LIMIT_BYTES))


def _tree_rss(pid: int) -> int:
    import psutil

    try:
        p = psutil.Process(pid)
        procs = [p, *p.children(recursive=True)]
    except psutil.Error:
        return 0
    total = 0
    for q in procs:
        try:
            total += q.memory_info().rss
        except psutil.Error:
            pass
    return total


def run_tiereg(case: Case, out: Path, *, timeout_s: float = TIMEOUT_S,
               options: tuple[str, ...] = ()) -> Run:
    """``tiereg register`` on the case in a limited child process; RESULT.json into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    result = out / "RESULT.json"
    result.unlink(missing_ok=True)
    cmd = [tiereg_command(), "register", case.moving, case.reference, "-o", str(result),
           *options]
    (out / "command.txt").write_text(" ".join(cmd) + "\n")
    t0 = time.perf_counter()
    with open(out / "stdout.txt", "wb") as so, open(out / "stderr.txt", "wb") as se:
        proc = subprocess.Popen(cmd, stdout=so, stderr=se, preexec_fn=_limit_memory,
                                start_new_session=True)
    peak_tree, timed_out = 0, False
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            break
        peak_tree = max(peak_tree, _tree_rss(proc.pid))
        if time.perf_counter() - t0 > timeout_s and not timed_out:
            timed_out = True
            os.killpg(proc.pid, signal.SIGKILL)
        time.sleep(0.25)
    seconds = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here, not by Popen
    stderr = (out / "stderr.txt").read_text(errors="replace")
    peak_mb = max(usage.ru_maxrss / 1024.0, peak_tree / 1024.0**2)
    tail = " | ".join(line.strip() for line in stderr.strip().splitlines()[-2:])[:300]
    return Run(seconds, peak_mb, proc.returncode, timed_out,
               "Traceback (most recent call last)" in stderr, tail)


def _angles(T_est: Transform, T_true: Transform) -> tuple[float, float]:
    """(heading error, tilt error) in degrees: the rotation ``R_est R_true^T`` about the
    reference's vertical, and how far it tips the vertical."""
    dR = T_est.rotation @ T_true.rotation.T
    heading = np.degrees(np.arctan2(dR[1, 0] - dR[0, 1], dR[0, 0] + dR[1, 1]))
    tilt = np.degrees(np.arccos(np.clip(dR[2, 2], -1.0, 1.0)))
    return float(heading), float(tilt)


def score(case: Case, run: Run, result_path: Path, model_xyz: np.ndarray) -> Row:
    """The case's row: see the module docstring for what counts as correct."""
    nan = float("nan")
    res = json.loads(result_path.read_text()) if result_path.is_file() else None
    truth = json.loads(Path(case.truth).read_text()) if case.truth is not None else None
    if truth is None:
        true_scale = nan
    else:
        T_true = Transform(np.asarray(truth["T_ref_mov"]))
        true_scale = T_true.scale
    if res is None:
        return Row(case, run, true_scale, None, False, nan, nan, nan, nan, nan, nan, nan, False,
                   "no RESULT.json" + (" (timed out)" if run.timed_out else ""))
    confident = bool(res["confident"])
    note = "; ".join(res.get("reasons", []))[:200]
    fine_ran = any(s.get("name") == "fine" and s.get("method") not in (None, "none")
                   for s in res.get("stages", []))
    cell = float(res.get("cell_size") or nan)
    if case.truth is None:
        return Row(case, run, true_scale, confident, not confident, nan, nan, nan, nan, cell,
                   nan, nan, fine_ran, note)
    T_est = Transform(np.asarray(res["T_ref_mov"]))
    # the truth fit's own RMS residual over the model's points (GSD), where recorded
    rms_tol = max(RMS_TOL_GSD, float((truth.get("fit_points") or {}).get("rms_gsd") or 0.0))
    heading, tilt = _angles(T_est, T_true)
    ds = T_est.scale / T_true.scale - 1.0
    centre = model_xyz.mean(axis=0, keepdims=True)
    dxy = (T_est.apply(centre) - T_true.apply(centre))[0, :2]
    cells = float(np.hypot(*dxy) / cell)
    err = np.linalg.norm(T_est.apply(model_xyz) - T_true.apply(model_xyz), axis=1)
    rms, mx = float(np.sqrt(np.mean(err**2)) / case.gsd), float(err.max() / case.gsd)
    ok = (abs(heading) <= HEADING_TOL_DEG and tilt <= TILT_TOL_DEG and abs(ds) <= SCALE_TOL
          and cells <= 1.0 and (not fine_ran or rms <= rms_tol))
    return Row(case, run, true_scale, confident, bool(ok), heading, tilt, ds, cells, cell, rms,
               mx, fine_ran, note)


def _thin_count(name: str, n: int) -> int:
    rng = np.random.default_rng(sum(map(ord, name)))
    lo, hi = np.log(THIN_RANGE[0]), np.log(THIN_RANGE[1])
    return int(min(n, round(np.exp(rng.uniform(lo, hi)))))


def scene_cases(b: BuiltScene) -> tuple[list[Case], np.ndarray]:
    """The four cases of a reconstructed scene and the model's points."""
    from sfm_reconstruct import read_observations

    s = b.scene
    out = WORK / s.name / "moving"
    xyz = read_observations(b.model_dir).xyz
    thin_dir = out / "thin"
    n_thin = _thin_count(s.name, len(xyz))
    if not (thin_dir / "points3D.txt").is_file():
        pick = np.sort(np.random.default_rng(s.seed).choice(len(xyz), n_thin, replace=False))
        thin_dir.mkdir(parents=True, exist_ok=True)
        write_colmap_points_txt(thin_dir / "points3D.txt", xyz[pick])
    full = out / "points.xyz"
    if not full.is_file():
        write_xyz(full, xyz)
    lidar = WORK / s.name / "lidar.laz"
    partial = WORK / s.name / "lidar-partial.laz"
    truth = str(WORK / s.name / "truth.json")
    gsd = float(b.truth["gsd"])

    def case(variant, moving, ref, n):
        return Case(f"{s.name}/{variant}", s.name, s.half, variant, str(moving), str(ref), n,
                    truth, gsd, s.name)

    return [case("model", b.model_dir, lidar, len(xyz)),
            case("points-thin", thin_dir / "points3D.txt", lidar, n_thin),
            case("points-full", full, lidar, len(xyz)),
            case("partial", b.model_dir, partial, len(xyz))], xyz


def autzen_trim_cases() -> tuple[list[Case], np.ndarray] | None:
    """The shipped Autzen model against the shipped lidar (feet), with cameras and as points."""
    model = PACKAGE_DATA / "autzen_colmap"
    if not (model / "truth.json").is_file():
        return None
    from sfm_reconstruct import read_observations

    xyz = read_observations(model).xyz
    full = WORK / "autzen-trim" / "points.xyz"
    if not full.is_file():
        full.parent.mkdir(parents=True, exist_ok=True)
        write_xyz(full, xyz)
    truth = json.loads((model / "truth.json").read_text())
    lidar = PACKAGE_DATA / "autzen_trim.laz"
    mk = (lambda variant, moving: Case(f"autzen-trim/{variant}", "autzen-trim", "dev", variant,
                                       str(moving), str(lidar), len(xyz),
                                       str(model / "truth.json"), float(truth["gsd"]),
                                       "autzen-trim"))
    return [mk("model", model), mk("points-full", full)], xyz


def build_all(names: list[str]) -> dict[str, BuiltScene]:
    built = {}
    for s in SCENES:
        if s.name in names:
            t = time.perf_counter()
            built[s.name] = build_scene(s)
            b = built[s.name]
            log.info("%s built in %.0f s: %s registered of %d, %s points", s.name,
                     time.perf_counter() - t, b.reconstruction.get("n_registered"),
                     b.block["n_images"], b.reconstruction.get("n_points"))
    return built


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="two scenes, for development")
    parser.add_argument("--scenes", nargs="*", help="only these scenes (names as in the table)")
    parser.add_argument("--timeout", type=float, default=TIMEOUT_S)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    t_all = time.perf_counter()
    names = list(QUICK) if args.quick else [s.name for s in SCENES]
    if args.scenes:
        names = [n for n in names if n in args.scenes]
    built = build_all(names)
    t_build = time.perf_counter() - t_all
    cases: list[Case] = []
    points: dict[str, np.ndarray] = {}
    for name, b in built.items():
        if b.model_dir is not None:
            c, xyz = scene_cases(b)
            cases += c
            points[name] = xyz
    negatives = QUICK_NEGATIVES if args.quick else NEGATIVES
    for mov, ref in negatives:
        if mov in points and ref in built and built[ref].lidar is not None:
            s = built[mov].scene
            cases.append(Case(f"{mov}/negative:{ref}", mov, s.half, "negative",
                              str(built[mov].model_dir), str(WORK / ref / "lidar.laz"),
                              len(points[mov]), None, float(built[mov].truth["gsd"]), ref))
    if not args.quick and not args.scenes:
        extra = autzen_trim_cases()
        if extra:
            cases += extra[0]
            points["autzen-trim"] = extra[1]
    out_root = WORK / ("quick" if args.quick else "runs")
    rows = []
    for case in cases:
        out = out_root / case.name.replace("/", "__").replace(":", "_")
        run = run_tiereg(case, out, timeout_s=args.timeout)
        row = score(case, run, out / "RESULT.json", points[case.scene])
        rows.append(row)
        log.info("%-40s exit %d  %6.1f s  %6.0f MB  correct %s  confident %s  %s", case.name,
                 run.exit_code, run.seconds, run.peak_mb, row.correct, row.confident,
                 run.stderr_tail[:80] if run.exit_code not in (0, 3) else row.note[:80])
    # the fine stage alone, started at the truth: what the data allow (not in the counts)
    attainable = []
    for case in cases:
        if case.variant == "model" and case.truth is not None:
            out = out_root / (case.name.replace("/", "__") + "__from-truth")
            run = run_tiereg(case, out, timeout_s=args.timeout,
                             options=("--coarse", "none", "--initial", case.truth))
            attainable.append(score(case, run, out / "RESULT.json", points[case.scene]))
            log.info("%-40s from the truth: RMS %.2f GSD, confident %s", case.name,
                     attainable[-1].rms_gsd, attainable[-1].confident)
    seconds = time.perf_counter() - t_all
    from sfm_report import write_report

    target = out_root if args.quick or args.scenes else RESULTS  # the results: every scene
    write_report(rows, attainable, built, target, seconds=seconds, build_seconds=t_build,
                 speed=machine_speed(), command=" ".join(["python", "benchmarks/sfm.py",
                                                           *sys.argv[1:]]),
                 date=datetime.date.today().isoformat())
    print(f"wrote {target / 'sfm.md'} ({len(rows)} cases, {seconds / 60:.1f} min)")


if __name__ == "__main__":
    main()
