"""Coarse-registration benchmark: tiereg's coarse methods and peers on simulated scenes.

The protocol follows the coarse-registration literature's (the share of heading x scale
parameter pairs a method recovers) on more varied ground: five kinds of synthetic world and real
surfaces, any heading, scales 0.25-4 (feet vs metres included), any shift, partial overlap down
to 30 % of the block, and negative cases whose tie points come from a world the lidar never saw.
Case numbers split the cases: even ones are the development half (settings are chosen on them),
odd ones the held-out half (only reported).

    python benchmarks/coarse.py            # full run -> benchmarks/results/coarse.{md,json,png}
    python benchmarks/coarse.py --methods auto --no-peers --half heldout   # -> work/heldout/
    python benchmarks/coarse.py --quick    # a few cases -> benchmarks/work/ (development)
    python benchmarks/coarse.py --timing   # auto (as `tiereg overlap`) on the synthetic scenes,
                                           # one case at a time on all cores
                                           # -> benchmarks/results/coarse-timing.md

A case is *correct* when the heading is within 2 deg, the scale within 2 % and the horizontal
position of the block centre within one coarse cell of the truth. A negative case is correct when
the answer is not confident. *Confidently wrong*: marked confident and not correct, the number
that matters most. Peers give no confidence; their wrong answers are counted as wrong only.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from peers import PEERS_IMAGE, run_open3d_fpfh_ransac  # noqa: E402

from tiereg import register  # noqa: E402
from tiereg.grid import GridSpec, cell_size_from_density, rasterize  # noqa: E402
from tiereg.io import open_points  # noqa: E402
from tiereg.overlap import check_overlap  # noqa: E402
from tiereg.reference import Reference, prepare_reference  # noqa: E402
from tiereg.simulate import (  # noqa: E402
    KINDS,
    HiddenTransform,
    LidarSurvey,
    SceneSpec,
    make_scene,
    make_world,
    write_scene,
)
from tiereg.transform import Transform  # noqa: E402

WORK = HERE / "work" / "coarse"
RESULTS = HERE / "results"
SCALES = (0.25, 0.5, 1.0, 2.0, 3.2808, 4.0)  # model units per reference unit; 3.2808: feet
HEADINGS_PER_SCALE = 3  # one per third of the circle, random inside it
TIEREG_METHODS = ("auto", "search", "moments", "qafmt", "afmt", "fmt", "qafmt-classic",
                  "afmt-classic", "fmt-classic", "pomf")
HEADING_TOL_DEG, SCALE_TOL = 2.0, 0.02
OPEN3D_EVERY = 4  # Open3D runs on every fourth case
FULL_METHODS = ("auto", "search", "overlap")  # every case; the other tiereg methods on a sample:
SAMPLE_EVERY = 3  # every third case (and every negative case) keeps the run under 30 minutes
# --timing: a case during which the host took more than this share of the cores' time (steal
# time, on a virtual machine) is timed again, up to RETIMES runs, and the fastest run is kept
MAX_STOLEN, RETIMES = 0.05, 3


@dataclass(frozen=True)
class Case:
    scene: str
    index: int
    hidden: HiddenTransform
    overlap: float
    negative: bool = False


@dataclass
class Outcome:
    method: str
    case: Case
    correct: bool
    confident: bool | None
    heading_err_deg: float
    scale_err: float
    horiz_err_cells: float
    seconds: float
    note: str = ""
    stolen: float = float("nan")  # share of the cores' time the host took during the run
    loop_ms: float = float("nan")  # the speed line's loop just before the run (--timing)


# ------------------------------------------------------------------------------------- scenes
LOOKALIKE_KIND: dict[str, str] = {}


def scene_specs(quick: bool) -> dict[str, SceneSpec]:
    survey = LidarSurvey(density_per_m2=0.5 if quick else 1.0)
    kinds = ("suburban", "mountains") if quick else KINDS
    specs = {k: SceneSpec(kind=k, seed=10 + i, survey=survey) for i, k in enumerate(kinds)}
    if not quick:
        try:
            from real_worlds import LOOKALIKE_KIND as lookalike
            from real_worlds import REAL_WORLDS, real_scene_spec

            LOOKALIKE_KIND.update(lookalike)
            specs.update({name: real_scene_spec(name, 20 + i)
                          for i, name in enumerate(REAL_WORLDS)})
        except ImportError:  # the real surfaces are optional
            pass
    return specs


def load_world(name: str, spec: SceneSpec):
    if name in KINDS:
        return make_world(spec.kind, size_m=spec.world_size_m, cell=spec.world_cell_m,
                          seed=spec.seed)
    from real_worlds import load_real_world

    return load_real_world(name)


def make_cases(name: str, index0: int, rng: np.random.Generator, quick: bool) -> list[Case]:
    cases = []
    scales = (1.0, 3.2808, 0.5) if quick else SCALES
    per = 2 if quick else HEADINGS_PER_SCALE  # one heading per 360/per degrees
    for scale in scales:
        for q in range(per):
            heading = float(rng.uniform(0, 360 / per) + q * 360 / per)
            hidden = replace(HiddenTransform.random(rng), heading_deg=heading, scale=scale)
            cases.append(Case(name, index0 + len(cases), hidden, float(rng.uniform(0.3, 1.0))))
    cases.append(Case(name, index0 + len(cases), HiddenTransform.random(rng), 1.0, negative=True))
    return cases


# ------------------------------------------------------------------------------------ methods
def evaluate(T_est: Transform, case: Case, scene, cell: float) -> tuple[bool, float, float, float]:
    """(correct, heading error deg, relative scale error, horizontal error in cells)."""
    p_est, p_true = T_est.parameters(), scene.T_ref_mov.parameters()
    dk = (np.degrees(p_est.kappa - p_true.kappa) + 180.0) % 360.0 - 180.0
    ds = p_est.scale / p_true.scale - 1.0
    centre = scene.moving.mean(axis=0, keepdims=True)
    dxy = (T_est.apply(centre) - scene.T_ref_mov.apply(centre))[0, :2]
    cells = float(np.hypot(*dxy) / cell)
    ok = abs(dk) <= HEADING_TOL_DEG and abs(ds) <= SCALE_TOL and cells <= 1.0
    return ok, float(dk), float(ds), cells


def run_tiereg(method: str, scene, ref: Reference) -> tuple[Transform, bool, float, str]:
    """``method``: a coarse method, or ``overlap``: what ``tiereg overlap`` computes (auto's
    coarse stage, then the share on the reference and the outline)."""
    t = time.perf_counter()
    if method == "overlap":
        result = check_overlap(scene.moving, ref, coarse="auto").registration
    else:
        result = register(scene.moving, ref, coarse=method, fine="none")
    return result.T_ref_mov, result.confident, time.perf_counter() - t, "; ".join(result.reasons)


def stolen_seconds() -> float:
    """CPU time the host has taken from this machine's cores (Linux's steal time: a virtual
    CPU ready to run while the hypervisor runs something else); NaN where not known."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


