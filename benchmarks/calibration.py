"""Cross-aided camera calibration on simulated blocks with known cameras.

Each case is a simulated image block (a world, its lidar, a camera with distortion, a flight
plan) made into what structure from motion would have made of it with an uncalibrated camera:
the focal length 2 % off (either way), no radial distortion, the principal point at the image
centre (the true one is up to 1 % of the image off it), the poses and points bundle-adjusted
with those intrinsics held. The block kinds: nadir strips over flat ground, nadir strips over
relief, tilted strips (alternately 8-12 degrees forward and backward), cross strips; 15 to 60
images. The cases are split into a dev half (the settings were chosen on it) and a held-out half
(only reported). Side by side, in the lidar's frame:

(a) registration only: the flawed model placed by the similarity that best fits its points to
    the true ones (a registration as good as the bent model allows; ``tiereg register`` itself is
    not yet reliable on strongly bent models, and is being improved separately);
(b) pycolmap's bundle adjustment refining the intrinsics (focal length, principal point, k1, k2),
    poses and points from the images alone, then placed as (a);
(c) the same with the lidar control points (:func:`tiereg.control.select_control_points`: tie
    points on strictly planar patches, one per cell of a 12 x 12 grid, the check points left
    out) as fixed ground control: their height from the lidar, their plan position from (a);
(d) ``tiereg calibrate`` from (a)'s registration;
(e) the floor the data allow: ``tiereg calibrate`` of the model adjusted with the true camera
    (images only, intrinsics held at the truth, placed as (a)), refining only the poses and the
    points against the lidar. No method that must find the intrinsics can expect to place the
    cameras better than (e);
(f) a model with nothing to calibrate: ``tiereg calibrate`` of the same true-camera model with
    every intrinsic free, which should leave them where they are, within their precision.

Measured per case: focal length error (%), k1 error (%), principal point error (px), camera
centre RMS (m, against the true centres; also less their mean error, the common offset that
the focal length's error times the flying height makes), the height residuals at the check
points (those ``tiereg calibrate`` held out; their RMS after the points off the lidar, such as
vehicles, are left out, and NMAD) against the tie-point noise: the same residuals of the model
adjusted with the true camera. What (d) held or flagged, its time and the memory it added.
Then the speed block (50 images, 5,000 tie points): time and peak memory in a fresh process,
one adjustment with the lidar costs in Python (the first version) and native, on one and two
threads, and the same adjustment with ``scipy.optimize.least_squares``.

    python benchmarks/calibration.py          # -> benchmarks/results/calibration.md (+ .json)
    python benchmarks/calibration.py --quick  # two small cases -> benchmarks/work/ (development)
"""

from __future__ import annotations

import argparse
import copy
import datetime
import json
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS, WORK = HERE / "results", HERE / "work"
sys.path.insert(0, str(HERE))

from calibration_blocks import PeakMemory, make_block, truth_camera  # noqa: E402
from calibration_solvers import speed_block  # noqa: E402

from tiereg.calibrate import calibrate  # noqa: E402
from tiereg.calibrate.lidar import LidarPatches, lidar_reference  # noqa: E402
from tiereg.calibrate.model import transform_model  # noqa: E402
from tiereg.control import select_control_points  # noqa: E402
from tiereg.robust import nmad  # noqa: E402
from tiereg.simulate.cameras import (  # noqa: E402
    CameraModel,
    FlightPlan,
    fitted_registration,
    flawed_model,
)
from tiereg.transform import Transform  # noqa: E402

FOCAL_TOL, K1_TOL, PP_TOL_PX, CENTRE_TOL_M, CHECK_TOL = 1e-3, 0.10, 1.0, 0.2, 1.2
METHODS = ("a", "b", "c", "d", "e", "f")
METHOD_NAMES = {"a": "(a) registered only", "b": "(b) pycolmap BA, images only",
                "c": "(c) pycolmap BA, lidar GCPs", "d": "(d) tiereg calibrate",
                "e": "(e) true camera, tiereg calibrate of poses",
                "f": "(f) true camera, tiereg calibrate"}


