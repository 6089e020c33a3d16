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
from .coarse import CoarseResult, register_translation
from .coarse.scoring import ScaleRange, tie_cell_for
from .coarse.similarity import register_similarity
from .crs import crs_label, crs_units
from .errors import InputError
from .fine import METHODS as FINE_METHODS
from .fine import FineResult, register_fine
from .io import PointSource, as_point_source
from .level import (
    MIN_CAMERA_TILT_DEG,
    Vertical,
    starting_poses,
    vertical_from_cameras,
    vertical_from_points,
)
from .points import PointSet, gross_outliers, validate_points
from .progress import ProgressFactory, no_progress
from .quality import HeightStats, PointResiduals
from .reference import Reference, prepare_reference
from .surface import LocalSurface, SurfaceSampler
from .transform import Transform
from .verdict import HOPELESS_UNEXPLAINED, Verdict, decide, judge_refined

MIN_MOVING_POINTS = 30
# the quality heights: local planes of the lidar within this many spacings of a tie point; half a
# spacing inside the corridor the fine stage reads (2.5 spacings at least), so that the fine
# stage's move cannot take a neighbour out of it
SURFACE_RADIUS_SPACINGS = 2.0

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
    levelling: dict[str, Any] | None = None  # how a model in any orientation was levelled
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
            "levelling": self.levelling,
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


def _scatter(values: np.ndarray, where: np.ndarray) -> np.ndarray:
    """``values`` of the points set in ``where``, NaN for the others: a value per point."""
    out = np.full(len(where), np.nan)
    out[where] = values
    return out


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


def _register_levelled(vertical: Vertical, mov_src: PointSource, centre: np.ndarray,
                       moving: object, reference: object, **options: Any) -> RegistrationResult:
    """Register the model from each of the orientations ``vertical`` proposes
    (:func:`~tiereg.level.starting_poses`); the answer whose registration is confident (then the
    more confident) wins, and two confident answers that disagree are no answer. ``centre``: the
    model's centroid, which the levelling turns about."""
    poses = starting_poses(vertical, centre)
    results: list[RegistrationResult] = []
    for pose in poses:
        r = register(mov_src, results[0].reference if results else reference, initial=pose.T,
                     level="none", free_tilt=pose.free_tilt, **options)
        results.append(replace(r, T_initial=None))
    best = max(results, key=lambda r: (r.confident, r.confidence))
    reasons = list(best.reasons)
    if vertical.ambiguous and not best.confident:  # else the reference decided the vertical
        reasons.append("the vertical of the moving model is ambiguous (no dominant plane); give "
                       "a model with its cameras, or a starting pose (`initial`)")
    rivals = [r for r in results if r.confident and r is not best
              and not _same_answer(r, best, centre[None])]
    if rivals:  # the lidar decides between them, as between the coarse stage's rivals
        decided = _better_orientation([best, *rivals], mov_src, centre)
        best, rivals = (decided, []) if decided is not None else (best, rivals)
    if rivals:
        reasons.append("two orientations of the vertical register confidently: the answer is "
                       "ambiguous")
    info = {"source": vertical.source, "up": list(vertical.up), "tilt_deg": vertical.tilt_deg,
            "sign_known": vertical.sign_known, "flatness": vertical.flatness,
            "tried": len(results), "confident_answers": sum(r.confident for r in results),
            "chosen": poses[results.index(best)].name}
    confident = best.confident and not rivals
    inputs = replace(best.inputs, moving_args=_path_args(moving))
    return replace(best, confident=confident, reasons=tuple(dict.fromkeys(reasons)),
                   confidence=best.confidence if confident else min(best.confidence, 0.49),
                   levelling=info, inputs=inputs, seconds=sum(r.seconds for r in results),
                   reference_seconds=results[0].reference_seconds)