def timed_tiereg(method: str, scene, ref: Reference, *, retime: bool):
    """:func:`run_tiereg` and the share of the cores' time the host took meanwhile; with
    ``retime``, the speed line's loop just before (:func:`loop_ms`), and run again while that
    share exceeds :data:`MAX_STOLEN` (at most :data:`RETIMES` runs), keeping the fastest (the
    answer is the same every time). Returns ``(T, confident, seconds, note, stolen, loop_ms,
    runs)``."""
    runs = []
    for _ in range(RETIMES if retime else 1):
        loop = loop_ms(number=2) if retime else float("nan")
        before = stolen_seconds()
        T, conf, sec, note = run_tiereg(method, scene, ref)
        runs.append((sec, (stolen_seconds() - before) / ((os.cpu_count() or 1) * sec),
                     loop, T, conf, note))
        if not runs[-1][1] > MAX_STOLEN:  # NaN (not known) counts as not stolen
            break
    sec, stolen, loop, T, conf, note = min(runs, key=lambda r: r[0])
    return T, conf, sec, note, stolen, loop, len(runs)


def _pixel_to_map(spec: GridSpec) -> np.ndarray:
    """3x3: (row, col, 1) -> (x, y, 1) at cell centres."""
    c = spec.cell_size
    return np.array([[0.0, c, spec.x0 + 0.5 * c], [-c, 0.0, spec.y0 - 0.5 * c], [0, 0, 1.0]])