@dataclass(frozen=True)
class Case:
    name: str
    half: str  # "dev" or "held-out"
    kind: str  # block kind: flat nadir, relief nadir, tilted strips, cross strips
    world: str
    flat: bool
    plan: FlightPlan
    seed: int


def _plan(strips, ips, height, *, cross=False, tilt=0.0) -> FlightPlan:
    return FlightPlan(strips=strips, images_per_strip=ips, flying_height_m=height, cross=cross,
                      tilt_deg=tilt)


# (kind, world, flat, plan): 6 per kind, alternately dev and held-out
_SPECS = [
    ("flat nadir", "suburban", True, _plan(3, 5, 400)),
    ("flat nadir", "urban", True, _plan(4, 6, 500)),
    ("flat nadir", "suburban", True, _plan(3, 8, 500)),
    ("flat nadir", "suburban", True, _plan(5, 8, 400)),
    ("flat nadir", "urban", True, _plan(3, 5, 500, cross=True)),
    ("flat nadir", "suburban", True, _plan(6, 10, 600)),
    ("relief nadir", "suburban", False, _plan(3, 6, 400)),
    ("relief nadir", "urban", False, _plan(4, 8, 500)),
    ("relief nadir", "farmland", False, _plan(4, 6, 500)),
    ("relief nadir", "suburban", False, _plan(5, 10, 500)),
    ("relief nadir", "urban", False, _plan(3, 5, 400)),
    ("relief nadir", "farmland", False, _plan(5, 8, 600)),
    ("tilted strips", "suburban", False, _plan(3, 6, 400, tilt=10)),
    ("tilted strips", "farmland", False, _plan(4, 6, 500, tilt=12)),
    ("tilted strips", "urban", False, _plan(4, 8, 500, tilt=10)),
    ("tilted strips", "suburban", True, _plan(4, 8, 400, tilt=10)),
    ("tilted strips", "suburban", False, _plan(5, 10, 500, tilt=8)),
    ("tilted strips", "urban", False, _plan(3, 5, 400, tilt=12)),
    ("cross strips", "suburban", False, _plan(3, 4, 400, cross=True)),
    ("cross strips", "urban", False, _plan(3, 6, 500, cross=True, tilt=8)),
    ("cross strips", "farmland", False, _plan(3, 5, 500, cross=True)),
    ("cross strips", "farmland", False, _plan(4, 6, 500, cross=True, tilt=10)),
    ("cross strips", "urban", False, _plan(3, 4, 400, cross=True)),
    ("cross strips", "suburban", False, _plan(5, 6, 600, cross=True, tilt=10)),
]


def cases(quick: bool) -> list[Case]:
    out = []
    for i, (kind, world, flat, plan) in enumerate(_SPECS):
        half = "dev" if i % 2 == 0 else "held-out"
        name = (f"{kind.split()[0]}-{world}{'-flat' if flat else ''}-{plan.n_images}img"
                f"-{plan.flying_height_m:.0f}m")
        out.append(Case(name, half, kind, world, flat, plan, seed=100 + i))
    if quick:  # a small tilted cross block (dev) and a small flat nadir block (held-out)
        return [_quick(out[19], _plan(2, 4, 500, cross=True, tilt=8), "dev"),
                _quick(out[0], _plan(3, 4, 500), "held-out")]
    return out


def _quick(case: Case, plan: FlightPlan, half: str) -> Case:
    from dataclasses import replace

    return replace(case, plan=plan, half=half,
                   name=case.name.split("-")[0] + f"-{case.world}-quick")


def flawed(block, camera: CameraModel, seed: int):
    """The uncalibrated model (see the module docstring) and its fitted registration."""
    sign = 1.0 if seed % 2 else -1.0
    rec, _ = flawed_model(block, focal_error=0.02 * sign, ignore_distortion=True,
                          principal_px=(camera.width_px / 2, camera.height_px / 2), seed=seed)
    return rec, fitted_registration(rec, block)


