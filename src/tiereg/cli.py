"""The ``tiereg`` command line: a thin layer over the library.

Exit codes: 0 registered and confident; 3 ran to the end without a reliable registration
(RESULT.json still written, ``"confident": false``); 2 bad usage or input (one line on stderr);
anything else is a bug.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import re
import shutil
import signal
import sys
import threading
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path

from .cli_options import EXIT_BAD_INPUT, Parser, build_parser
from .errors import InputError, TieregError
from .io.base import all_or_nothing

EXIT_OK, EXIT_NOT_CONFIDENT = 0, 3  # and EXIT_BAD_INPUT (2), which argparse exits with too
log = logging.getLogger("tiereg")

def _progress_factory(quiet: bool):
    if quiet or not sys.stderr.isatty():
        return None
    from tqdm import tqdm

    def make(desc: str, total: int):
        return tqdm(total=total, desc=desc, unit="pt", unit_scale=True, leave=False,
                    file=sys.stderr, dynamic_ncols=True)

    return make


def _setup_logging(args: argparse.Namespace) -> None:
    """Our messages at the asked level; other libraries' only with -vv (they would repeat our
    one-line errors in their own words)."""
    level = logging.ERROR if args.quiet else (
        logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    for old in [h for h in log.handlers if getattr(h, "tiereg_cli", False)]:
        log.removeHandler(old)  # main() may run more than once in one process
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("tiereg: %(message)s"))
    handler.tiereg_cli = True  # type: ignore[attr-defined]
    log.addHandler(handler)
    log.setLevel(level)
    log.propagate = False
    if args.verbose >= 2:
        logging.basicConfig(level=logging.DEBUG, stream=sys.stderr)
    else:
        logging.getLogger().setLevel(logging.CRITICAL + 1)


def _summary(result) -> str:
    """What was found, how confident, how precise and how good: a few lines for the terminal."""
    p = result.T_ref_mov.parameters()
    d = p.to_dict()
    units = result.inputs.units
    stages = ["no coarse stage"]
    if result.coarse:
        channel = result.coarse.evidence.channel  # by heights, or by what stands on them
        stages = [f"coarse {result.coarse.method}" + (" on objects" if channel == "objects"
                                                      else "")]
    if result.fine is not None:
        stages.append(f"fine {result.fine.method} ({result.fine.model})")
    lines = [
        f"confident:   {'yes' if result.confident else 'NO'} (confidence {result.confidence:.2f})",
        f"found:       scale {p.scale:.6f}, heading {d['kappa_deg']:.3f} deg, tilt "
        f"{d['omega_deg']:.3f} / {d['phi_deg']:.3f} deg ({', '.join(stages)})",
        f"translation: {p.translation[0]:.3f} {p.translation[1]:.3f} {p.translation[2]:.3f} "
        f"({units}), cell {result.cell_size:g}",
    ]
    if result.fine is not None and not result.fine.refused:
        t = result.fine.precision(p.scale)["translation"]
        if any(v is not None for v in t):
            lines.append("precision:   " + " / ".join("held" if v is None else f"{v:.3f}"
                                                      for v in t)
                         + f" ({units}, 1 sigma x / y / z at the block centre)")
    q, b = result.quality, result.residuals.stats(after=False) if result.residuals else None
    if q.n_used:
        was = f" (before the fine stage {b.nmad_dz:.3f})" if b is not None and b.n_used and \
            result.fine is not None else ""
        lines.append(f"heights:     at {q.n_used}/{q.n_moving} points median {q.median_dz:.3f}, "
                     f"NMAD {q.nmad_dz:.3f}{was}, RMSE {q.rmse_z:.3f}")
    lines.extend(f"note:        {r}" for r in result.reasons)
    lines.extend(f"warning:     {w}" for w in result.warnings)
    return "\n".join(lines)


def _cmd_register(args: argparse.Namespace) -> int:
    from .files import load_transform
    from .io import check_not_input, write_points
    from .io.base import check_writable, write_text_atomic
    from .pipeline import register

    out = Path(args.output)
    inputs = (args.moving, args.reference, args.initial or [])
    check_writable(out)  # fail before any work if the result could not be written
    check_not_input(out, *inputs)
    if args.output_points:
        check_writable(args.output_points)
        check_not_input(args.output_points, *inputs)
        if Path(args.output_points).resolve() == out.resolve():
            raise InputError(f"--output-points {args.output_points}: is the -o file too; give "
                             "the points another name")
    if args.report and Path(args.report).exists() and not Path(args.report).is_dir():
        raise InputError(f"--report {args.report}: is a file; give a folder for the report")
    initial = load_transform(args.initial)[0] if args.initial else None
    result = register(args.moving, args.reference, coarse=args.coarse, fine=args.fine,
                      cell_size=args.cell_size, initial=initial, level=args.level,
                      free_tilt=args.free_tilt, moving_format=args.moving_format,
                      reference_format=args.reference_format,
                      scale_range=tuple(args.scale_range) if args.scale_range else None,
                      progress=_progress_factory(args.quiet))
    if args.output_points:
        from .io import read_points

        moving = read_points(args.moving, format=args.moving_format)
        write_points(args.output_points, result.T_ref_mov.apply(moving.xyz))
    write_text_atomic(out, result.to_json() + "\n")
    report = None
    if args.report:
        from .report import write_report

        report = write_report(result, args.report)
    if not args.quiet:
        print(_summary(result))
        if result.levelling:
            lv = result.levelling
            print(f"levelled:    the model was tilted by {lv.tilt_deg:.1f} deg (vertical from "
                  f"its {lv.source})")
        print(f"result:      {out}")
        if report is not None:
            print(_report_line(report))
    return EXIT_OK if result.confident else EXIT_NOT_CONFIDENT


def _report_line(report) -> str:
    n = len(report.control_points)
    cps = f", {n} lidar control points" if n else ""
    return f"report:      {report.html}{cps}"


def _cmd_overlap(args: argparse.Namespace) -> int:
    from .overlap import check_overlap, write_overlap

    if args.out and Path(args.out).exists() and not Path(args.out).is_dir():
        raise InputError(f"--out {args.out}: is a file; give a folder")
    reference = args.reference if len(args.reference) > 1 else args.reference[0]
    result = check_overlap(args.moving, reference, cell_size=args.cell_size, coarse=args.coarse,
                           moving_format=args.moving_format,
                           reference_format=args.reference_format,
                           progress=_progress_factory(args.quiet))
    files = write_overlap(result, args.out) if args.out else ()
    if not args.quiet:
        r = result.registration
        print(f"{result.verdict} (confidence {r.confidence:.2f})")
        if result.confident:
            print(f"area:        {result.area:,.0f} square {r.inputs.units} "
                  f"({len(result.outline['coordinates'])} part(s))")
        lines = _summary(r).splitlines()
        print("\n".join(line for line in lines if not line.startswith("confident:")))
        print(f"time:        {result.seconds - r.reference_seconds:.1f} s "
              f"(+ {r.reference_seconds:.1f} s reading and gridding the reference)")
        if files:
            print(f"wrote:       {', '.join(str(Path(args.out) / f) for f in files)}")
    return EXIT_OK if result.confident else EXIT_NOT_CONFIDENT


def _cmd_report(args: argparse.Namespace) -> int:
    from .io.base import check_input_file, note_input
    from .report import report_from_result_file

    if os.path.lexists(args.result):  # a missing one: the report says what to give
        check_input_file(args.result)  # a FIFO is refused, not waited on
    note_input(args.result)  # no report file may replace it
    report = report_from_result_file(args.result, args.out,
                                     progress=_progress_factory(args.quiet))
    if not args.quiet:
        print(_report_line(report))
    return EXIT_OK


def _cmd_apply(args: argparse.Namespace) -> int:
    from .files import apply_to_file, load_transform
    from .io import check_not_input
    from .io.las import SOURCE_CRS

    check_not_input(args.output, args.transform, args.input)
    T, reference_crs = load_transform(args.transform)
    if args.inverse:
        T = T.inverse
    # forward, into the reference's frame and so its CRS where RESULT.json names it; the inverse
    # carries reference data into the model's frame, which no CRS describes
    frame = None if args.inverse else (reference_crs or SOURCE_CRS)
    apply_to_file(T, args.input, args.output, format=args.format,
                  progress=_progress_factory(args.quiet), crs_wkt=frame)
    if not args.quiet:
        print(f"wrote {args.output}")
    return EXIT_OK


def _cmd_grid(args: argparse.Namespace) -> int:
    from .files import grid_to_geotiff

    if args.workers is not None or args.scheduler is not None:
        from .distributed import cluster, grid_archive, index_cache_beside

        with cluster(workers=args.workers, scheduler=args.scheduler) as client:
            spec = grid_archive(args.input, args.output, cell_size=args.cell_size,
                                stat=args.stat, client=client, progress=_progress_factory(
                                    args.quiet), cache=index_cache_beside(args.output))
    else:
        spec = grid_to_geotiff(args.input, args.output, cell_size=args.cell_size,
                               stat=args.stat, format=args.format,
                               progress=_progress_factory(args.quiet))
    if not args.quiet:
        print(f"wrote {args.output}: {spec.shape[0]} rows x {spec.shape[1]} cols, "
              f"cell {spec.cell_size:g}")
    return EXIT_OK


def _cmd_batch(args: argparse.Namespace) -> int:
    from .batch import run_batch
    from .distributed import cluster

    if len(args.paths) < 2:
        raise InputError("give at least one block and then the archive (a folder or glob)")
    blocks, reference = args.paths[:-1], args.paths[-1]
    with cluster(workers=args.workers, scheduler=args.scheduler) as client:
        done = run_batch(blocks, reference, args.out, client=client, report=args.report,
                         sigma_range=tuple(args.scale_range),
                         progress=_progress_factory(args.quiet))
    if not args.quiet:
        n_ok = sum(o.confident for o in done.outcomes)
        n_before = sum(o.skipped for o in done.outcomes)
        print(f"{n_ok} of {len(done.outcomes)} blocks confident ({n_before} done before); "
              f"{done.summary_csv}, {done.overview_png}")
    return EXIT_OK if done.all_confident else EXIT_NOT_CONFIDENT


def _cmd_info(args: argparse.Namespace) -> int:
    from .files import describe

    info = describe(args.input, format=args.format)
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        for k, v in info.items():
            print(f"{k + ':':<22}{v}")
    return EXIT_OK


def _cmd_demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    outcome = run_demo(args.out, progress=_progress_factory(args.quiet))
    r = outcome.result
    code = EXIT_OK if r.confident else EXIT_NOT_CONFIDENT
    if args.quiet:
        return code
    true, est = outcome.T_ref_mov_true, r.T_ref_mov
    print(f"tiereg demo: a COLMAP model ({outcome.n_points:,} points, 12 images rendered over the "
          "shipped Autzen 2010 lidar sample, reconstructed by pycolmap: its own gauge, upside "
          "down) registered to that lidar (110,000 points, feet) with no initial guess")
    print(f"{'':11}{'ft/unit':>10}{'block centre x':>17}{'y':>14}{'z':>10}")
    for name, T, c in (("truth", true, outcome.block_centre_true),
                       ("recovered", est, outcome.block_centre_est)):
        print(f"{name:11}{T.scale:10.4f}{c[0]:17.3f}{c[1]:14.3f}{c[2]:10.3f}")
    e = outcome.error
    print(f"{'error':11}{est.scale / true.scale - 1:+10.2%}{e[0]:17.3f}{e[1]:14.3f}{e[2]:10.3f}"
          f"   (horizontal {outcome.error_cells:.3f} cell of {r.cell_size:g} ft)")
    print(f"rotation error {outcome.rotation_error_deg:.3f} deg; over the model's points RMS "
          f"{outcome.rms_gsd:.2f} GSD (the images' ground sampling distance, "
          f"{outcome.gsd:g} ft)")
    print(_summary(r))
    print(f"wrote {Path(args.out) / 'RESULT.json'}, truth.json")
    print(_report_line(outcome.report))
    return code


def _cmd_simulate(args: argparse.Namespace) -> int:
    import numpy as np

    from .simulate import (
        HiddenTransform,
        ImageBlock,
        LidarSurvey,
        SceneSpec,
        make_scene,
        write_scene,
    )

    if not 0.0 < args.overlap <= 1.0:
        raise InputError(f"--overlap must be in (0, 1], got {args.overlap}")
    if args.scale is not None and not args.scale > 0:
        raise InputError(f"--scale must be positive, got {args.scale}")
    hidden = None
    if args.heading is not None or args.scale is not None:
        rnd = HiddenTransform.random(np.random.default_rng([args.seed, 2]))
        hidden = HiddenTransform(
            heading_deg=rnd.heading_deg if args.heading is None else args.heading,
            scale=rnd.scale if args.scale is None else args.scale,
            tilt_deg=rnd.tilt_deg, model_origin=rnd.model_origin)
    spec = SceneSpec(kind=args.kind, seed=args.seed, world_size_m=args.world_size,
                     lidar_size_m=args.lidar_size, overlap=args.overlap, hidden=hidden,
                     survey=LidarSurvey(density_per_m2=args.lidar_density),
                     block=ImageBlock(side_m=args.block_size,
                                      tie_points_per_km2=args.tie_density))
    scene = make_scene(spec)
    out = write_scene(scene, args.out)
    if not args.quiet:
        p = scene.T_ref_mov.parameters()
        print(f"wrote {out}/reference.laz ({len(scene.lidar.xyz):,} points), tiepoints.xyz "
              f"({len(scene.moving):,} points), truth.json")
        print(f"truth: scale {p.scale:.6f}, kappa {np.degrees(p.kappa):.3f} deg, overlap "
              f"{scene.overlap:.0%}")
    return EXIT_OK


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from .calibrate.cli import command

    return command(args)


COMMANDS = {"register": _cmd_register, "overlap": _cmd_overlap, "report": _cmd_report,
            "simulate": _cmd_simulate, "apply": _cmd_apply, "grid": _cmd_grid,
            "batch": _cmd_batch, "info": _cmd_info, "demo": _cmd_demo,
            "calibrate": _cmd_calibrate}


class _Terminated(BaseException):
    """SIGTERM or SIGHUP, raised where the program is, so that every clean-up runs (temporary
    files go) as for Ctrl-C."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _on_signal(signum: int, frame: object) -> None:
    signal.signal(signum, signal.SIG_IGN)  # a second signal must not cut the clean-up short
    raise _Terminated(signum)