def run_image_peer(name: str, scene, ref: Reference, cell: float) -> tuple[Transform, float, str]:
    """Grids as a user would make them: lidar at the tie-point cell, tie points at their own."""
    ref_grid = ref.grid(cell)
    mov_cell = cell_size_from_density(scene.moving)
    lo, hi = scene.moving.min(axis=0), scene.moving.max(axis=0)
    mov_spec = GridSpec.from_bounds(lo[0], lo[1], hi[0], hi[1], mov_cell)
    mov = rasterize(scene.moving, mov_spec, stats=("median",))
    est = PEERS_IMAGE[name](ref_grid["mean"], mov["median"])
    G = _pixel_to_map(ref_grid.spec) @ est.H_ref_mov @ np.linalg.inv(_pixel_to_map(mov_spec))
    s = float(np.sqrt(abs(np.linalg.det(G[:2, :2]))))
    kappa = float(np.arctan2(G[1, 0], G[0, 0]))
    t_xy = G[:2, 2] + ref.origin[:2]
    T = Transform.from_parameters(scale=s, kappa=kappa, translation=(*t_xy, ref.origin[2]))
    return T, est.seconds, est.note


def run_open3d(scene, ref: Reference, cell: float) -> tuple[Transform, float, str]:
    base = ref.base
    rows, cols = np.nonzero(base.mask)
    x, y = base.spec.xy(rows, cols)
    cloud = np.column_stack([x, y, base["mean"][rows, cols]]) + ref.origin
    est = run_open3d_fpfh_ransac(scene.moving, cloud, voxel=cell)
    try:
        T = Transform(est.T_ref_mov)
    except Exception as exc:  # a collapsed or reflected estimate
        return Transform.identity(), est.seconds, f"invalid transform: {exc}"
    return T, est.seconds, est.note


# ---------------------------------------------------------------------------------------- run
def run(quick: bool, with_open3d: bool, workers: int,
        methods: tuple[str, ...] = TIEREG_METHODS, *, scenes: tuple[str, ...] | None = None,
        peers: bool = True, retime: bool = False, half: str | None = None
        ) -> tuple[list[Outcome], dict]:
    """All scenes (or those named), ``workers`` at a time (each scene in its own process).
    ``retime``: probe the machine's speed before each run and time again the runs the host
    took time from (:func:`timed_tiereg`). ``half``: ``"dev"`` (even case numbers) or
    ``"heldout"`` (odd) only."""
    WORK.mkdir(parents=True, exist_ok=True)
    specs = scene_specs(quick)  # also fills LOOKALIKE_KIND, which the workers need passed
    jobs = [(i, name, spec, quick, with_open3d and peers, LOOKALIKE_KIND.get(name, spec.kind),
             methods, peers, retime, half)
            for i, (name, spec) in enumerate(specs.items()) if scenes is None or name in scenes]
    if workers > 1:
        from multiprocessing import get_context

        with get_context("spawn").Pool(workers) as pool:
            parts = pool.map(run_scene, jobs, chunksize=1)
    else:
        parts = [run_scene(job) for job in jobs]
    outcomes = [o for part, _ in parts for o in part]
    meta = {"scenes": {k: v for _, m in parts for k, v in m.items()}, "workers": workers}
    return outcomes, meta