def _ba_options(refine_intrinsics: bool):
    import pycolmap

    opt = pycolmap.BundleAdjustmentOptions(
        refine_focal_length=refine_intrinsics, refine_principal_point=refine_intrinsics,
        refine_extra_params=refine_intrinsics, print_summary=False)
    opt.ceres.loss_function_type = pycolmap.LossFunctionType.SOFT_L1
    opt.ceres.loss_function_scale = 1.0  # twice the simulated pixel noise
    opt.ceres.solver_options.max_num_iterations = 200
    return opt


def images_only(rec, block):
    """(b): pycolmap's bundle adjustment of everything from the images alone, then placed."""
    import pycolmap

    out = copy.deepcopy(rec)
    pycolmap.bundle_adjustment(out, _ba_options(True))
    transform_model(out, fitted_registration(out, block))
    return out


def with_gcps(rec, T: Transform, ref, check_ids: np.ndarray):
    """(c): pycolmap's bundle adjustment with the lidar control points as fixed ground control
    (their height from the lidar, their plan position from the registration)."""
    import pycolmap

    out = copy.deepcopy(rec)
    transform_model(out, Transform.from_translation(-ref.origin) @ T)
    ids = np.array(sorted(out.point3D_ids()), dtype=np.int64)
    xyz = np.array([out.points3D[int(i)].xyz for i in ids])
    keep = ~np.isin(ids, check_ids)
    cps = select_control_points(xyz[keep], ref)
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in out.reg_image_ids():
        config.add_image(image_id)
    for cp in cps:
        pid = int(ids[keep][cp.index])
        out.points3D[pid].xyz = np.asarray(cp.xyz) - ref.origin
        config.add_constant_point(pid)
    if len(cps) >= 3:
        pycolmap.create_default_bundle_adjuster(_ba_options(True), config, out).solve()
    transform_model(out, Transform.from_translation(ref.origin))
    return out, len(cps)


def true_camera_runs(oracle, block, lidar_xyz, model_dir: Path):
    """(e) and (f): the model adjusted with the true camera, calibrated against the lidar with
    the intrinsics held at the truth (poses and points only), and with every intrinsic free.
    Returns the two models and (f)'s standard deviations and held parameters."""
    model_dir.mkdir(parents=True, exist_ok=True)
    oracle.write_binary(str(model_dir))
    T = fitted_registration(oracle, block)
    e = calibrate(model_dir, lidar_xyz, T_ref_mov=T, refine=("poses",))
    f = calibrate(model_dir, lidar_xyz, T_ref_mov=T)
    fallback = placed(oracle, T)
    info = {"sigma": dict(zip(f.camera().names, f.camera().sigma)),
            "held": [h[0] for h in f.camera().held], "confident": f.confident}
    return (e.model if e.model is not None else fallback,
            f.model if f.model is not None else fallback, info)


def placed(rec, T: Transform):
    out = copy.deepcopy(rec)
    transform_model(out, T)
    return out


def evaluate(rec, camera: CameraModel, block, patches: LidarPatches, origin, check_ids
             ) -> dict:
    """The metrics of a model in the reference frame (see the module docstring)."""
    p = np.asarray(rec.cameras[1].params, dtype=np.float64)
    ids = np.array(sorted(rec.reg_image_ids()))
    centres = np.array([rec.images[int(i)].projection_center() for i in ids])
    d = centres - block.centres[ids - 1]
    xyz = np.array([rec.points3D[int(i)].xyz for i in check_ids]).reshape(-1, 3) - origin
    dz = patches.at(xyz).dz_m
    dz = dz[np.isfinite(dz)]
    truth = (camera.focal_px, camera.cx_px, camera.cy_px, camera.k1, camera.k2)
    return {"intrinsic_err": dict(zip(("f", "cx", "cy", "k1", "k2"),
                                      (float(a - b) for a, b in zip(p, truth)))),
            "focal_err_pct": 100 * (p[0] / camera.focal_px - 1),
            "k1_err_pct": 100 * (p[3] / camera.k1 - 1),
            "pp_err_px": float(np.hypot(p[1] - camera.cx_px, p[2] - camera.cy_px)),
            "centre_rms_m": float(np.sqrt(np.mean(np.sum(d**2, axis=1)))),
            "centre_rms_z_m": float(np.sqrt(np.mean(d[:, 2] ** 2))),
            "centre_rms_rel_m": float(np.sqrt(np.mean(np.sum((d - d.mean(axis=0))**2,
                                                              axis=1)))),
            "check_rms_m": float(np.sqrt(np.mean(dz**2))) if len(dz) else float("nan"),
            "check_nmad_m": float(nmad(dz)) if len(dz) else float("nan")}


