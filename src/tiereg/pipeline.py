"""The end-to-end registration: read -> grid -> coarse -> (fine) -> quality.

``register(moving, reference)`` is the one entry point; the command line is a thin layer on it.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ._json import dumps_json
from ._version import __version__
from .coarse import METHODS as COARSE_METHODS
from .coarse import CoarseResult
from .coarse.scoring import tie_cell_for
from .crs import crs_label, crs_units
from .errors import InputError
from .fine import METHODS as FINE_METHODS
from .fine import FineResult
from .io import PointSource, as_point_source
from .level import (
    MIN_CAMERA_TILT_DEG,
    StartingPose,
    Vertical,
    is_steep_ground,
    starting_poses,
    vertical_from_cameras,
    vertical_from_points,
)
from .points import PointSet, gross_outliers, validate_points
from .progress import ProgressFactory, no_progress
from .quality import HeightStats, PointResiduals
from .reference import Reference, prepare_reference
from .stages import Frames, coarse_stage, fine_stage, heights_after, no_coarse_stage
from .transform import Transform
from .verdict import Verdict

MIN_MOVING_POINTS = 30

PointsLike = str | os.PathLike[str] | Sequence[str | os.PathLike[str]] | PointSet | np.ndarray


@dataclass(frozen=True)
class Inputs:
    moving: str
    reference: str
    moving_format: str
    reference_format: str
    n_reference: int
    crs_wkt: str | None = field(default=None, repr=False)
    units: str = "unknown"
    moving_args: tuple[str, ...] = ()  # the paths as given (to read the inputs again)
    reference_args: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        return {
            "moving": self.moving,
            "reference": self.reference,
            "moving_format": self.moving_format,
            "reference_format": self.reference_format,
            "n_reference": self.n_reference,
            "units": self.units,
            "crs": crs_label(self.crs_wkt),
            "crs_wkt": self.crs_wkt,  # for `tiereg apply`: the frame T_ref_mov maps into
            "moving_paths": list(self.moving_args),
            "reference_paths": list(self.reference_args),
        }


@dataclass(frozen=True)
class Levelling:
    """How a model in any orientation was levelled before it was registered: its vertical
    (:class:`~tiereg.level.Vertical`), the starting orientations tried and the one chosen."""

    source: str  # "cameras" or "points": what gave the vertical
    up: tuple[float, float, float]  # the vertical in the model frame
    tilt_deg: float
    sign_known: bool  # cameras tell up from down; a plane does not
    flatness: float
    tried: int  # orientations registered
    confident_answers: int  # of them, those registered confidently: 0 or 1 (the first ends it)
    chosen: str  # the orientation whose answer is the registration's

    def to_dict(self) -> dict[str, Any]:
        return {"source": self.source, "up": list(self.up), "tilt_deg": self.tilt_deg,
                "sign_known": self.sign_known, "flatness": self.flatness, "tried": self.tried,
                "confident_answers": self.confident_answers, "chosen": self.chosen}


@dataclass(frozen=True)
class RegistrationResult:
    """Everything a registration found; ``to_dict()`` is RESULT.json."""

    T_ref_mov: Transform
    confident: bool
    confidence: float
    coarse: CoarseResult | None
    fine: FineResult | None
    quality_before: HeightStats
    quality: HeightStats
    inputs: Inputs
    cell_size: float
    seconds: float  # the whole registration, reading the inputs included
    reasons: tuple[str, ...] = ()
    fine_note: str = ""
    warnings: tuple[str, ...] = ()
    T_initial: Transform | None = None  # the starting pose given by the caller, if any
    residuals: PointResiduals | None = field(default=None, repr=False, compare=False)
    # the prepared reference (its base grid): for reports and control points, and to register
    # more blocks against the same lidar without reading it again
    reference: Reference | None = field(default=None, repr=False, compare=False)
    levelling: Levelling | None = None  # how a model in any orientation was levelled
    reference_seconds: float = 0.0  # of ``seconds``: reading and gridding the reference
    verdict: Verdict | None = None  # the refined fits of the coarse answer and its rivals

    def to_dict(self) -> dict[str, Any]:
        stages: list[dict[str, Any]] = []
        if self.coarse is not None:
            stages.append(self.coarse.to_dict())
        if self.verdict is not None:
            stages.append({"name": "verdict", **self.verdict.to_dict()})
        if self.fine is not None:
            stages.append(self.fine.to_dict())
        else:
            stages.append({"name": "fine", "method": "none", "seconds": 0.0,
                           "note": self.fine_note})
        params = self.T_ref_mov.parameters()
        p = params.to_dict()
        precision = self.fine.precision(params.scale) if self.fine is not None else {
            "scale": None, "omega_deg": None, "phi_deg": None, "kappa_deg": None,
            "translation": None}
        return {
            "tiereg_version": __version__,
            "T_ref_mov": self.T_ref_mov.matrix.tolist(),
            "parameters": p,
            "precision": precision,
            "confident": self.confident,
            "confidence": round(self.confidence, 4),
            "reasons": list(self.reasons),
            "warnings": list(self.warnings),
            "cell_size": self.cell_size,
            "base_cell": None if self.reference is None else self.reference.base_cell,
            "seconds": round(self.seconds, 3),
            "reference_seconds": round(self.reference_seconds, 3),
            "stages": stages,
            "quality": self.quality.to_dict(),
            "quality_before": self.quality_before.to_dict(),
            "inputs": self.inputs.to_dict(),
            "T_initial": None if self.T_initial is None else self.T_initial.matrix.tolist(),
            "levelling": None if self.levelling is None else self.levelling.to_dict(),
            "exports": {
                "pdal_filters_transformation_matrix": self.T_ref_mov.to_pdal(),
                "cloudcompare_matrix": self.T_ref_mov.to_cloudcompare().splitlines(),
            },
        }

    def to_json(self) -> str:
        return dumps_json(self.to_dict())


log = logging.getLogger(__name__)


def _as_source(points: PointsLike | PointSource, fmt: str | None, role: str) -> PointSource:
    return as_point_source(points, role=role, format=fmt)


def _path_args(points: object) -> tuple[str, ...]:
    """The paths a caller gave (absolute), or () for arrays, point sets and prepared sources."""
    if isinstance(points, (str, os.PathLike)):
        return (os.path.abspath(os.fspath(points)),)
    if isinstance(points, Sequence) and points and all(
            isinstance(p, (str, os.PathLike)) for p in points):
        return tuple(os.path.abspath(os.fspath(p)) for p in points)
    if isinstance(points, Reference):
        return points.source_args
    return ()


LEVEL_MODES = ("auto", "cameras", "points", "none")


def find_vertical(source: PointSource, xyz: np.ndarray, *, mode: str) -> Vertical | None:
    """The moving model's vertical when it must be levelled first, else ``None``."""
    vertical = None
    if mode in ("auto", "cameras") and source.info.format in ("colmap", "bundler"):
        if source.info.format == "colmap":
            from .io.colmap import read_colmap_model as read_model
        else:
            from .io.bundler import read_bundler_model as read_model
        model = read_model(source.info.path)
        vertical = vertical_from_cameras(model.camera_centres, model.viewing_directions, xyz)
    if mode == "cameras" and vertical is None:
        raise InputError(f"{source.info.path}: no cameras that look down in this model; use "
                         "`level` points, or give a COLMAP/Bundler model with its images")
    if vertical is not None:  # the sign of the viewing direction decides, upside down included
        return vertical if vertical.off_up_deg > MIN_CAMERA_TILT_DEG else None
    if mode in ("auto", "points"):  # both senses, whatever the tilt: the reference decides
        return vertical_from_points(xyz)
    return None