def run_scene(job) -> tuple[list[Outcome], dict]:
    index, name, spec, quick, with_open3d, lookalike, methods, peers, retime, half = job
    rng = np.random.default_rng([2026, index])
    outcomes: list[Outcome] = []
    meta: dict = {"scenes": {}}
    t0 = time.perf_counter()
    world = load_world(name, spec)
    base_scene = make_scene(spec, world=world)
    laz = WORK / f"{name}-{spec.seed}{'-quick' if quick else ''}"
    if not (laz / "reference.laz").exists():
        write_scene(base_scene, laz)
    ref_source = open_points(laz / "reference.laz")
    cell = cell_size_from_density(base_scene.tie_points.true_xyz)
    # first returns, at an eighth of the tie cell (what `tiereg register` would choose)
    ref = prepare_reference(ref_source, base_cell=cell / 8)
    meta["scenes"][name] = {"kind": spec.kind, "cell": cell,
                            "lidar_points": ref_source.info.count,
                            "tie_points": len(base_scene.moving),
                            "setup_s": round(time.perf_counter() - t0, 1)}
    cases = make_cases(name, 1000 * index, rng, quick)
    if half is not None:  # the development half: even case numbers; held out: odd ones
        cases = [c for c in cases if (c.index % 2 == 0) == (half == "dev")]
    for case in cases:
        case_spec = replace(spec, hidden=case.hidden, overlap=case.overlap)
        if case.negative:  # tie points from a synthetic world of the same character
            case_spec = replace(case_spec, kind=lookalike, tie_world_seed=spec.seed + 1000)
        scene = make_scene(case_spec, world=world, lidar=base_scene.lidar)
        for method in methods:
            if not (method in FULL_METHODS or case.negative or case.index % SAMPLE_EVERY == 0):
                continue
            T, conf, sec, note, stolen, loop, runs = timed_tiereg(method, scene, ref,
                                                                  retime=retime)
            outcomes.append(replace(_outcome(f"tiereg {method}", case, scene, T, conf, sec,
                                             note, cell), stolen=stolen, loop_ms=loop))
            timed = meta["scenes"][name]
            timed["retimed"] = timed.get("retimed", 0) + (runs > 1)
        for peer in PEERS_IMAGE if peers else ():
            T, sec, note = run_image_peer(peer, scene, ref, cell)
            outcomes.append(_outcome(peer, case, scene, T, None, sec, note, cell))
        if with_open3d and case.index % OPEN3D_EVERY == 0:  # the slowest peer: a sample
            T, sec, note = run_open3d(scene, ref, cell)
            outcomes.append(_outcome("open3d_fpfh_ransac", case, scene, T, None, sec, note,
                                     cell))
    print(f"{name}: {len(cases)} cases done", file=sys.stderr)
    return outcomes, meta["scenes"]


def _outcome(method, case, scene, T, confident, seconds, note, cell) -> Outcome:
    ok, dk, ds, cells = evaluate(T, case, scene, cell)
    if case.negative:
        ok = confident is False
    return Outcome(method, case, ok, confident, dk, ds, cells, seconds, note[:200])