@contextlib.contextmanager
def _signals_raise() -> Iterator[None]:
    if threading.current_thread() is not threading.main_thread():
        yield  # signals reach the main thread only (main() called from a worker thread)
        return
    old = {s: signal.signal(s, _on_signal) for s in (signal.SIGTERM, signal.SIGHUP)}
    try:
        yield
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)


def _output_folders(args: argparse.Namespace) -> list[str]:
    """The folders a command may create (removed again when it fails)."""
    names = {"register": "report", "overlap": "out", "report": "out", "simulate": "out"}
    folder = getattr(args, names.get(args.command, ""), None)
    return [folder] if folder else []


def _cli_message(text: str, command: str, parser: Parser) -> str:
    """One printable line, with the library's parameter names (`cell_size`) given as the
    command's options (--cell-size)."""
    options = parser.commands[command].flags

    def flag(m: re.Match) -> str:
        name = m.group(1)
        if name == "format" and "--format" not in options and "--moving-format" in options:
            return "--moving-format/--reference-format"
        option = "--" + name.replace("_", "-")
        return option if option in options else name

    text = re.sub(r"`([a-z_]+)`", flag, " ".join(text.split()))
    return "".join(c if c.isprintable() else f"\\x{ord(c):02x}" for c in text)


def _run(args: argparse.Namespace) -> int:
    """The command, writing all its outputs or none."""
    if args.command == "demo":  # it reads back what it writes: a new folder goes on failure
        fresh = not os.path.lexists(args.out)
        try:
            return COMMANDS[args.command](args)
        except BaseException:
            if fresh and Path(args.out).is_dir():
                shutil.rmtree(args.out, ignore_errors=True)
            raise
    if args.command == "batch":  # resumable: each block's outputs are written whole as it ends
        return COMMANDS[args.command](args)
    with all_or_nothing(folders=_output_folders(args)):
        try:
            return COMMANDS[args.command](args)
        except BrokenPipeError:  # output piped into e.g. `head`: not an error of ours
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.error(f"a command is needed: one of {', '.join(COMMANDS)}")
    _setup_logging(args)
    try:
        with _signals_raise(), warnings.catch_warnings():
            if args.verbose < 2:  # numpy's and laspy's warnings: the user sees our one line
                warnings.simplefilter("ignore")
            return _run(args)
    except TieregError as exc:
        print(f"tiereg {args.command}: error: {_cli_message(str(exc), args.command, parser)}",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("tiereg: interrupted", file=sys.stderr)
        return 128 + signal.SIGINT
    except _Terminated as exc:
        print(f"tiereg: stopped by {signal.Signals(exc.signum).name}", file=sys.stderr)
        return 128 + exc.signum
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
    except OSError as exc:  # the system failed us (a disk error) outside any output: one line
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"tiereg {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