def _register_levelled(vertical: Vertical, moving: Moving, reference: object,
                       **options: Any) -> RegistrationResult:
    """Register the model from the orientations ``vertical`` proposes
    (:func:`~tiereg.level.starting_poses`, the points as they are first where their plane says
    nothing of their vertical), in their order until one registers confidently: that answer,
    else the most confident of them. A wrong orientation (the ground mirrored) is rejected by
    the verdict as any wrong pose is (the tie points' own scatter bounds what it may leave)."""
    centre = moving.xyz[moving.keep].mean(axis=0)  # the levelling turns about it
    ref, reference_seconds = _open_reference(reference, options["reference_format"],
                                             options["progress"])
    # the points' plane says nothing of their vertical: none, or steep ground leans it
    as_is_first = vertical.source == "points" and (
        vertical.ambiguous or is_steep_ground(ref.base.cell_points(max_cells=100_000)))
    poses: list[StartingPose] = []
    results: list[RegistrationResult] = []
    for pose in starting_poses(vertical, centre, as_is_first=as_is_first):
        if any(r.confident for r in results):
            break
        r = _register_from(moving, ref, initial=pose.T, free_tilt=pose.free_tilt, **options)
        poses.append(pose)
        results.append(replace(r, T_initial=None))
    best = max(results, key=lambda r: (r.confident, r.confidence))
    reasons = list(best.reasons)
    if vertical.ambiguous and not best.confident:  # else the reference decided the vertical
        reasons.append("the vertical of the moving model is ambiguous (no dominant plane); give "
                       "a model with its cameras, or a starting pose (`initial`)")
    info = Levelling(vertical.source, tuple(vertical.up), vertical.tilt_deg, vertical.sign_known,
                     vertical.flatness, len(results), sum(r.confident for r in results),
                     poses[results.index(best)].name)
    return replace(best, reasons=tuple(dict.fromkeys(reasons)), levelling=info,
                   seconds=time.perf_counter() - moving.t0, reference_seconds=reference_seconds)