# ------------------------------------------------------------------------------------ reports
def summarize(outcomes: list[Outcome]) -> dict:
    out: dict = {}
    for m in dict.fromkeys(o.method for o in outcomes):
        pos = [o for o in outcomes if o.method == m and not o.case.negative]
        neg = [o for o in outcomes if o.method == m and o.case.negative]
        good = [o for o in pos if o.correct]
        out[m] = {
            "cases": len(pos),
            "correct": len(good),
            "confidently_wrong": sum(1 for o in pos + neg if o.confident and not o.correct)
            if pos and pos[0].confident is not None else None,
            "confident": sum(1 for o in pos if o.confident) if pos and pos[0].confident
            is not None else None,
            "negatives": len(neg),
            "negatives_rejected": sum(1 for o in neg if o.correct),
            "median_heading_err_deg": float(np.median([abs(o.heading_err_deg) for o in good]))
            if good else None,
            "median_scale_err_pct": float(np.median([abs(o.scale_err) * 100 for o in good]))
            if good else None,
            "median_horiz_err_cells": float(np.median([o.horiz_err_cells for o in good]))
            if good else None,
            "median_seconds": float(np.median([o.seconds for o in pos + neg])),
            "by_scene": {s: [sum(o.correct for o in pos if o.case.scene == s),
                             sum(1 for o in pos if o.case.scene == s)]
                         for s in dict.fromkeys(o.case.scene for o in pos)},
            "by_scale": {f"{sc:g}": [sum(o.correct for o in pos if o.case.hidden.scale == sc),
                                     sum(1 for o in pos if o.case.hidden.scale == sc)]
                         for sc in sorted({o.case.hidden.scale for o in pos})},
        }
    return out


def _fmt(v, spec=".2f"):
    return "-" if v is None else format(v, spec)