def _better_orientation(results: list[RegistrationResult], mov_src: PointSource,
                        centre: np.ndarray) -> RegistrationResult | None:
    """Of confident registrations from different orientations that disagree, the one whose
    refined fit explains the tie points' heights beyond doubt (:func:`~tiereg.verdict.decide`),
    or ``None``."""
    ref = results[0].reference
    moving = mov_src.read().xyz - centre
    to_local = Transform.from_translation(-ref.origin)
    starts = [to_local @ r.T_ref_mov @ Transform.from_translation(centre) for r in results]
    verdict = decide(moving, ref, starts, cell=max(r.cell_size for r in results))
    return results[verdict.chosen] if verdict.confident else None


def _same_answer(a: RegistrationResult, b: RegistrationResult, centre: np.ndarray) -> bool:
    """Two registrations agree: rotation within 2 degrees, scale within 2 %, the block centre
    within a cell."""
    Ta, Tb = a.T_ref_mov, b.T_ref_mov
    Ra = Ta.matrix[:3, :3] / Ta.parameters().scale
    Rb = Tb.matrix[:3, :3] / Tb.parameters().scale
    angle = math.degrees(math.acos(float(np.clip((np.trace(Ra @ Rb.T) - 1) / 2, -1, 1))))
    ratio = Ta.parameters().scale / Tb.parameters().scale
    moved = float(np.linalg.norm(Ta.apply(centre) - Tb.apply(centre)))
    return angle <= 2.0 and abs(ratio - 1) <= 0.02 and moved <= max(a.cell_size, b.cell_size)


def _to_world(T_local: Transform, o_ref: np.ndarray, o_mov: np.ndarray) -> Transform:
    """``T_ref_mov`` in file coordinates from one between the two local (centred) frames."""
    return Transform.from_translation(o_ref) @ T_local @ Transform.from_translation(-o_mov)


def height_differences(xyz_ref: np.ndarray, surface: SurfaceSampler | LocalSurface
                       ) -> np.ndarray:
    """``Z(x, y) - z`` of points (the surface's local frame) on the surface; NaN off it."""
    if isinstance(surface, LocalSurface):
        return surface.heights(xyz_ref[:, 0], xyz_ref[:, 1]) - xyz_ref[:, 2]
    z, ok = surface.sample(xyz_ref[:, 0], xyz_ref[:, 1])
    return np.where(ok, z - xyz_ref[:, 2], np.nan)


def _translation_grid(ref: Reference, cell_size: float, moving: np.ndarray):
    """The reference grid a translation-only search correlates (``cell_size``: reference units),
    refused where it or the tie points' grid on its lattice would exceed
    :data:`~tiereg.coarse.scoring.MAX_REFERENCE_CELLS` or
    :data:`~tiereg.coarse.scoring.MAX_TIE_SIDE` cells a side."""
    from .coarse.scoring import MAX_REFERENCE_CELLS, MAX_TIE_SIDE

    (x0, y0, x1, y1) = ref.base.spec.bounds
    extent = np.ptp(moving[:, :2], axis=0).max()
    least = max(max(x1 - x0, y1 - y0) / MAX_REFERENCE_CELLS, extent / MAX_TIE_SIDE)
    if cell_size < least:
        raise InputError(f"cell_size {cell_size:g} is too fine for a translation-only search of "
                         f"this reference and block; give cell_size of at least {least:.3g} "
                         "(reference units), or let the coarse stage find the scale too")
    return ref.grid(cell_size)


MIN_TIE_SIDE = 32  # a coarser tie cell is tried only while the block spans this many cells


def _coarser_tie_cell(scale: float, moving: np.ndarray, ref: Reference,
                      tie_cell: float) -> float | None:
    """Twice ``tie_cell`` when an answer at ``scale`` (reference units per model unit) lies
    within a sweep step of the smallest scale the search could reach with ``tie_cell`` and the
    block still spans :data:`MIN_TIE_SIDE` doubled cells (a dense model gridded as if
    thinned), else None."""
    extent = float(np.max(moving[:, :2].max(axis=0) - moving[:, :2].min(axis=0)))
    if (not ScaleRange.of(moving, ref, tie_cell).at_lowest(scale)
            or extent / (2 * tie_cell) < MIN_TIE_SIDE):
        return None
    return 2 * tie_cell


