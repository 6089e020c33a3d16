"""The options of the ``tiereg`` commands (:func:`build_parser`) and their examples."""

from __future__ import annotations

import argparse

from ._version import __version__

EXIT_BAD_INPUT = 2  # bad usage or input: one line on stderr

EXAMPLES = {
    "register": """examples:
  tiereg register tiepoints.txt lidar.laz -o RESULT.json
  tiereg register sparse/0 tiles/ -o RESULT.json --output-points tie_in_lidar_frame.laz
  tiereg register points3D.txt 'tiles/*.laz' -o RESULT.json --cell-size 40 -q
  tiereg register ties.txt lidar.laz -o RESULT.json --coarse none --initial approx.txt
  tiereg register ties.txt lidar.laz -o RESULT.json --report report/""",
    "overlap": """examples:
  tiereg overlap tiepoints.txt lidar.laz
  tiereg overlap sparse/0 tiles/ --out overlap/   (overlap.json, overlap.geojson, overlap.png)""",
    "report": """examples:
  tiereg report RESULT.json report/     (run where `tiereg register` ran: it reads the inputs again)
  then open report/report.html in a browser""",
    "apply": """examples:
  tiereg apply RESULT.json tiepoints.txt tiepoints_registered.txt
  tiereg apply RESULT.json model.ply model_georef.ply
  tiereg apply --inverse RESULT.json lidar.laz lidar_in_model_frame.laz
  tiereg apply matrix.txt dsm.tif dsm_moved.tif      (16 numbers: PDAL/CloudCompare matrix)""",
    "grid": """examples:
  tiereg grid lidar.laz dsm.tif --cell-size 1 --stat max
  tiereg grid 'tiles/*.laz' dem.tif --cell-size 2 --stat min
  tiereg grid archive/ dsm.tif --cell-size 1 --workers 2    (a tile a task on 2 processes)""",
    "batch": """examples:
  tiereg batch blocks/*.txt 'archive/*.laz' --out results/ --workers 2
  tiereg batch a.txt b.txt archive/ --out results/ --scheduler tcp://10.0.0.5:8786 --report""",
    "info": """examples:
  tiereg info lidar.laz
  tiereg info sparse/0 --json""",
    "simulate": """examples:
  tiereg simulate scene1
  tiereg simulate scene2 --kind urban --seed 7 --overlap 0.5 --heading 130 --scale 3.2808
  tiereg simulate small --world-size 3000 --lidar-size 2000 --block-size 1500""",
    "demo": """examples:
  tiereg demo
  tiereg demo --out /tmp/tiereg-demo -q; echo $?   # 0: confident, 3: not""",
}


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors (exit code 2) that knows its commands and their flags."""

    def __init__(self, *args, **kwargs) -> None:
        self.flags: set[str] = set()  # the option strings of this (sub)command
        self.commands: dict[str, Parser] = {}
        super().__init__(*args, **kwargs)  # adds --help

    def add_argument(self, *args, **kwargs) -> argparse.Action:
        action = super().add_argument(*args, **kwargs)
        self.flags.update(action.option_strings)
        return action

    def add_exclusive(self, *arguments: tuple[tuple, dict]) -> None:
        """Mutually exclusive options, each given as ``(args, kwargs)`` of ``add_argument``."""
        group = self.add_mutually_exclusive_group()
        for args, kwargs in arguments:
            self.flags.update(group.add_argument(*args, **kwargs).option_strings)

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _add_common(p: Parser) -> None:
    p.add_exclusive(
        (("-q", "--quiet"), dict(action="store_true", help="print errors only, no progress")),
        (("-v", "--verbose"), dict(action="count", default=0, help="more detail (-vv: debug)")))


def build_parser() -> Parser:
    parser = Parser(
        prog="tiereg",
        description="Co-register photogrammetric tie points (moving) with airborne lidar "
                    "(reference), with no initial guess.",
        epilog="Run 'tiereg COMMAND --help' for a command's options and examples.",
    )
    parser.add_argument("--version", action="version", version=f"tiereg {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    from .calibrate.cli import EXAMPLES as CALIBRATE_EXAMPLES
    from .calibrate.cli import add_arguments as calibrate_args

    EXAMPLES.setdefault("calibrate", CALIBRATE_EXAMPLES)
    for name, help_, add_arguments in _PARSERS + (
            ("calibrate", "Calibrate the cameras of a COLMAP MODEL against a lidar REFERENCE "
                          "(self-calibrating bundle adjustment).", calibrate_args),):
        p = sub.add_parser(name, help=help_, description=help_, epilog=EXAMPLES.get(name),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        _add_common(p)
        add_arguments(p)
        parser.commands[name] = p
    return parser


def _register_args(p: Parser) -> None:
    from .coarse import METHODS as COARSE
    from .fine import METHODS as FINE

    p.add_argument("moving", metavar="MOVING", help="tie points: XYZ/CSV, PLY, LAS/LAZ, COLMAP "
                   "points3D.txt/.bin or model folder, Bundler .out")
    p.add_argument("reference", metavar="REFERENCE", nargs="+",
                   help="lidar LAS/LAZ file(s), a folder or glob of tiles, or a GeoTIFF DSM")
    p.add_argument("-o", "--output", required=True, metavar="RESULT.json",
                   help="where to write the result")
    p.add_argument("--coarse", choices=COARSE, default="auto", help="coarse method (default auto)")
    p.add_argument("--fine", choices=FINE, default="auto", help="fine method")
    p.add_argument("--cell-size", type=float, metavar="M",
                   help="grid cell in reference units (default: from the tie-point density)")
    p.add_argument("--level", choices=("auto", "cameras", "points", "none"), default="auto",
                   help="vertical of a model in any orientation: from a COLMAP/Bundler model's "
                   "cameras, from the points' dominant plane, or none (default auto); not used "
                   "with --initial or --coarse none, whose pose already says which way is up")
    p.add_argument("--free-tilt", action="store_true",
                   help="the moving points may lean by a degree or more (a model levelled from "
                   "its own points; --level does this by itself): heights are compared after "
                   "a fitted plane")
    p.add_argument("--initial", metavar="TRANSFORM",
                   help="a starting pose (RESULT.json or a 16-number matrix file); with "
                   "--coarse none the fine stage starts from it")
    p.add_argument("--scale-range", type=float, nargs=2, metavar=("LO", "HI"),
                   help="the scale is known to lie in this range (reference units per model "
                   "unit): only it is searched (default: every scale the data allow)")
    p.add_argument("--report", metavar="DIR",
                   help="write a report: maps, histograms, statistics, control points, report.html")
    p.add_argument("--output-points", metavar="PATH",
                   help="also write the moving points in the reference frame (format by suffix)")
    p.add_argument("--moving-format", metavar="FMT", help="override format detection")
    p.add_argument("--reference-format", metavar="FMT", help="override format detection")
    p.add_argument("--seed", type=int, default=0, help="accepted for scripts that pass one: the "
                   "registration draws no random numbers, so every run gives the same answer")


def _overlap_args(p: Parser) -> None:
    from .coarse import METHODS as COARSE

    p.add_argument("moving", metavar="MOVING")
    p.add_argument("reference", metavar="REFERENCE", nargs="+")
    p.add_argument("--out", metavar="DIR", help="write overlap.json, overlap.geojson (the "
                   "outline) and overlap.png")
    p.add_argument("--coarse", choices=COARSE, default="auto", help="coarse method (default auto)")
    p.add_argument("--cell-size", type=float, metavar="M")
    p.add_argument("--moving-format", metavar="FMT")
    p.add_argument("--reference-format", metavar="FMT")


def _report_args(p: Parser) -> None:
    p.add_argument("result", metavar="RESULT.json")
    p.add_argument("out", metavar="DIR", help="report folder (created if needed)")


def _apply_args(p: Parser) -> None:
    p.add_argument("transform", metavar="TRANSFORM", help="RESULT.json, JSON with 'matrix', or "
                   "a text file of 16 numbers")
    p.add_argument("input", metavar="IN", help="points (any readable format) or a GeoTIFF DSM")
    p.add_argument("output", metavar="OUT", help="output; LAS/LAZ keeps all point attributes")
    p.add_argument("--inverse", action="store_true",
                   help="apply the inverse (reference frame -> moving frame)")
    p.add_argument("--format", metavar="FMT", help="input format, if detection fails")


def _grid_args(p: Parser) -> None:
    p.add_argument("input", metavar="POINTS", nargs="+", help="point file(s), folder or glob")
    p.add_argument("output", metavar="OUT.tif")
    p.add_argument("--cell-size", type=float, metavar="M",
                   help="cell size in file units (default: about 4 points per cell)")
    p.add_argument("--stat", choices=("mean", "min", "max", "median", "count"), default="mean")
    p.add_argument("--format", metavar="FMT", help="input format, if detection fails")
    _add_cluster(p)


def _batch_args(p: Parser) -> None:
    p.add_argument("paths", metavar="BLOCKS... REFERENCE", nargs="+", help="the blocks' tie "
                   "points, then the archive: a folder or quoted glob of LAS/LAZ/COPC tiles")
    p.add_argument("--out", required=True, metavar="DIR", help="results: a folder per block "
                   "(RESULT.json), summary.csv, overview.png; blocks done there are skipped")
    p.add_argument("--report", action="store_true", help="a report per block")
    p.add_argument("--scale-range", type=float, nargs=2, default=(0.25, 4.0), metavar=("LO",
                   "HI"), help="the blocks' scale, reference units per model unit (default "
                   "0.25 4); a narrower range searches fewer windows")
    _add_cluster(p)


def _info_args(p: Parser) -> None:
    p.add_argument("input", metavar="FILE", nargs="+")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--format", metavar="FMT", help="input format, if detection fails")


def _simulate_args(p: Parser) -> None:
    p.add_argument("out", metavar="OUTDIR")
    p.add_argument("--kind", choices=("farmland", "suburban", "urban", "forest", "mountains"),
                   default="suburban")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--overlap", type=float, default=1.0, help="share of the block inside the "
                   "lidar footprint, in (0, 1]; the coarse stage needs 0.3 or more")
    p.add_argument("--heading", type=float, help="hidden heading in degrees (default random)")
    p.add_argument("--scale", type=float, help="hidden scale, model units per metre (default "
                   "random in 0.25-4)")
    p.add_argument("--lidar-density", type=float, default=2.0, metavar="PTS_PER_M2")
    p.add_argument("--tie-density", type=float, default=350.0, metavar="PTS_PER_KM2")
    p.add_argument("--world-size", type=float, default=8000.0, metavar="M")
    p.add_argument("--lidar-size", type=float, default=4000.0, metavar="M")
    p.add_argument("--block-size", type=float, default=3000.0, metavar="M")


def _demo_args(p: Parser) -> None:
    p.add_argument("--out", default="demo-output", metavar="DIR", help="output folder")


_PARSERS = (
    ("register", "Register MOVING points (tie points) to a REFERENCE (lidar or DSM).",
     _register_args),
    ("overlap", "Do MOVING and REFERENCE overlap, and where? A quick answer from the coarse "
                "registration.", _overlap_args),
    ("report", "Write the report of an earlier registration from its RESULT.json.", _report_args),
    ("apply", "Apply a transform (RESULT.json or a 4x4 matrix file) to a point file or DSM.",
     _apply_args),
    ("grid", "Rasterize points into a GeoTIFF (streaming; memory follows the grid).", _grid_args),
    ("batch", "Register many BLOCKS (tie points) against one lidar archive, each found anywhere "
              "in it.", _batch_args),
    ("info", "Describe a point file, tile set or DSM: format, count, extent, CRS, density.",
     _info_args),
    ("simulate", "Simulate a scene with a known answer: lidar (reference.laz), tie points "
                 "(tiepoints.xyz) and truth.json.", _simulate_args),
    ("demo", "Register the shipped COLMAP model to the shipped lidar sample and compare with the "
             "truth.", _demo_args),
)


def _add_cluster(p: Parser) -> None:
    p.add_exclusive(
        (("--workers",), dict(type=int, metavar="N", help="a local Dask cluster of N processes")),
        (("--scheduler",), dict(metavar="ADDRESS", help="a running Dask scheduler "
                                "(tcp://host:8786); its workers must see the same files")))