def write_report(outcomes: list[Outcome], meta: dict, out_dir: Path, seconds: float) -> None:
    # a peer that could not run anywhere is left out of the tables, and the report says so
    missing = sorted({o.method for o in outcomes} - {o.method for o in outcomes
                                                     if "unavailable:" not in o.note})
    outcomes = [o for o in outcomes if o.method not in missing]
    summary = summarize(outcomes)
    ran = {o.method for o in outcomes}
    out_dir.mkdir(parents=True, exist_ok=True)
    meta = {**meta, "date": datetime.datetime.now(datetime.timezone.utc).isoformat(
        timespec="seconds")}
    lines = [
        "# Coarse-registration benchmark", "",
        f"- date: {meta['date']}; "
        f"machine: {platform.machine()}, Python {platform.python_version()}; "
        f"total run time {seconds / 60:.1f} min; cases: {meta.get('selection', 'both halves')} "
        "(development half: even case numbers, held-out half: odd ones)",
        "- scenes: " + ", ".join(f"{k} ({v['tie_points']} tie points, "
                                 f"{v['lidar_points']:,} lidar points, cell {v['cell']:g} m)"
                                 for k, v in meta["scenes"].items()),
        f"- cases per scene: scales {', '.join(f'{s:g}' for s in SCALES)} x "
        f"{HEADINGS_PER_SCALE} headings (one per {360 // HEADINGS_PER_SCALE} deg sector, random "
        "inside), random shift, "
        "overlap U(0.3, 1), small random tilt; plus one negative case per scene (tie points "
        "from another world)",
        f"- tiereg {' and '.join(m for m in FULL_METHODS if f'tiereg {m}' in ran)}"
        f"{' and the image peers' if set(PEERS_IMAGE) & ran else ''} run on every case; the other "
        f"tiereg methods on every {SAMPLE_EVERY}rd case and the negative cases, Open3D on every "
        f"{OPEN3D_EVERY}th case (the counts show how many)",
        *([f"- re-run this time: {', '.join(sorted({o.method for o in outcomes} - set(kept)))}; "
           f"kept from the run of {meta['kept']['from']}: {', '.join(kept)}"]
          if (kept := meta.get("kept", {}).get("methods")) else []),
        f"- correct: heading within {HEADING_TOL_DEG:g} deg, scale within "
        f"{SCALE_TOL:.0%}, block centre within one coarse cell; confidently wrong: marked "
        "confident and not correct (peers give no confidence)",
        f"- times: {meta.get('workers', 1)} scene(s) at a time, each in its own process, on "
        f"{os.cpu_count()} cores; `coarse-timing.md` gives auto's time with the cores to itself",
        *([f"- left out, not installed on this machine: {', '.join(missing)} "
           "(`make bench-peers` installs the peers)"] if missing else []), "",
        "| method | correct | rate | confidently wrong | confident | negatives rejected | "
        "median heading err (deg) | median scale err (%) | median position err (cells) | "
        "median s/case |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for m, s in summary.items():
        lines.append(
            f"| {m} | {s['correct']}/{s['cases']} | {s['correct'] / max(s['cases'], 1):.0%} | "
            f"{_fmt(s['confidently_wrong'], 'd')} | {_fmt(s['confident'], 'd')} | "
            f"{s['negatives_rejected']}/{s['negatives']} | "
            f"{_fmt(s['median_heading_err_deg'])} | {_fmt(s['median_scale_err_pct'])} | "
            f"{_fmt(s['median_horiz_err_cells'])} | {s['median_seconds']:.2f} |")
    scenes = list(meta["scenes"])
    lines += ["", "## Correct by scene", "", "| method | " + " | ".join(scenes) + " |",
              "|---|" + "---:|" * len(scenes)]
    for m, s in summary.items():
        lines.append(f"| {m} | " + " | ".join(
            f"{s['by_scene'].get(n, [0, 0])[0]}/{s['by_scene'].get(n, [0, 0])[1]}"
            for n in scenes) + " |")
    scale_keys = list(next(iter(summary.values()))["by_scale"]) if summary else []
    lines += ["", "## Correct by scale", "", "| method | " + " | ".join(scale_keys) + " |",
              "|---|" + "---:|" * len(scale_keys)]
    for m, s in summary.items():
        lines.append(f"| {m} | " + " | ".join("{}/{}".format(*s["by_scale"].get(k, [0, 0]))
                                              for k in scale_keys) + " |")
    lines += ["", "![success against heading and scale](coarse.png)", ""]
    (out_dir / "coarse.md").write_text("\n".join(lines) + "\n")
    raw = [{"method": o.method, "scene": o.case.scene, "case": o.case.index,
            "negative": o.case.negative, "heading_deg": o.case.hidden.heading_deg,
            "scale": o.case.hidden.scale, "overlap": o.case.overlap, "correct": o.correct,
            "confident": o.confident, "heading_err_deg": o.heading_err_deg,
            "scale_err": o.scale_err, "horiz_err_cells": o.horiz_err_cells,
            "seconds": o.seconds, "note": o.note} for o in outcomes]
    (out_dir / "coarse.json").write_text(json.dumps({"meta": meta, "summary": summary,
                                                     "outcomes": raw}, indent=1,
                                                    default=_json_number) + "\n")
    plot(outcomes, out_dir / "coarse.png")


def keep_others(outcomes: list[Outcome], path: Path) -> tuple[list[Outcome], dict]:
    """The new outcomes, and those of the methods they lack from an earlier run's JSON."""
    last = json.loads(path.read_text())
    ran = {o.method for o in outcomes}
    kept = [Outcome(r["method"], Case(r["scene"], r["case"],
                                      HiddenTransform(heading_deg=r["heading_deg"],
                                                      scale=r["scale"]),
                                      r["overlap"], r["negative"]),
                    r["correct"], r["confident"], r["heading_err_deg"], r["scale_err"],
                    r["horiz_err_cells"], r["seconds"], r["note"])
            for r in last["outcomes"] if r["method"] not in ran]
    methods = sorted({o.method for o in kept})
    date = last["meta"].get("date") or next(  # results written before the JSON kept the date
        (line.split(";")[0].removeprefix("- date: ") for line in
         path.with_suffix(".md").read_text().splitlines() if line.startswith("- date: ")), "?")
    return outcomes + kept, {"methods": methods, "from": date}


def _json_number(o):
    if isinstance(o, (np.integer, np.floating, np.bool_)):
        return o.item()
    raise TypeError(type(o).__name__)


def plot(outcomes: list[Outcome], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5))
    methods = list(dict.fromkeys(o.method for o in outcomes))
    bins = np.arange(0, 361, 45)
    for m in methods:
        pos = [o for o in outcomes if o.method == m and not o.case.negative]
        h = np.array([o.case.hidden.heading_deg for o in pos])
        ok = np.array([o.correct for o in pos], float)
        idx = np.digitize(h, bins) - 1
        rate = [ok[idx == i].mean() if (idx == i).any() else np.nan for i in range(len(bins) - 1)]
        ax1.plot(bins[:-1] + 22.5, np.array(rate) * 100, marker="o", label=m)
        scales = sorted({o.case.hidden.scale for o in pos})
        rate = [np.mean([o.correct for o in pos if o.case.hidden.scale == s]) for s in scales]
        ax2.plot(scales, np.array(rate) * 100, marker="o", label=m)
    ax1.set(xlabel="hidden heading (deg)", ylabel="correct (%)", ylim=(-5, 105),
            title="success against heading")
    ax2.set(xlabel="hidden scale (model units per metre)", ylabel="correct (%)", xscale="log",
            ylim=(-5, 105), title="success against scale")
    ax2.minorticks_off()  # log-axis minor labels would overprint the scale labels
    ax2.set_xticks(SCALES, [f"{s:g}" for s in SCALES])
    ax1.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def loop_ms(number: int = 10) -> float:
    """The speed line's loop (``sum(range(100_000))``), best of five, in milliseconds."""
    import timeit

    return min(timeit.repeat("sum(range(100_000))", number=number, repeat=5)) / number * 1e3


