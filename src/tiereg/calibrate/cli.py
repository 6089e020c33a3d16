"""``tiereg calibrate``: its options and what it writes (the command line's parser calls these)."""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

EXAMPLES = """examples:
  tiereg calibrate sparse/0 lidar.laz -o calibrated/
  tiereg calibrate sparse/0 tiles/ -o calibrated/ --result RESULT.json --report
  tiereg calibrate sparse/0 lidar.laz -o calibrated/ --refine focal,distortion,poses
writes calibrated/model/ (COLMAP, .bin and .txt, in the lidar's frame), calibrated/CALIBRATION.json
and with --report calibrated/report/report.html"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", metavar="MODEL", help="COLMAP model folder (cameras, images, "
                   "points3D; .bin or .txt), in any frame")
    p.add_argument("reference", metavar="REFERENCE", nargs="+",
                   help="lidar LAS/LAZ file(s), a folder or glob of tiles")
    p.add_argument("-o", "--output", required=True, metavar="OUTDIR",
                   help="folder for model/, CALIBRATION.json and the report")
    p.add_argument("--refine", default="focal,principal,distortion,poses",
                   metavar="LIST", help="what to refine: a comma list of focal, principal, "
                   "distortion, poses (default all; points are always refined)")
    p.add_argument("--result", metavar="RESULT.json",
                   help="the model's registration from `tiereg register` (default: register "
                   "it first)")
    p.add_argument("--report", action="store_true", help="write OUTDIR/report/report.html")
    p.add_argument("--reference-format", metavar="FMT", help="override format detection")


def _check_output(out: Path, model: str, reference: list[str]) -> None:
    from ..errors import InputError
    from ..io import check_not_input

    if out.exists() and not out.is_dir():
        raise InputError(f"-o {out}: is a file; give a folder for the outputs")
    if (out / "model").resolve() == Path(model).resolve() or out.resolve() == Path(
            model).resolve():
        raise InputError(f"-o {out}: would write over the input model {model}; choose "
                         "another output folder")
    check_not_input(out / "CALIBRATION.json", model, reference)


def write_outputs(result, out: Path, *, report: bool) -> Path | None:
    """``model/`` (when calibrated), ``CALIBRATION.json``, and with ``report`` the report;
    the model is written beside and renamed into place whole."""
    from ..io.base import write_text_atomic
    from .model import write_model

    out.mkdir(parents=True, exist_ok=True)
    if result.model is not None:
        tmp = Path(tempfile.mkdtemp(prefix=".model-", dir=out))
        try:
            write_model(result.model, tmp)
            if (out / "model").exists():
                shutil.rmtree(out / "model")
            tmp.rename(out / "model")
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    write_text_atomic(out / "CALIBRATION.json", result.to_json() + "\n")
    if report:
        from .report import write_calibration_report

        return write_calibration_report(result, out / "report")
    return None


def summary(result) -> str:
    lines = [f"confident:   {'yes' if result.confident else 'NO'}"]
    lines += [f"reason:      {r}" for r in result.reasons]
    for cam in result.cameras:
        parts = []
        for n, b, a, s in zip(cam.names, cam.before, cam.after, cam.sigma):
            shown = "held" if cam.is_held(n) else f"{a:.6g} +- {s:.2g}" if s else f"{a:.6g}"
            parts.append(f"{n} {b:.6g} -> {shown}")
        lines.append(f"camera {cam.camera_id}:    " + ", ".join(parts))
        lines += [f"held:        {n}: {r}" for n, r in cam.held]
    lines += [f"warning:     {w}" for w in result.warnings]
    rb, ra = result.reprojection_rms_before_px, result.reprojection_rms_after_px
    lines.append(f"reprojection RMS: {rb:.3f} -> {ra:.3f} px")
    if result.check_before is not None and result.check_after is not None:
        lines.append(f"lidar check points ({result.n_check}): height RMSE "
                     f"{result.check_before.rmse_z:.3f} -> {result.check_after.rmse_z:.3f}")
    return "\n".join(lines)


def command(args: argparse.Namespace) -> int:
    """Run ``tiereg calibrate``; returns the exit code (0 confident, 3 not reliable)."""
    from . import calibrate

    out = Path(args.output)
    _check_output(out, args.model, args.reference)
    reference = args.reference[0] if len(args.reference) == 1 else args.reference
    result = calibrate(args.model, reference, refine=args.refine, result=args.result,
                       reference_format=args.reference_format)
    report = write_outputs(result, out, report=args.report)
    if not args.quiet:
        print(summary(result))
        print(f"result:      {out / 'CALIBRATION.json'}"
              + (f", model {out / 'model'}" if result.model is not None else ""))
        if report is not None:
            print(f"report:      {report}")
    return 0 if result.confident else 3