def register(
    moving: PointsLike | PointSource,
    reference: PointsLike | PointSource | Reference,
    *,
    coarse: str = "auto",
    fine: str = "auto",
    cell_size: float | None = None,
    initial: Transform | np.ndarray | None = None,
    level: str = "auto",
    free_tilt: bool = False,
    scale_range: tuple[float, float] | None = None,
    moving_format: str | None = None,
    reference_format: str | None = None,
    progress: ProgressFactory | None = None,
) -> RegistrationResult:
    """Register the sparse ``moving`` points (tie points) to the dense ``reference`` (lidar).

    Parameters
    ----------
    moving, reference
        Paths (any supported format; several LAS/LAZ tiles, a glob or a folder for the reference),
        a :class:`~tiereg.PointSet`, or an ``(N, 3)`` float64 array. ``reference`` may also be a
        :class:`~tiereg.reference.Reference` prepared once and used for many registrations.
    coarse
        ``"auto"`` (the default), ``"search"``, ``"moments"``, ``"fmt"``, ``"afmt"``,
        ``"qafmt"`` (and their ``-classic`` forms), ``"pomf"`` (translation only), or
        ``"none"`` (keep the input position): :mod:`tiereg.coarse`.
    fine
        ``"auto"`` or ``"lsm"`` (least-squares matching of the points to the lidar surface,
        7 parameters, with precision), ``"planes"`` (matching to planar segments of the lidar
        around each point), ``"icp-point"`` or ``"icp-plane"`` (classic ICP, for
        comparison and dense moving sets), or ``"none"``. It runs when the coarse answer is
        confident (or ``coarse="none"``).
    cell_size
        Grid cell in reference units; by default derived from the moving points' density.
    initial
        A starting ``T_ref_mov`` (e.g. from GNSS/IMU or an earlier run). The moving points are
        placed by it first; the answer includes it. With ``coarse="none"`` the fine stage starts
        from it.
    level
        The moving model's vertical, for models in any orientation (:mod:`tiereg.level`):
        ``"auto"`` (from the cameras of a COLMAP or Bundler model, else from the points when
        their dominant plane is clearly tilted), ``"cameras"``, ``"points"`` or ``"none"``. Not
        used with ``initial`` or ``coarse="none"``.
    free_tilt
        The moving points may lean by a degree or more (a model levelled from its own points, as
        ``level`` does): the coarse stage then judges poses by the heights after a fitted plane.
    scale_range
        ``(low, high)``: the scale is known to lie in this range (reference units per model
        unit, after ``initial``); the similarity search looks only there (by default at every
        scale at which the block could be found), and an answer within a sweep step of either
        end is not confident. Not used by ``coarse="pomf"`` or ``"none"``.

    Returns
    -------
    RegistrationResult
        ``T_ref_mov`` maps moving points into the reference frame; ``confident`` says whether the
        answer can be trusted.
    """
    t0 = time.perf_counter()
    _check_options(coarse=coarse, fine=fine, level=level, cell_size=cell_size,
                   scale_range=scale_range)
    read = _read_moving(moving, moving_format, t0)
    options = dict(coarse=coarse, fine=fine, cell_size=cell_size, scale_range=scale_range,
                   reference_format=reference_format, progress=progress or no_progress)
    if initial is None and coarse != "none" and level != "none":
        vertical = find_vertical(read.source, read.xyz[read.keep], mode=level)
        if vertical is not None:
            return _register_levelled(vertical, read, reference, **options)
    if initial is not None and not isinstance(initial, Transform):
        initial = Transform(np.asarray(initial, dtype=np.float64))
    return _register_from(read, reference, initial=initial, free_tilt=free_tilt, **options)


def _check_options(*, coarse: str, fine: str, level: str, cell_size: float | None,
                   scale_range: tuple[float, float] | None = None) -> None:
    if coarse not in COARSE_METHODS:
        raise InputError(f"unknown coarse method {coarse!r}; choose one of {COARSE_METHODS}")
    if fine not in FINE_METHODS:
        raise InputError(
            f"fine method {fine!r} is not available in tiereg {__version__}; "
            f"choose one of {', '.join(FINE_METHODS)}"
        )
    if level not in LEVEL_MODES:
        raise InputError(f"unknown levelling {level!r}; choose one of {', '.join(LEVEL_MODES)}")
    if cell_size is not None and not (cell_size > 0 and math.isfinite(cell_size)):
        raise InputError(f"cell_size must be a positive number, got {cell_size}")
    if scale_range is not None and not (
            len(scale_range) == 2 and 0 < scale_range[0] <= scale_range[1] < math.inf):
        raise InputError(f"`scale_range` must be two positive numbers, the lower first, got "
                         f"{tuple(scale_range)}")