def run_case(case: Case, folder: Path) -> dict:
    """Every method on one case: metrics, and what (d) held, flagged and took."""
    t0 = time.perf_counter()
    camera = truth_camera(case.seed)
    scene, block = make_block(case.world, case.flat, case.plan, camera, case.seed)
    rec, T = flawed(block, camera, case.seed)
    oracle, _ = flawed_model(block, focal_error=0.0, ignore_distortion=False, seed=case.seed)
    model_dir = folder / case.name
    model_dir.mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(model_dir))
    lidar_xyz = scene.lidar.xyz
    with PeakMemory() as mem:
        c0, w0 = time.process_time(), time.perf_counter()
        r = calibrate(model_dir, lidar_xyz, T_ref_mov=T)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    row = {"case": asdict(case), "n_images": int(len(block.centres)),
           "n_points": int(len(block.xyz)), "camera": asdict(camera),
           "d": {"confident": r.confident, "reasons": list(r.reasons),
                 "warnings": list(r.warnings), "held": [list(h) for h in r.camera().held],
                 "sigma": dict(zip(r.camera().names, r.camera().sigma)),
                 "n_control": r.n_control, "n_check": r.n_check, "rounds": r.rounds,
                 "seconds": wall, "cpu_seconds": cpu,
                 "lidar_read_seconds": r.solver.get("lidar_read_seconds", float("nan")),
                 "memory_added_mb": mem.peak - mem.start}}
    if r.model is None:
        row["error"] = "; ".join(r.reasons)
        return row
    ref = lidar_reference(lidar_xyz)
    check_ids = r.residuals["point_ids"][r.residuals["check"]]
    origin = ref.origin
    xyz_a = np.array([p.xyz for _, p in sorted(placed(rec, T).points3D.items())]) - origin
    patches = LidarPatches.read(ref, xyz_a)
    models = {"a": placed(rec, T)}
    t = time.perf_counter()
    models["b"] = images_only(rec, block)
    row["b_seconds"] = time.perf_counter() - t
    t = time.perf_counter()
    models["c"], row["c_gcps"] = with_gcps(rec, T, ref, check_ids)
    row["c_seconds"] = time.perf_counter() - t
    models["d"] = r.model
    models["e"], models["f"], row["f"] = true_camera_runs(oracle, block, lidar_xyz,
                                                         folder / f"{case.name}-true")
    for m, model in models.items():
        row[m] = {**row.get(m, {}), **evaluate(model, camera, block, patches, origin, check_ids)}
    truth = placed(oracle, fitted_registration(oracle, block))
    row["tie_noise"] = evaluate(truth, camera, block, patches, origin, check_ids)
    xyz_t = np.array([truth.points3D[int(i)].xyz for i in check_ids])
    row["tie_noise"]["height_rms_vs_truth_m"] = float(
        np.sqrt(np.mean((xyz_t[:, 2] - block.xyz[check_ids - 1, 2]) ** 2)))
    row["seconds_all"] = time.perf_counter() - t0
    return row


# --- verdicts ---------------------------------------------------------------------------------

def _state(row: dict, name: str) -> str:
    """``held``, ``flagged`` or ``refined``: what (d) did with intrinsic ``name``."""
    if any(h[0] == name for h in row["d"]["held"]):
        return "held"
    if any(f": {name}: " in w for w in row["d"]["warnings"]):
        return "flagged"
    return "refined"


