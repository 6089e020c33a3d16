"""The structure-from-motion benchmark's report: ``sfm.md`` and ``sfm.json``."""

from __future__ import annotations

import json
import os
import platform
from dataclasses import asdict
from pathlib import Path

import numpy as np

HALVES = ("dev", "held-out")


def _f(v, spec=".2f") -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "-"
    return format(v, spec)


def _yn(v) -> str:
    return "-" if v is None else ("yes" if v else "no")


def summarize(rows) -> dict:
    """Counts over a set of rows."""
    negatives = [r for r in rows if r.case.variant == "negative"]
    return {
        "cases": len(rows),
        "positives": len(rows) - len(negatives),
        "negatives": len(negatives),
        "correct_and_confident": sum(r.correct and bool(r.confident) for r in rows
                                     if r.case.variant != "negative"),
        "correct": sum(r.correct for r in rows if r.case.variant != "negative"),
        "negatives_rejected": sum(r.correct for r in negatives),
        "confidently_wrong": sum(bool(r.confident) and not r.correct for r in rows),
        "tracebacks": sum(r.run.traceback for r in rows),
        "timeouts": sum(r.run.timed_out for r in rows),
        "no_result": sum(r.confident is None for r in rows),
        "max_peak_mb": max((r.run.peak_mb for r in rows), default=float("nan")),
        "seconds": sum(r.run.seconds for r in rows),
    }


def _summary_line(label: str, s: dict) -> str:
    return (f"| {label} | {s['cases']} | **{s['correct_and_confident']}/{s['positives']}** | "
            f"{s['correct']}/{s['positives']} | **{s['confidently_wrong']}** | "
            f"{s['negatives_rejected']}/{s['negatives']} | {s['tracebacks']} | "
            f"{s['timeouts']} | {s['no_result']} | {_f(s['max_peak_mb'], '.0f')} | "
            f"{s['seconds'] / 60:.1f} |")


SUMMARY_HEAD = [
    "| set | cases | correct and confident | correct | confidently wrong | negatives rejected "
    "| tracebacks | timeouts | no RESULT.json | max peak MB | tiereg min |",
    "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
]


def _reconstruction_lines(built) -> list[str]:
    lines = [
        "| scene | half | images (registered) | rays missed (%) | points | reproj. px | GSD | "
        "flying height | "
        "model units per ref. unit | up in model frame | truth fit: points RMS / median, GSD "
        "(ref. units; points used) | cameras RMS, GSD (ref. units) | fits differ at centre (GSD) / rotation (deg) / scale (%) | "
        "f, k1, k2 true / estimated | render s | COLMAP s |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---|---|---:|---|---|---:|---:|",
    ]
    for name, b in built.items():
        rec, t, s = b.reconstruction, b.truth, b.scene
        reg = rec.get("n_registered", 0)
        head = (f"| {name} | {s.half} | {b.block['n_images']} ({reg}) | "
                f"{100 * b.block['miss_fraction']:.2f} | "
                f"{rec.get('n_points', 0):,} | {_f(rec.get('reprojection_error_px'))} | "
                f"{b.block['gsd']:.3g} | {b.block['flying_height']:.0f} | ")
        cam = s.camera
        true_cam = f"{cam.focal_px:g}, {cam.k1:g}, {cam.k2:g}"
        if t is None:
            lines.append(head + "- | - | - | - | - | " + true_cam + " / - | "
                         f"{b.seconds.get('render', 0):.0f} | "
                         f"{b.seconds.get('reconstruct', 0):.0f} |")
            continue
        fp, fc, fd = t["fit_points"], t["fit_cameras"], t["fits_differ"]
        est = rec.get("camera_params", [])
        est_s = ", ".join(_f(v, ".4g") for v in (est[0], est[3], est[4])) if len(est) == 5 else "-"
        up = ", ".join(f"{u:+.2f}" for u in t["up_in_model_frame"])
        lines.append(
            head + f"{t['model_units_per_ref_unit']:.4g} | ({up}) | "
            f"{fp['rms_gsd']:.2f} / {fp['median_gsd']:.2f} ({fp['rms']:.3g} / {fp['median']:.3g};"
            f" {fp['n_used']:,} of {fp['n']:,}) | "
            f"{fc['rms_gsd']:.2f} ({fc['rms']:.3g}) | {fd['at_block_centre'] / t['gsd']:.2f} / "
            f"{fd['rotation_deg']:.3f} / {100 * fd['scale_relative']:.2f} | "
            f"{true_cam} / {est_s} | {b.seconds.get('render', 0):.0f} | "
            f"{b.seconds.get('reconstruct', 0):.0f} |")
    return lines


