"""``tiereg.calibrate``: register a COLMAP model to the lidar, then let the lidar calibrate it.

1. The model is registered (:func:`tiereg.register`), or placed by a given ``T_ref_mov``.
2. In the reference frame (near the lidar's origin), the tie points on planar, smooth lidar
   patches are split into control points and held-out check points (one in
   ``1 / CHECK_EVERY``, spread over the block).
3. Rounds of a self-calibrating bundle adjustment (:mod:`tiereg.calibrate.adjust`): the control
   points whose lidar residual is more than ``REJECT_SIGMAS`` robust standard deviations off
   are left out (canopy, moved objects, blunders), the patches are fitted again where the points
   moved, until the control set no longer changes.
4. After each adjustment the covariance of the intrinsics says which ones the block does not
   determine (:data:`TOLERANCE`): they are put back to their input value, held, and the round
   is solved again. Held parameters are reported with the reason.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import load_transform
from ..quality import HeightStats
from ..robust import nmad
from ..transform import Transform
from .adjust import refine_indices
from .degenerate import TOLERANCE, Tolerance
from .lidar import LidarPatches, Patches, lidar_reference
from .model import observations, poses_points, read_model, reprojection, transform_model
from .result import PARAM_NAMES, CalibrationResult, CameraCalibration
from .rounds import (
    MAX_ROUNDS,
    Outcome,
    Rounds,
    check_split,
    pixel_sigma,
    run_rounds,
    select_control,
    spread,
)

log = logging.getLogger(__name__)

REFINE_KINDS = ("focal", "principal", "distortion", "poses")
MIN_CONTROL = 10
CHECK_OUTLIER_NMADS = 5.0


def _registration(model: Path, reference, T_ref_mov, reference_format):
    """``(T_ref_mov, confident, Reference, reasons)`` from a registration or as given."""
    from ..pipeline import register

    if T_ref_mov is None:
        reg = register(str(model), reference, reference_format=reference_format)
        return reg.T_ref_mov, reg.confident, reg.reference, tuple(reg.reasons)
    if not isinstance(T_ref_mov, Transform):
        T_ref_mov = Transform(np.asarray(T_ref_mov, dtype=np.float64))
    return T_ref_mov, True, lidar_reference(reference, reference_format=reference_format), ()


def _rms(res: np.ndarray) -> float:
    ok = np.isfinite(res).all(axis=1)
    return float(np.sqrt(np.mean(np.sum(res[ok] ** 2, axis=1)))) if ok.any() else float("nan")


def _stats(patches: Patches, mask: np.ndarray) -> HeightStats | None:
    if not mask.any():
        return None
    return HeightStats.from_dz(patches.dz_m[mask], int(mask.sum()))


def _parse_refine(refine) -> tuple[str, ...]:
    if isinstance(refine, str):
        refine = tuple(w.strip() for w in refine.split(",") if w.strip())
    bad = [w for w in refine if w not in REFINE_KINDS]
    if bad or not refine:
        raise InputError(f"`refine`: unknown {', '.join(bad) or 'empty list'}; give a comma "
                         f"list of {', '.join(REFINE_KINDS)}")
    return tuple(refine)


def _camera_results(rec, start: dict[int, np.ndarray], cov: np.ndarray, labels: list,
                    held: dict[tuple[int, int], str], rms_before: dict, rms_after: dict,
                    n_images: dict) -> tuple[CameraCalibration, ...]:
    sig = np.sqrt(np.maximum(np.diag(cov), 0.0)) if len(labels) else np.zeros(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sig, sig) if len(labels) else cov
    out = []
    for cid in sorted(rec.cameras):
        cam = rec.cameras[cid]
        names = PARAM_NAMES[cam.model.name]
        rows = {i: k for k, (c, i) in enumerate(labels) if c == cid}
        sigma = tuple(float(sig[rows[i]]) if i in rows else None for i in range(len(names)))
        pairs = [(names[i], names[j], float(corr[rows[i], rows[j]]))
                 for i in rows for j in rows if i < j and abs(corr[rows[i], rows[j]]) > 0.5]
        out.append(CameraCalibration(
            camera_id=int(cid), model=cam.model.name, width_px=int(cam.width),
            height_px=int(cam.height), names=names,
            before=tuple(float(v) for v in start[cid]),
            after=tuple(float(v) for v in cam.params), sigma=sigma,
            held=tuple((names[i], r) for (c, i), r in sorted(held.items()) if c == cid),
            correlations=tuple(pairs), n_images=int(n_images.get(cid, 0)),
            reprojection_rms_before_px=rms_before.get(cid, float("nan")),
            reprojection_rms_after_px=rms_after.get(cid, float("nan"))))
    return tuple(out)


def _per_camera_rms(rec, obs) -> dict[int, float]:
    res, cams = reprojection(rec, obs)
    return {int(c): _rms(res[cams == c]) for c in np.unique(cams)}


def calibrate(model, reference, *, refine=REFINE_KINDS, T_ref_mov=None, result=None,
              reference_format: str | None = None, tolerance: Tolerance = TOLERANCE,
              max_rounds: int = MAX_ROUNDS, num_threads: int = 0) -> CalibrationResult:
    """Calibrate the cameras of the COLMAP ``model`` against the lidar ``reference``.

    Parameters
    ----------
    model
        A COLMAP model folder (``.bin`` or ``.txt``) in any frame.
    reference
        The lidar: paths as :func:`tiereg.register` takes them.
    refine
        What to refine: a tuple or comma list of ``focal``, ``principal``, ``distortion``,
        ``poses`` (points are always refined).
    T_ref_mov, result
        The model's registration (a :class:`~tiereg.Transform` or 4x4 matrix, or the path of a
        RESULT.json of ``tiereg register``); by default the model is registered first.
    tolerance
        The standard deviations above which an intrinsic is held (:class:`Tolerance`).
    num_threads
        Ceres' threads (0: the cores this process may use).
    """
    t0 = time.perf_counter()
    refine = _parse_refine(refine)
    if T_ref_mov is None and result is not None:
        T_ref_mov, _ = load_transform(result)
    rec = read_model(model)
    start = {cid: np.array(c.params, dtype=np.float64) for cid, c in rec.cameras.items()}
    t_reg = time.perf_counter()
    T, reg_ok, ref, reg_reasons = _registration(Path(model), reference, T_ref_mov,
                                                reference_format)
    t_reg = time.perf_counter() - t_reg
    transform_model(rec, Transform.from_translation(-ref.origin) @ T)
    obs = observations(rec)
    t_lidar = time.perf_counter()
    xyz0 = poses_points(rec, obs)[2]
    lidar = LidarPatches.read(ref, xyz0)
    # reading the lidar: the reference prepared (or registered to) and the points near the ties
    t_lidar = time.perf_counter() - t_lidar + t_reg
    p0 = lidar.at(xyz0)
    check = check_split(xyz0) & p0.ok
    spread0 = spread(p0, check, lidar.floor_m)
    control = select_control(p0, check, spread0)
    res0, _ = reprojection(rec, obs)
    base = dict(T_ref_mov=T, registration_confident=reg_ok, reprojection_rms_before_px=_rms(res0),
                pixel_sigma_px=pixel_sigma(rec, obs), check_before=_stats(p0, check),
                n_check=int(check.sum()), refined=refine,
                inputs={"model": str(model), "reference": str(reference)})
    reasons = [f"registration: {r}" for r in reg_reasons] if not reg_ok else []
    if control.sum() < MIN_CONTROL:
        reasons.append(f"only {int(control.sum())} tie points lie on smooth lidar patches (at "
                       f"least {MIN_CONTROL} needed): nothing to calibrate against")
    rms0 = _per_camera_rms(rec, obs)
    if reasons:
        return _not_run(rec, obs, start, base, reasons, rms0, t0)
    st = Rounds(rec, obs, lidar, check, control, p0, spread0, base["pixel_sigma_px"], start,
                {cid: refine_indices(c.model.name, refine) for cid, c in rec.cameras.items()},
                {int(i): np.array(rec.images[int(i)].projection_center())
                 for i in obs.image_ids}, "poses" in refine, num_threads)
    outcome = run_rounds(st, tolerance=tolerance, max_rounds=max_rounds)
    return _finish(st, outcome, ref, p0, control, base, rms0, t0, t_lidar, max_rounds)


def _not_run(rec, obs, start, base: dict, reasons: list[str], rms0: dict, t0: float):
    """The result of a calibration that could not run: the input intrinsics, not confident."""
    cams = _camera_results(rec, start, np.zeros((0, 0)), [], {}, rms0, rms0,
                           _images_per_camera(obs))
    return CalibrationResult(
        confident=False, reasons=tuple(reasons), cameras=cams,
        reprojection_rms_after_px=base["reprojection_rms_before_px"], check_after=None,
        control_before=None, control_after=None, n_control=0, rounds=0,
        seconds=time.perf_counter() - t0, model=None, **base)


def _images_per_camera(obs) -> dict[int, int]:
    ids, counts = np.unique(obs.camera_of_image, return_counts=True)
    return {int(i): int(n) for i, n in zip(ids, counts)}


def _check_grew(before: HeightStats | None, after: HeightStats | None) -> str | None:
    """Why the check points say the calibration made the heights worse, or ``None``: their
    RMSE and NMAD both grew by more than two standard errors of the RMSE."""
    if before is None or after is None or before.n_used < 2:
        return None
    limit = 1.0 + 2.0 / math.sqrt(2.0 * before.n_used)
    if after.rmse_z > limit * before.rmse_z and after.nmad_dz > limit * before.nmad_dz:
        return (f"the height residuals at the check points grew (RMSE {before.rmse_z:.3f} -> "
                f"{after.rmse_z:.3f}): the lidar and the images disagree")
    return None


def _check_inliers(after: Patches, check: np.ndarray, floor_m: float) -> np.ndarray:
    """The check points whose height residual after calibration lies within
    ``CHECK_OUTLIER_NMADS`` robust standard deviations of the median: the others are features
    the lidar does not have (vehicles, blunders), which no calibration can bring onto it."""
    dz = after.dz_m
    ok = check & np.isfinite(dz)
    if ok.sum() < 5:
        return ok
    scale = max(nmad(dz[ok]), floor_m)
    return ok & (np.abs(dz - np.median(dz[ok])) <= CHECK_OUTLIER_NMADS * scale)


def _finish(st: Rounds, outcome: Outcome, ref, p0: Patches, control0, base: dict, rms0: dict,
            t0: float, t_lidar: float, max_rounds: int) -> CalibrationResult:
    rec = st.rec
    res1, _ = reprojection(rec, st.obs)
    inliers = _check_inliers(st.patches, st.check, st.lidar.floor_m)
    base = {**base, "check_before": _stats(p0, inliers), "n_check": int(inliers.sum()),
            "n_check_outliers": int((st.check & ~inliers).sum())}
    check_after = _stats(st.patches, inliers)
    reasons = [] if outcome.converged else [
        f"the control points did not settle in {max_rounds} rounds"]
    grew = _check_grew(base["check_before"], check_after)
    if grew:
        reasons.append(grew)
    rms1 = _per_camera_rms(rec, st.obs)
    transform_model(rec, Transform.from_translation(ref.origin))
    cams = _camera_results(rec, st.start, outcome.cov, outcome.labels, st.held, rms0, rms1,
                           _images_per_camera(st.obs))
    solver = {"name": "ceres (pycolmap cost functions, pyceres)", "rounds": st.rounds,
              "iterations": st.iterations, "termination": st.termination,
              "solve_seconds": round(st.solve_seconds, 3),
              "lidar_read_seconds": round(t_lidar, 3)}
    residuals = {"xyz": poses_points(rec, st.obs)[2], "point_ids": st.obs.point_ids,
                 "check": inliers, "control": st.control, "control_before": control0,
                 "dz_before": p0.dz_m, "dz_after": st.patches.dz_m}
    warnings = tuple(f"camera {c}: {PARAM_NAMES[rec.cameras[c].model.name][i]}: {r}"
                     for (c, i), r in sorted(outcome.weak.items()))
    return CalibrationResult(
        confident=not reasons, reasons=tuple(reasons), cameras=cams, warnings=warnings,
        reprojection_rms_after_px=_rms(res1), check_after=check_after,
        control_before=_stats(p0, control0), control_after=_stats(st.patches, st.control),
        n_control=int(st.control.sum()), rounds=st.rounds, seconds=time.perf_counter() - t0,
        solver=solver, model=rec, residuals=residuals, **base)