def _similarity(moving: np.ndarray, ref: Reference, *, tie_cell: float, method: str,
                free_tilt: bool) -> tuple[CoarseResult, float]:
    """:func:`~tiereg.coarse.similarity.register_similarity`, searched again with a coarser tie
    cell while its answer lies at the smallest scale the tie cell lets the reference be searched
    at (the block may be smaller still); the result and the tie cell it was found with."""
    result = register_similarity(moving, ref, tie_cell=tie_cell, method=method,
                                 free_tilt=free_tilt)
    while (coarser := _coarser_tie_cell(result.T_ref_mov.scale, moving, ref,
                                        tie_cell)) is not None:
        log.info("answer at the smallest scale searched: tie cell %.4g -> %.4g", tie_cell,
                 coarser)
        tie_cell = coarser
        result = register_similarity(moving, ref, tie_cell=tie_cell, method=method,
                                     free_tilt=free_tilt)
    return result, tie_cell


def _height_stats(xyz_ref: np.ndarray, sampler: SurfaceSampler) -> HeightStats:
    return HeightStats.from_dz(height_differences(xyz_ref, sampler), len(xyz_ref))


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

    Returns
    -------
    RegistrationResult
        ``T_ref_mov`` maps moving points into the reference frame; ``confident`` says whether the
        answer can be trusted.
    """
    t0 = time.perf_counter()
    progress = progress or no_progress
    if coarse not in COARSE_METHODS:
        raise InputError(f"unknown coarse method {coarse!r}; choose one of {COARSE_METHODS}")
    if fine not in FINE_METHODS:
        raise InputError(
            f"fine method {fine!r} is not available in tiereg {__version__}; "
            f"choose one of {', '.join(FINE_METHODS)}"
        )
    if level not in LEVEL_MODES:
        raise InputError(f"unknown levelling {level!r}; choose one of {', '.join(LEVEL_MODES)}")
    mov_src = _as_source(moving, moving_format, "moving")
    mov = mov_src.read()
    validate_points(mov, min_count=MIN_MOVING_POINTS, role="moving")
    log.info("read %d moving points (%.1f s)", len(mov.xyz), time.perf_counter() - t0)
    # a few points far outside the block would set the levelling, the cell size, the tie grid's
    # extent and how far the fine stage moves the block: they are left out of all estimation,
    # and still transformed and reported like every point
    stray = gross_outliers(mov.xyz)
    keep = ~stray
    if initial is None and coarse != "none" and level != "none":
        vertical = find_vertical(mov_src, mov.xyz[keep], mode=level)
        if vertical is not None:
            return _register_levelled(vertical, mov_src, mov.xyz[keep].mean(axis=0), moving,
                                      reference, coarse=coarse,
                                      fine=fine, cell_size=cell_size,
                                      reference_format=reference_format, progress=progress)
    if initial is not None and not isinstance(initial, Transform):
        initial = Transform(np.asarray(initial, dtype=np.float64))
    mov_xyz = mov.xyz if initial is None else initial.apply(mov.xyz)
    T_start = Transform.identity() if initial is None else initial
    o_mov = np.round(mov_xyz[keep].mean(axis=0))
    mov_local = mov_xyz - o_mov
    # the tie points' own grid cell, in their own units (the reference's, after ``initial``)
    tie_cell = tie_cell_for(mov_local[keep])
    if cell_size is not None and not (cell_size > 0 and math.isfinite(cell_size)):
        raise InputError(f"cell_size must be a positive number, got {cell_size}")

    reference_seconds = 0.0
    if isinstance(reference, Reference):
        ref = reference
    else:
        ref_src = _as_source(reference, reference_format, "reference")
        if ref_src.info.count == 0:
            raise InputError(f"{ref_src.info.path}: the reference point set is empty; "
                             "give a file with points in it")
        t_ref = time.perf_counter()
        ref = prepare_reference(ref_src, progress=progress)  # its base cell from its own data
        reference_seconds = time.perf_counter() - t_ref
        log.info("reference prepared: %d points, base cell %.3g (%.1f s)", ref_src.info.count,
                 ref.base_cell, reference_seconds)
        ref = replace(ref, source_args=_path_args(reference))
    ref_src, o_ref = ref.source, ref.origin
    T_in = Transform.from_translation(o_ref).inverse  # reference -> local
    T_mov_local = Transform.from_translation(o_mov)  # local moving -> moving

    coarse_result: CoarseResult | None = None
    verdict: Verdict | None = None
    reasons: list[str] = []
    if coarse == "none":
        T_local = T_in @ T_mov_local
        cell_size = cell_size or tie_cell  # the moving points are in the reference frame
        before = _height_stats(T_local.apply(mov_local), ref.surface())
        confident, confidence = before.overlap_fraction > 0.3, 0.0
        reasons.append("no coarse registration was asked for (`coarse` none)")
    else:
        if coarse == "pomf":  # level data at the reference's scale: a cell in its units
            grid = _translation_grid(ref, cell_size or tie_cell, mov_local[keep])
            coarse_result = register_translation(mov_local[keep], grid,
                                                 reference_fine=ref.base)
        else:  # search, auto
            coarse_result, tie_cell = _similarity(mov_local[keep], ref, tie_cell=tie_cell,
                                                  method=coarse, free_tilt=free_tilt)
        T_local = coarse_result.T_ref_mov
        log.info("coarse (%s): scale %.6g, heading %.2f deg, %s (%.1f s)", coarse,
                 T_local.scale, math.degrees(T_local.parameters().kappa) % 360.0,
                 "confident" if coarse_result.confident else "not confident",
                 coarse_result.seconds)
        # the registration's cell, in reference units: the tie cell at the scale found
        cell_size = cell_size or coarse_result.cell_size
        before = _height_stats((T_in @ T_mov_local).apply(mov_local), ref.surface())
        if coarse == "pomf":
            confident, confidence = coarse_result.confident, coarse_result.confidence
            reasons.extend(coarse_result.reasons)
        else:  # the refined fits of the answer and its rivals decide
            verdict = judge_refined(mov_local[keep], ref, coarse_result, tie_cell=tie_cell,
                                    cell=cell_size)
            T_local = verdict.best.T
            confident = verdict.confident and not coarse_result.limits
            confidence = verdict.confidence if confident else min(verdict.confidence, 0.49)
            reasons.extend(verdict.reasons + coarse_result.limits)
            log.info("verdict: pose %d of %d (0: the coarse answer), %s (%.1f s so far)",
                     verdict.chosen, len(verdict.poses),
                     "confident" if confident else "not confident", time.perf_counter() - t0)
        coarse_result = replace(coarse_result,
                                T_ref_mov=_to_world(coarse_result.T_ref_mov, o_ref, o_mov)
                                @ T_start)
    sampler = ref.surface()

    T_before_fine = T_local
    fine_result: FineResult | None = None
    warnings: list[str] = []
    if stray.any():
        rows = np.flatnonzero(stray)
        warnings.append(f"{len(rows)} moving point(s) far outside the block (row(s) "
                        f"{', '.join(map(str, rows[:5]))}{' ...' if len(rows) > 5 else ''}, "
                        "from 0) were left out of the estimation: check them (a nodata height "
                        "such as -9999?)")
    fine_note = "not asked for (`fine` none)"
    # the fine stage polishes a pose that explains the heights, confident or not (a right pose
    # metres off in height is confident only after it); it cannot make a wrong one right
    hopeless = (verdict.best.unexplained > HOPELESS_UNEXPLAINED if verdict is not None
                else coarse == "pomf" and not confident)
    if fine != "none" and hopeless:
        fine_note = "skipped: no pose found explains the tie points' heights"
    elif fine != "none":
        fine_result = register_fine(T_local.apply(mov_local[keep]), ref, cell_size=cell_size,
                                    method="lsm" if fine == "auto" else fine)
        log.info("fine (%s): %s (%.1f s)", fine_result.method,
                 f"refused: {fine_result.refused}" if fine_result.refused else "accepted",
                 fine_result.seconds)
        vouched = verdict is not None and not fine_result.contradicts_coarse
        if fine_result.refused and vouched:
            # the verdict's refined fit already placed the tie points on the surface; a fine
            # stage that finds nothing better leaves that pose as the answer
            warnings.append(f"the fine stage kept the coarse answer: {fine_result.refused}")
        elif fine_result.refused:
            # nothing vouches for the pose to the tie points' precision, and a fine answer that
            # moves far contradicts it
            confident = False
            start = "starting pose" if coarse == "none" else "coarse answer"
            advice = ("check the inputs (noise points in the lidar not classed as noise, a wrong "
                      "unit or CRS)" if fine_result.contradicts_coarse else
                      "give a closer starting pose (`initial`), or let the coarse stage find it"
                      if coarse == "none" else "check the inputs")
            verb = "contradicts" if fine_result.contradicts_coarse else "could not confirm"
            reasons.append(f"the fine stage {verb} the {start}: {fine_result.refused}; {advice}")
        else:
            T_local = fine_result.T_increment @ T_local
        if fine_result.held and not fine_result.refused:
            warnings.append(f"the data do not determine {', '.join(fine_result.held)} (flat or "
                            "featureless ground): held at the coarse answer")

    placed = T_local.apply(mov_local)
    # the heights after registration against the lidar's own points where the fine stage read
    # them (a grid cell's mean is metres off beside walls and in canopy gaps), else the grid
    surface: SurfaceSampler | LocalSurface = sampler
    if fine_result is not None and fine_result.lidar is not None and len(fine_result.lidar) >= 50:
        surface = LocalSurface(fine_result.lidar, radius=SURFACE_RADIUS_SPACINGS * ref.spacing)
    if fine_result is not None:
        fine_result = replace(fine_result, lidar=None)
    dz_after = height_differences(placed, surface)
    after = HeightStats.from_dz(dz_after, len(placed))
    accepted = fine_result is not None and not fine_result.refused
    residuals = PointResiduals.from_dz(
        placed + o_ref, height_differences(T_before_fine.apply(mov_local), surface), dz_after,
        _scatter(np.where(np.isfinite(fine_result.fit.residuals), fine_result.fit.weights,
                          np.nan), keep) if accepted else None)
    T_ref_mov = _to_world(T_local, o_ref, o_mov) @ T_start
    inputs = Inputs(
        moving=mov_src.info.path,
        reference=ref_src.info.path,
        moving_format=mov_src.info.format,
        reference_format=ref_src.info.format,
        n_reference=ref_src.info.count,
        crs_wkt=ref_src.info.crs_wkt,
        units=crs_units(ref_src.info.crs_wkt),
        moving_args=_path_args(moving),
        reference_args=_path_args(reference),
    )
    return RegistrationResult(
        T_ref_mov=T_ref_mov,
        confident=bool(confident),
        confidence=float(confidence),
        coarse=coarse_result,
        fine=fine_result,
        quality_before=before,
        quality=after,
        inputs=inputs,
        cell_size=float(cell_size),
        seconds=time.perf_counter() - t0,
        reference_seconds=reference_seconds,
        reasons=tuple(reasons),
        fine_note=fine_note,
        warnings=tuple(warnings),
        T_initial=initial,
        residuals=residuals,
        reference=ref,
        verdict=verdict,
    )