def _case_lines(rows) -> list[str]:
    lines = [
        "| case | half | variant | points | true scale | correct | confident | heading err "
        "(deg) | tilt err (deg) | scale err (%) | position err (cells) | cell | RMS / max "
        "(GSD) | s | peak MB | exit | note |",
        "|---|---|---|---:|---:|---|---|---:|---:|---:|---:|---:|---|---:|---:|---:|---|",
    ]
    for r in rows:
        c, run = r.case, r.run
        note = r.note
        if run.exit_code not in (0, 3):
            note = ("timed out; " if run.timed_out else "") + run.stderr_tail
        note = note.replace("|", "/")[:160]
        lines.append(
            f"| {c.name} | {c.half} | {c.variant} | {c.n_points:,} | {_f(r.true_scale, '.4g')} "
            f"| {_yn(r.correct)} | {_yn(r.confident)} | {_f(r.heading_err_deg)} | "
            f"{_f(r.tilt_err_deg)} | {_f(100 * r.scale_err)} | "
            f"{_f(r.position_err_cells, '.3g')} | {_f(r.cell_size, '.3g')} | "
            f"{_f(r.rms_gsd, '.3g')} / {_f(r.max_gsd, '.3g')} | {run.seconds:.1f} | "
            f"{run.peak_mb:.0f} | {run.exit_code} | {note} |")
    return lines


def _outcome_lines(rows) -> list[str]:
    """How the cases ended: exit code and the first reason given (or stderr's last line)."""
    from collections import Counter

    def kind(r) -> str:
        if r.run.timed_out:
            return "timed out"
        if r.run.exit_code not in (0, 3):
            last = r.run.stderr_tail.split(" | ")[-1] if r.run.stderr_tail else ""
            return f"exit {r.run.exit_code}: {last[:90]}"
        first = r.note.split("; ")[0] if r.note else ""
        return f"exit {r.run.exit_code}: {first[:90]}"

    counts = Counter(kind(r) for r in rows)
    return ["| outcome | cases |", "|---|---:|",
            *[f"| {k.replace('|', '/')} | {n} |" for k, n in counts.most_common()]]


def _attainable_lines(rows) -> list[str]:
    lines = ["| scene | half | RMS / max from the truth (GSD) | scale err (%) | confident | s | "
             "peak MB | exit |", "|---|---|---|---:|---|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r.case.scene} | {r.case.half} | {_f(r.rms_gsd)} / {_f(r.max_gsd)} | "
                     f"{_f(100 * r.scale_err, '.3f')} | {_yn(r.confident)} | "
                     f"{r.run.seconds:.1f} | {r.run.peak_mb:.0f} | {r.run.exit_code} |")
    return lines