def machine_speed() -> str:
    """Two fixed workloads, best of five, so that timings from different machines compare: the
    interpreter (a loop) and the transforms (an FFT pair) the sweep spends its time in."""
    import timeit

    loop = loop_ms()
    fft = min(timeit.repeat("irfft2(rfft2(a))", setup="import numpy as np; from scipy.fft import "
                            "rfft2, irfft2; a = np.random.default_rng(0).random((512, 512))",
                            number=10, repeat=5)) / 10
    return (f"machine speed: `sum(range(100_000))` {loop:.2f} ms, a 512 x 512 FFT pair "
            f"{fft * 1e3:.2f} ms (lower is faster)")


def write_timing(outcomes: list[Outcome], meta: dict, path: Path, seconds: float) -> None:
    """Seconds per case of auto, one case at a time with the machine's cores to itself."""
    def row(name: str, sel: list[Outcome]) -> str:
        t = np.array([o.seconds for o in sel])
        ok = sum(o.correct for o in sel)
        return (f"| {name} | {len(sel)} | {ok}/{len(sel)} | {np.median(t):.2f} | "
                f"{np.percentile(t, 90):.2f} | {t.max():.2f} | {int((t >= 5.0).sum())} |")

    date = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    stolen = np.array([o.stolen for o in outcomes])
    loops = np.array([o.loop_ms for o in outcomes])
    retimed = sum(v.get("retimed", 0) for v in meta["scenes"].values())
    lines = [
        "# Coarse registration: time per case (`--coarse auto`, as `tiereg overlap` runs it)",
        "",
        f"- date: {date}; machine: {platform.machine()}, {os.cpu_count()} cores, Python "
        f"{platform.python_version()}; total run time {seconds / 60:.1f} min",
        f"- {meta['speed']}",
        "- one case at a time, the cores to itself (its threads use them all); the lidar is "
        "read and gridded once per scene, before the clock starts, as the acceptance asks",
        "- each case is `tiereg.overlap.check_overlap` (`tiereg overlap`): the coarse stage "
        "(`auto`), then the tie points' share on the lidar and the overlap's outline; `correct` "
        "as in `coarse.md`",
        "- the coarse benchmark's simulated scenes: " + ", ".join(
            f"{k} ({v['tie_points']} tie points, cell {v['cell']:g} m)"
            for k, v in meta["scenes"].items()),
        "- the cases of `coarse.md` (the same seeds), negative cases included",
        f"- the host's steal time (a virtual machine's cores taken by others): a case during "
        f"which it took more than {MAX_STOLEN:.0%} of the cores' time was timed again, up to "
        f"{RETIMES} runs, and its fastest run kept ({retimed} of {len(outcomes)} cases); "
        + (f"stolen during the kept runs: median {np.nanmedian(stolen):.1%}, at most "
           f"{np.nanmax(stolen):.1%} (`stolen` below)" if np.isfinite(stolen).any()
           else "not known on this system"),
        f"- the speed line's loop just before each case (`loop ms`, best of five): median "
        f"{np.nanmedian(loops):.2f} ms, {np.nanmin(loops):.2f}-{np.nanmax(loops):.2f} ms", "",
        "| scene | cases | correct | median s | p90 s | max s | 5 s or more |",
        "|---|---:|---:|---:|---:|---:|---:|",
        *(row(sc, [o for o in outcomes if o.case.scene == sc])
          for sc in dict.fromkeys(o.case.scene for o in outcomes)),
        row("all", outcomes), "",
        "| scene | case | scale | overlap | correct | confident | s | stolen | loop ms |",
        "|---|---:|---:|---:|---|---|---:|---:|---:|",
        *(f"| {o.case.scene} | {o.case.index % 1000} | {o.case.hidden.scale:g} | "
          f"{o.case.overlap:.2f} | {o.correct} | {o.confident} | {o.seconds:.2f} | "
          f"{o.stolen:.1%} | {o.loop_ms:.2f} |" for o in outcomes), "",
    ]
    path.write_text("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a few cases, results to work/")
    parser.add_argument("--no-open3d", action="store_true", help="skip the Open3D baseline")
    parser.add_argument("--workers", type=int, default=2, help="scenes run in parallel")
    parser.add_argument("--methods", default=",".join(TIEREG_METHODS),
                        help="tiereg coarse methods, comma-separated")
    parser.add_argument("--timing", action="store_true",
                        help="auto alone on the synthetic scenes, one case at a time on all "
                             "cores -> results/coarse-timing.md")
    parser.add_argument("--half", choices=("dev", "heldout"),
                        help="the development half (even case numbers) or the held-out half "
                             "(odd) only, results to work/")
    parser.add_argument("--no-peers", action="store_true",
                        help="tiereg's methods only, results to work/")
    parser.add_argument("--keep-others", action="store_true",
                        help="methods not run this time keep their outcomes from the last "
                             "results (after a change that touches only the methods run)")
    args = parser.parse_args()
    t0 = time.perf_counter()
    if args.timing:
        # a shared machine's speed can drift within a run (here by two to three times within an
        # hour): measured before and after, and before each case
        speed = machine_speed()
        outcomes, meta = run(False, with_open3d=False, workers=1, methods=("overlap",),
                             scenes=KINDS, peers=False, retime=True)
        meta["speed"] = f"{speed}; at the end of the run: {machine_speed().split(': ', 1)[1]}"
        write_timing(outcomes, meta, RESULTS / "coarse-timing.md", time.perf_counter() - t0)
        print(RESULTS / "coarse-timing.md")
        return
    outcomes, meta = run(args.quick, with_open3d=not args.no_open3d, workers=args.workers,
                         methods=tuple(args.methods.split(",")), peers=not args.no_peers,
                         half=args.half)
    if args.keep_others:
        outcomes, meta["kept"] = keep_others(outcomes, RESULTS / "coarse.json")
    partial = args.quick or args.half or args.no_peers
    meta["selection"] = args.half or "both halves"
    out_dir = WORK / (args.half or "all") if partial else RESULTS
    write_report(outcomes, meta, out_dir, time.perf_counter() - t0)
    print(out_dir / "coarse.md")


if __name__ == "__main__":
    main()