def verdicts(row: dict) -> dict[str, bool | None]:
    """Each acceptance line on one case: True, False, or None where it does not apply (the
    geometry does not determine the parameter: held or flagged, which is the right answer
    when the error is within three of its standard deviations or the parameter is held)."""
    if "error" in row:
        return {}
    d, sig = row["d"], row["d"]["sigma"]
    out: dict[str, bool | None] = {}

    def line(key, name, err, tol, sigma_scale):
        st = _state(row, name)
        s = sig.get(name)
        if st == "refined":
            out[key] = abs(err) <= tol
        elif st == "flagged":  # not silently wrong: within three standard deviations
            out[key + "_honest"] = s is not None and abs(err) <= 3 * s * sigma_scale
        else:
            out[key + "_honest"] = True

    cam = row["camera"]
    line("focal", "f", d["focal_err_pct"] / 100, FOCAL_TOL, 1 / cam["focal_px"])
    line("k1", "k1", d["k1_err_pct"] / 100, K1_TOL, 1 / abs(cam["k1"]))
    worst_pp = "cx" if _state(row, "cx") != "refined" else "cy"
    line("principal", worst_pp, d["pp_err_px"], PP_TOL_PX, 1.0)
    key = "centres" if _state(row, "f") == "refined" else "centres_weak"
    out[key] = d["centre_rms_m"] <= CENTRE_TOL_M
    if "e" in row:  # the floor: the true camera, poses and points against the lidar
        out["centres_floor"] = row["e"]["centre_rms_m"] <= CENTRE_TOL_M
    if "f" in row:  # nothing to calibrate: every free intrinsic within 3 sigma of the truth
        f = row["f"]
        out["unchanged"] = all(n in f["held"] or (f["sigma"].get(n) is not None
                                                  and abs(err) <= 3 * f["sigma"][n])
                               for n, err in f["intrinsic_err"].items())
    out["check"] = d["check_rms_m"] <= CHECK_TOL * row["tie_noise"]["check_rms_m"]
    return out


# --- report -------------------------------------------------------------------------------------

def _f(v, fmt=".2f") -> str:
    return "n/a" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, fmt)


def _held_text(row: dict) -> str:
    parts = [f"{n} held" for n, _ in row["d"]["held"]]
    parts += [f"{w.split(': ')[1]} flagged" for w in row["d"]["warnings"]]
    return ", ".join(parts) or "-"