def write_report(rows, attainable, built, out_dir: Path, *, seconds: float,
                 build_seconds: float,
                 speed: str, command: str, date: str) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    halves = {h: summarize([r for r in rows if r.case.half == h]) for h in HALVES}
    total = summarize(rows)
    scenes = list(dict.fromkeys(r.case.scene for r in rows))
    by_scene = {s: summarize([r for r in rows if r.case.scene == s]) for s in scenes}
    variants = list(dict.fromkeys(r.case.variant for r in rows))
    by_variant = {v: summarize([r for r in rows if r.case.variant == v]) for v in variants}
    n_ok = sum(b.model_dir is not None for b in built.values())
    stage_s = {k: sum(b.seconds.get(k, 0.0) for b in built.values())
               for k in ("world", "render", "reconstruct", "truth", "lidar")}
    tiereg_s = sum(r.run.seconds for r in rows)
    lines = [
        "# Structure-from-motion benchmark: tiereg on COLMAP models of rendered aerial blocks",
        "",
        f"- {date}; `{command}`; {platform.machine()}, {os.cpu_count()} cores (shared with "
        f"other work), Python {platform.python_version()}; {speed}",
        f"- total run time {seconds / 60:.1f} min: building the scenes {build_seconds / 60:.1f} "
        "min (this run; cached parts cost nothing: first builds took "
        + ", ".join(f"{k} {v / 60:.1f}" for k, v in stage_s.items())
        + f" min), tiereg {tiereg_s / 60:.1f} min over {len(rows)} cases",
        f"- reconstructions: {n_ok} of {len(built)} scenes gave a model (pycolmap, CPU SIFT "
        "at most 4,096 features per image, exhaustive matching, incremental mapping, one RADIAL "
        "camera)",
        "- correct: heading and tilt within 2 deg, scale within 2 %, model centroid within one "
        "coarse cell (RESULT.json `cell_size`), and within 1.5 GSD RMS at the model's points "
        "(or the truth fit's own RMS residual where larger: the model is not rigid) "
        "when the fine stage ran; confidently wrong: `confident` and not correct; a negative "
        "(another place's lidar) is correct when not confident",
        "- each case: the installed `tiereg register MOVING LIDAR -o RESULT.json` in a child "
        "process, 900 s and 6 GB of address space at most; peak MB is the child's largest "
        "resident memory",
        "- halves: scenes with even seeds are the development half, odd seeds the held-out "
        "half (fixed in `sfm_scenes.SCENES` before any result); autzen-trim (the shipped model "
        "of the test suite) counts as development",
        "",
        "## Headline", "", *SUMMARY_HEAD,
        *[_summary_line(h, halves[h]) for h in HALVES], _summary_line("all", total), "",
        "## By variant", "", *SUMMARY_HEAD,
        *[_summary_line(v, s) for v, s in by_variant.items()], "",
        "## By scene", "", *SUMMARY_HEAD,
        *[_summary_line(s, v) for s, v in by_scene.items()], "",
        "## How the cases ended", "", *_outcome_lines(rows), "",
        "## The fine stage from the truth",
        "",
        "Not counted above: `tiereg register MODEL LIDAR --coarse none --initial truth.json` "
        "per scene, the fine stage started at the truth. How far it moves from the truth "
        "shows what the data allow: the models are not exact similarities of the world "
        "(COLMAP's self-calibration bends them a little), so the similarity that fits the "
        "lidar best and the one that fits the true surface points best differ.", "",
        *_attainable_lines(attainable), "",
        "## Reconstructions", "",
        "Scale: reference units (metres) per model unit is the inverse of the column; up: the "
        "reference's vertical in the model frame (COLMAP's gauge: z about -1 is upside down). "
        "Truth fit: model points against where their observations' true rays meet the surface "
        "(robust Umeyama; points used of points with consistent rays); cameras: reconstructed "
        "against true centres.", "",
        *_reconstruction_lines(built), "",
        "## Cases", "", *_case_lines(rows), "",
    ]
    (out_dir / "sfm.md").write_text("\n".join(lines) + "\n")
    data = {
        "date": date, "command": command, "seconds": seconds, "build_seconds": build_seconds,
        "summary": {"halves": halves, "all": total, "by_scene": by_scene,
                    "by_variant": by_variant},
        "scenes": {n: {"half": b.scene.half, "plan": asdict(b.scene.plan),
                       "camera": asdict(b.scene.camera), "block": b.block,
                       "reconstruction": b.reconstruction, "truth": b.truth, "lidar": b.lidar,
                       "seconds": b.seconds} for n, b in built.items()},
        "cases": [_row_dict(r) for r in rows],
        "fine_from_truth": [_row_dict(r) for r in attainable],
    }
    (out_dir / "sfm.json").write_text(json.dumps(_finite(data), indent=1, default=_jsonable,
                                                 allow_nan=False) + "\n")


def _row_dict(r) -> dict:
    return {**asdict(r.case), **asdict(r.run),
            **{k: v for k, v in asdict(r).items() if k not in ("case", "run")}}


def _finite(o):
    """JSON has no NaN: a number that is not finite is written as null."""
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    if isinstance(o, (float, np.floating)):
        return float(o) if np.isfinite(o) else None
    return o


def _jsonable(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o))