@dataclass(frozen=True, eq=False)
class Moving:
    """The tie points as read: ``keep`` leaves out a few points far outside the block, which
    would set the levelling, the cell size, the tie grid's extent and how far the fine stage
    moves the block (they are still transformed and reported like every point)."""

    source: PointSource
    xyz: np.ndarray
    keep: np.ndarray
    args: tuple[str, ...]  # the paths as given
    t0: float  # when the registration started (perf_counter)

    def stray_warning(self) -> tuple[str, ...]:
        rows = np.flatnonzero(~self.keep)
        if not len(rows):
            return ()
        return (f"{len(rows)} moving point(s) far outside the block (row(s) "
                f"{', '.join(map(str, rows[:5]))}{' ...' if len(rows) > 5 else ''}, "
                "from 0) were left out of the estimation: check them (a nodata height "
                "such as -9999?)",)


def _read_moving(moving: PointsLike | PointSource, fmt: str | None, t0: float) -> Moving:
    source = _as_source(moving, fmt, "moving")
    points = source.read()
    validate_points(points, min_count=MIN_MOVING_POINTS, role="moving")
    log.info("read %d moving points (%.1f s)", len(points.xyz), time.perf_counter() - t0)
    return Moving(source, points.xyz, ~gross_outliers(points.xyz), _path_args(moving), t0)


def _open_reference(reference: PointsLike | PointSource | Reference, fmt: str | None,
                    progress: ProgressFactory) -> tuple[Reference, float]:
    """The prepared reference and the seconds its preparation took (0 when given prepared)."""
    if isinstance(reference, Reference):
        return reference, 0.0
    source = _as_source(reference, fmt, "reference")
    if source.info.count == 0:
        raise InputError(f"{source.info.path}: the reference point set is empty; "
                         "give a file with points in it")
    t0 = time.perf_counter()
    ref = prepare_reference(source, progress=progress)  # its base cell from its own data
    seconds = time.perf_counter() - t0
    log.info("reference prepared: %d points, base cell %.3g (%.1f s)", source.info.count,
             ref.base_cell, seconds)
    return replace(ref, source_args=_path_args(reference)), seconds


def _register_from(moving: Moving, reference: PointsLike | PointSource | Reference, *,
                   initial: Transform | None, coarse: str, fine: str, cell_size: float | None,
                   free_tilt: bool, scale_range: tuple[float, float] | None,
                   reference_format: str | None, progress: ProgressFactory
                   ) -> RegistrationResult:
    """The registration of tie points placed by ``initial``: centre, coarse (with its verdict),
    fine, and the heights after."""
    keep = moving.keep
    mov_xyz = moving.xyz if initial is None else initial.apply(moving.xyz)
    o_mov = np.round(mov_xyz[keep].mean(axis=0))
    mov_local = mov_xyz - o_mov
    # the tie points' own grid cell, in their own units (the reference's, after ``initial``)
    tie_cell = tie_cell_for(mov_local[keep])
    ref, reference_seconds = _open_reference(reference, reference_format, progress)
    frames = Frames(ref.origin, o_mov, Transform.identity() if initial is None else initial)
    if coarse == "none":  # the moving points are in the reference frame: a cell in its units
        start = no_coarse_stage(mov_local, ref, frames, cell_size=cell_size or tie_cell)
    else:
        start = coarse_stage(mov_local, keep, ref, frames, method=coarse, tie_cell=tie_cell,
                             cell_size=cell_size, free_tilt=free_tilt, scale_range=scale_range)
    polished = fine_stage(mov_local, keep, ref, start, method=fine, coarse_method=coarse)
    after, residuals = heights_after(mov_local, keep, ref, start, polished)
    return RegistrationResult(
        T_ref_mov=frames.to_world(polished.T_local),
        confident=bool(polished.confident),
        confidence=float(polished.confidence),
        coarse=start.result,
        fine=None if polished.result is None else replace(polished.result, lidar=None),
        quality_before=start.before,
        quality=after,
        inputs=_inputs(moving, ref, reference),
        cell_size=float(start.cell_size),
        seconds=time.perf_counter() - moving.t0,
        reference_seconds=reference_seconds,
        reasons=start.reasons + polished.reasons,
        fine_note=polished.note,
        warnings=moving.stray_warning() + polished.warnings,
        T_initial=initial,
        residuals=residuals,
        reference=ref,
        verdict=start.verdict,
    )


def _inputs(moving: Moving, ref: Reference, reference: object) -> Inputs:
    info = ref.source.info
    return Inputs(
        moving=moving.source.info.path,
        reference=info.path,
        moving_format=moving.source.info.format,
        reference_format=info.format,
        n_reference=info.count,
        crs_wkt=info.crs_wkt,
        units=crs_units(info.crs_wkt),
        moving_args=moving.args,
        reference_args=_path_args(reference),
    )