def case_table(rows: list[dict], half: str) -> list[str]:
    out = [f"### {half} cases", "",
           "| case | img / pts | method | focal err % | k1 err % | pp err px | centres RMS m "
           "(z; less their mean) | check RMS / NMAD m | check RMS / tie noise |",
           "|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        if row["case"]["half"] != half:
            continue
        name = row["case"]["name"]
        if "error" in row:
            out.append(f"| {name} | {row['n_images']} / {row['n_points']} | (d) | not run: "
                       f"{row['error']} | | | | | |")
            continue
        noise = row["tie_noise"]["check_rms_m"]
        for m in METHODS:
            r = row[m]
            label = name if m == "a" else ""
            size = f"{row['n_images']} / {row['n_points']}" if m == "a" else ""
            out.append(f"| {label} | {size} | {METHOD_NAMES[m]} | {r['focal_err_pct']:+.3f} | "
                       f"{r['k1_err_pct']:+.1f} | {r['pp_err_px']:.2f} | "
                       f"{r['centre_rms_m']:.3f} ({r['centre_rms_z_m']:.3f}; "
                       f"{r.get('centre_rms_rel_m', float('nan')):.3f}) | "
                       f"{r['check_rms_m']:.3f} / {r['check_nmad_m']:.3f} | "
                       f"{r['check_rms_m'] / noise:.2f} |")
        d = row["d"]
        out.append(f"| | | tie noise (true camera) | | | | | {noise:.3f} / "
                   f"{row['tie_noise']['check_nmad_m']:.3f} | 1.00 |")
        out.append(f"| | | (d) held / flagged: {_held_text(row)}; {d['n_control']} control, "
                   f"{d['n_check']} check points, {d['rounds']} rounds, {d['seconds']:.1f} s "
                   f"({d['cpu_seconds']:.1f} s CPU, lidar reading {d['lidar_read_seconds']:.1f} "
                   f"s), +{d['memory_added_mb']:.0f} MB; (c) {row['c_gcps']} GCPs | | | | | | |")
    return out + [""]


def kind_table(rows: list[dict], half: str) -> list[str]:
    """Medians per block kind and method, and the margin of (d) over (b) and (c)."""
    out = [f"### {half} cases: medians per block kind", "",
           "| block kind | cases | method | abs focal err % | abs k1 err % | pp err px | "
           "centres RMS m | check RMS / tie noise |", "|---|---|---|---|---|---|---|---|"]
    keys = ("focal_err_pct", "k1_err_pct", "pp_err_px", "centre_rms_m")
    for kind in dict.fromkeys(r["case"]["kind"] for r in rows):
        sel = [r for r in rows if r["case"]["kind"] == kind and r["case"]["half"] == half
               and "error" not in r]
        if not sel:
            continue
        med = {m: [float(np.median([abs(r[m][k]) for r in sel])) for k in keys]
               + [float(np.median([r[m]["check_rms_m"] / r["tie_noise"]["check_rms_m"]
                                   for r in sel]))] for m in METHODS}
        for m in METHODS:
            v = med[m]
            out.append(f"| {kind if m == 'a' else ''} | {len(sel) if m == 'a' else ''} | "
                       f"{METHOD_NAMES[m]} | {v[0]:.3f} | {v[1]:.1f} | {v[2]:.2f} | {v[3]:.3f} "
                       f"| {v[4]:.2f} |")
        margin = [f"{min(med['b'][i], med['c'][i]) / max(med['d'][i], 1e-9):.1f}x"
                  for i in range(5)]
        out.append(f"| | | margin: best of (b), (c) / (d) | {' | '.join(margin)} |")
    return out + [""]


def acceptance(rows: list[dict], half: str) -> list[str]:
    names = {"focal": "focal within 0.1 % (determined)", "k1": "k1 within 10 % (determined)",
             "principal": "principal point within 1 px (determined)",
             "focal_honest": "focal held, or flagged and within 3 sigma (not determined)",
             "k1_honest": "k1 held, or flagged and within 3 sigma",
             "principal_honest": "principal point held, or flagged and within 3 sigma",
             "centres": "camera centres within 0.2 m RMS (focal determined)",
             "centres_weak": "camera centres within 0.2 m RMS (focal held or flagged)",
             "centres_floor": "camera centres within 0.2 m RMS with the true camera, (e)",
             "unchanged": "nothing to calibrate: intrinsics within 3 sigma of the truth, (f)",
             "check": "check RMS at most 1.2 x tie noise"}
    sel = [r for r in rows if r["case"]["half"] == half]
    v = [verdicts(r) for r in sel]
    out = [f"### {half} cases: acceptance of (d)", "", "| line | passed | failed cases |",
           "|---|---|---|"]
    for key, text in names.items():
        got = [(r["case"]["name"], x[key]) for r, x in zip(sel, v) if x.get(key) is not None]
        if got:
            bad = [n for n, ok in got if not ok]
            out.append(f"| {text} | {len(got) - len(bad)}/{len(got)} | {', '.join(bad) or '-'} |")
    not_run = [r["case"]["name"] for r in sel if "error" in r]
    if not_run:
        out.append(f"| not run (nothing to calibrate against) | | {', '.join(not_run)} |")
    return out + [""]


def speed_lines(speed: dict) -> list[str]:
    b = speed["block"]
    out = ["## Speed block: 50 images, 5,000 tie points", "",
           f"{b['images']} images, {b['points']} tie points, {b['observations']} observations, "
           f"{b['lidar_points']:,} lidar points (suburban, nadir, 600 m). Each run in a fresh "
           f"process. Load average of the machine (shared) before and after: "
           f"{', '.join(f'{x:.1f}' for x in speed['load_average'])} / "
           f"{', '.join(f'{x:.1f}' for x in speed['load_average_after'])}.", "",
           "| run | seconds | without lidar reading | CPU seconds | rounds (iterations) | peak "
           "memory MB (before) |", "|---|---|---|---|---|---|"]
    for threads in (1, 2):
        r = speed[f"calibrate_{threads}_threads"]
        if "error" in r:
            out.append(f"| tiereg calibrate, {threads} thread(s) | failed: {r['error']} |||||")
            continue
        out.append(f"| tiereg calibrate, {threads} thread(s) | {r['seconds']:.1f} | "
                   f"{r['seconds'] - r['lidar_read_seconds']:.1f} | {r['cpu_seconds']:.1f} | "
                   f"{r['rounds']} ({r['iterations']}) | {r['peak_rss_mb']:.0f} "
                   f"({r['rss_before_mb']:.0f}) |")
    out += ["", "One adjustment from the same start (the registered model, the first round's "
            "control points):", "", "| solver | seconds | iterations (evaluations) | final cost "
            "| focal px | k1 |", "|---|---|---|---|---|---|"]
    for name, r in speed["solvers"].items():
        if "error" in r:
            out.append(f"| {name} | failed: {r['error']} | | | | |")
            continue
        its = f"{r['iterations']}" + (f" ({r['jacobians']} Jacobians)" if "jacobians" in r
                                      else "")
        out.append(f"| {name} | {r['seconds']:.2f} | {its} | {r['final_cost']:.1f} | "
                   f"{r['focal']:.2f} | {r['k1']:.5f} |")
    return out + [""]


def write_report(rows: list[dict], speed: dict | None, folder: Path, seconds: float) -> Path:
    date = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    lines = ["# Cross-aided camera calibration benchmark", "",
             f"{len(rows)} simulated blocks ({sum(r['case']['half'] == 'dev' for r in rows)} dev, "
             f"{sum(r['case']['half'] == 'held-out' for r in rows)} held-out), {date}, "
             f"{seconds / 60:.0f} min in all. Made by `python benchmarks/calibration.py`; the "
             "method is in the script's docstring and docs/calibration.md.", "",
             "Every model starts from a focal length 2 % off, no distortion and the principal "
             "point at the image centre. The starting frame is the similarity fitted to the "
             "true points (not `tiereg register`, which is not yet reliable on strongly bent "
             "models). Tie noise: the check points' height residuals of the model adjusted "
             "with the true camera (images only, placed the same way); (e) and (f) start "
             "from that model, (e) with its intrinsics held (the floor for the camera "
             "centres), (f) with them free (a model with nothing to calibrate). Held and "
             "flagged parameters are what (d) reports; a flagged parameter counts as right "
             "when its error is within three of its standard deviations.", ""]
    for half in ("held-out", "dev"):
        lines += acceptance(rows, half) + kind_table(rows, half)
    if speed is not None:
        lines += speed_lines(speed)
    for half in ("held-out", "dev"):
        lines += case_table(rows, half)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "calibration.md"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    (folder / "calibration.json").write_text(json.dumps(
        {"date": date, "cases": rows, "speed": speed}, indent=1, default=_jsonable) + "\n",
        encoding="utf-8")
    return path


def _jsonable(v):
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="two small cases, results to work/")
    parser.add_argument("--cases", nargs="*", help="only the cases whose names contain these")
    parser.add_argument("--half", choices=("dev", "held-out"), help="only the cases of one half "
                        "(results to work/)")
    parser.add_argument("--no-speed", action="store_true", help="leave the speed block out")
    args = parser.parse_args()
    t0 = time.perf_counter()
    todo = cases(args.quick)
    if args.cases:
        todo = [c for c in todo if any(s in c.name for s in args.cases)]
    if args.half:
        todo = [c for c in todo if c.half == args.half]
    rows = []
    with tempfile.TemporaryDirectory(prefix="tiereg-calib-bench-") as tmp:
        for case in todo:
            row = run_case(case, Path(tmp))
            rows.append(row)
            d = row.get("d", {})
            print(f"{case.half:8s} {case.name:40s} focal {d.get('focal_err_pct', np.nan):+.3f} %"
                  f" k1 {d.get('k1_err_pct', np.nan):+.1f} % pp {d.get('pp_err_px', np.nan):.2f}"
                  f" centres {d.get('centre_rms_m', np.nan):.3f} m  {_held_text(row)}  "
                  f"{row.get('seconds_all', 0):.0f} s", flush=True)
    speed = None if args.no_speed else speed_block(args.quick)
    out = write_report(rows, speed, WORK if args.quick or args.cases or args.half else RESULTS,
                       time.perf_counter() - t0)
    print(out)


if __name__ == "__main__":
    main()
