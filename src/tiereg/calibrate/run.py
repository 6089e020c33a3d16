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

import copy
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..quality import HeightStats
from ..robust import nmad
from ..transform import Transform
from .adjust import Adjustment, PlaneConstraints, reduced_covariance, refine_indices
from .lidar import LidarPatches, Patches
from .model import model_arrays, pycolmap_module, read_model, transform_model
from .result import PARAM_NAMES, CalibrationResult, CameraCalibration

log = logging.getLogger(__name__)

REFINE_KINDS = ("focal", "principal", "distortion", "poses")
CHECK_EVERY = 5  # one tie point in five on a planar patch is a held-out check point
REJECT_SIGMAS = 3.0
MAX_ROUNDS = 5
SETTLED_CHANGE = 2e-5  # largest relative change of an intrinsic between settled rounds
MIN_CONTROL = 10


@dataclass(frozen=True)
class Tolerance:
    """Standard deviations that decide what the block determines. Above ``hold_*`` an intrinsic
    is not determined (a degenerate geometry): it is held at its input value. Between
    ``flag_*`` and ``hold_*`` it is refined and flagged as weakly determined. Focal length
    relative; principal point in pixels; distortion as the displacement it makes at the image
    corner, in pixels."""

    hold_focal_rel: float = 0.01
    hold_principal_px: float = 5.0
    hold_distortion_px: float = 2.0
    flag_focal_rel: float = 3e-4
    flag_principal_px: float = 0.3
    flag_distortion_px: float = 0.3


TOLERANCE = Tolerance()


def _registration(model: Path, reference, T_ref_mov, reference_format):
    """``(T_ref_mov, confident, Reference, reasons)`` from a registration or as given."""
    from ..io import open_points
    from ..io.base import ArraySource
    from ..points import PointSet
    from ..pipeline import register
    from ..reference import point_spacing, prepare_reference

    if T_ref_mov is None:
        reg = register(str(model), reference, reference_format=reference_format)
        return reg.T_ref_mov, reg.confident, reg.reference, tuple(reg.reasons)
    if not isinstance(T_ref_mov, Transform):
        T_ref_mov = Transform(np.asarray(T_ref_mov, dtype=np.float64))
    if isinstance(reference, np.ndarray):
        reference = PointSet(np.asarray(reference, dtype=np.float64), source="<reference array>")
    src = ArraySource(reference) if isinstance(reference, PointSet) else open_points(
        reference, format=reference_format)
    ref = prepare_reference(src, base_cell=max(4.0 * point_spacing(src), 1e-3))
    return T_ref_mov, True, ref, ()


def _reprojection(rec) -> tuple[np.ndarray, np.ndarray]:
    """Reprojection residuals ``(K, 2)`` (pixels) and the camera id of each observation."""
    a = model_arrays(rec)
    res = np.full((len(a.uv), 2), np.nan)
    cams = a.camera_of_image[a.obs_image]
    for cid in np.unique(cams):
        cam = rec.cameras[int(cid)]
        k = np.flatnonzero(cams == cid)
        pc = np.einsum("kij,kj->ki", a.R_cam_world[a.obs_image[k]],
                       a.xyz[a.obs_point[k]] - a.centres[a.obs_image[k]])
        proj = np.asarray(cam.img_from_cam(pc), dtype=np.float64).reshape(-1, 2)
        res[k] = proj - a.uv[k]
    return res, cams


def _rms(res: np.ndarray) -> float:
    ok = np.isfinite(res).all(axis=1)
    return float(np.sqrt(np.mean(np.sum(res[ok] ** 2, axis=1)))) if ok.any() else float("nan")


def _points(rec) -> tuple[np.ndarray, np.ndarray]:
    ids = np.array(sorted(rec.point3D_ids()), dtype=np.int64)
    return ids, np.array([rec.points3D[int(i)].xyz for i in ids]).reshape(-1, 3)


def _check_split(xyz: np.ndarray) -> np.ndarray:
    """Every ``CHECK_EVERY``-th point in a spatial order (a Hilbert-like interleave of a grid):
    check points spread evenly over the block."""
    lo, hi = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
    cell = np.floor((xyz[:, :2] - lo) / np.maximum(hi - lo, 1e-9) * 64).clip(0, 63).astype(int)
    order = np.lexsort((cell[:, 1] * (1 - 2 * (cell[:, 0] % 2)), cell[:, 0]))
    check = np.zeros(len(xyz), bool)
    check[order[CHECK_EVERY // 2 :: CHECK_EVERY]] = True
    return check


def _spread(patches: Patches, check: np.ndarray) -> float:
    """The robust spread of the lidar residuals of points no plane holds (the check points):
    what the tie points' heights are worth against the lidar now."""
    ok = patches.ok & check
    floor = 3.0 * float(np.median(patches.sigma_m[patches.ok])) if patches.ok.any() else 1e-3
    return max(nmad(patches.distance_m[ok]) if ok.sum() >= 5 else 0.0, floor, 1e-3)


def _control(patches: Patches, check: np.ndarray,
             previous: np.ndarray | None = None) -> np.ndarray:
    """The control points: planar patches (or control points of the ``previous`` round, whose
    patch may have just missed a rule where the point moved), not check points, lidar residual
    within ``REJECT_SIGMAS`` times :func:`_spread` of the median."""
    cand = patches.ok if previous is None else (patches.ok | previous)
    cand = cand & ~check & np.isfinite(patches.distance_m)
    if not cand.any():
        return cand
    d = patches.distance_m[cand]
    keep = np.abs(d - np.median(d)) <= REJECT_SIGMAS * _spread(patches, check)
    out = np.zeros_like(cand)
    out[np.flatnonzero(cand)[keep]] = True
    return out


def _stats(patches: Patches, mask: np.ndarray) -> HeightStats | None:
    if not mask.any():
        return None
    return HeightStats.from_dz(patches.dz_m[mask], int(mask.sum()))


def _sigma_shown(kind: str, sigma: float, value: float, corner: float, power: int,
                 focal: float) -> float:
    """The standard deviation in the units of :class:`Tolerance`."""
    if kind == "focal":
        return sigma / abs(value)
    if kind == "distortion":
        return sigma * focal * corner ** (power + 1)
    return sigma


def _hold_reason(kind: str, s: float, tol: Tolerance, *, flag: bool = False) -> str | None:
    """Why a refined intrinsic with standard deviation ``s`` (units of :class:`Tolerance`)
    must be held (or, with ``flag``, is weakly determined), or ``None``."""
    pre = "flag" if flag else "hold"
    limit = getattr(tol, f"{pre}_{kind}_rel" if kind == "focal" else f"{pre}_{kind}_px")
    if s <= limit:
        return None
    what = {"focal": f"sigma {100 * s:.3f} % > {100 * limit:.3f} %",
            "principal": f"sigma {s:.2f} px > {limit} px",
            "distortion": f"sigma {s:.2f} px at the image corner > {limit} px"}[kind]
    why = {"focal": "the block does not separate the focal length from the flying height "
                    "(level ground seen from above)",
           "principal": "the block does not separate the principal point from the camera "
                        "tilts (parallel strips)",
           "distortion": "too few observations toward the image edges"}[kind]
    return f"{what}: {why}; " + ("weakly determined" if flag else "held at its input value")


def _to_hold(cov: np.ndarray, labels: list[tuple[int, int]], rec, tol: Tolerance, *,
             flag: bool = False) -> dict[tuple[int, int], str]:
    """The refined intrinsics the adjustment does not determine (with ``flag``: determines
    weakly), with the reason."""
    from .model import MODELS

    out = {}
    for k, (cid, i) in enumerate(labels):
        cam = rec.cameras[cid]
        kinds = MODELS[cam.model.name]
        kind = next(n for n, idx in kinds.items() if i in idx)
        focal = float(np.mean([cam.params[j] for j in kinds["focal"]]))
        corner = math.hypot(cam.width / 2, cam.height / 2) / focal
        power = 2 * (kinds["distortion"].index(i) + 1) if kind == "distortion" else 0
        s = _sigma_shown(kind, math.sqrt(max(cov[k, k], 0.0)), float(cam.params[i]), corner,
                         power, focal)
        reason = _hold_reason(kind, s, tol, flag=flag)
        if reason is not None:
            out[(cid, i)] = reason
    return out


def _at_bound(rec, start: dict[int, np.ndarray], refine_idx) -> dict[tuple[int, int], str]:
    """Refined focal lengths that ran to their bound: the block does not determine them."""
    from .adjust import FOCAL_BOUND
    from .model import MODELS

    out = {}
    for cid, cam in rec.cameras.items():
        for i in MODELS[cam.model.name]["focal"]:
            change = abs(cam.params[i] / start[cid][i] - 1)
            if i in refine_idx.get(cid, ()) and change > 0.99 * FOCAL_BOUND:
                out[(cid, i)] = (f"ran to {100 * FOCAL_BOUND:.0f} % off its input value: the "
                                 "block does not separate the focal length from the flying "
                                 "height (level ground seen from above); held at its input "
                                 "value")
    return out


def _planes(patches: Patches, control: np.ndarray, ids: np.ndarray,
            spread: float) -> PlaneConstraints:
    """The control points' planes, with a robust loss as wide as the residuals' spread (in the
    first round that is the model's whole deformation: no point is taken for an outlier)."""
    rows = np.flatnonzero(control)
    sigma = patches.sigma_m[rows]
    return PlaneConstraints(ids[rows], patches.centroid[rows], patches.normal[rows], sigma,
                            max(1.0, spread / float(np.median(sigma))))


def _hold(rec, start: dict[int, np.ndarray], refine_idx: dict[int, tuple[int, ...]],
          new: dict[tuple[int, int], str], held: dict[tuple[int, int], str]) -> None:
    """Put the parameters in ``new`` back to their start value and stop refining them."""
    for (cid, i), reason in new.items():
        log.info("camera %d: holding parameter %d (%s)", cid, i, reason)
        held[(cid, i)] = reason
        refine_idx[cid] = tuple(j for j in refine_idx[cid] if j != i)
        params = np.array(rec.cameras[cid].params)
        params[i] = start[cid][i]
        rec.cameras[cid].params = params


def _parse_refine(refine) -> tuple[str, ...]:
    if isinstance(refine, str):
        refine = tuple(w.strip() for w in refine.split(",") if w.strip())
    bad = [w for w in refine if w not in REFINE_KINDS]
    if bad or not refine:
        raise InputError(f"--refine: unknown {', '.join(bad) or 'empty list'}; give a comma "
                         f"list of {', '.join(REFINE_KINDS)}")
    return tuple(refine)


def load_transform(path: str | os.PathLike[str]) -> Transform:
    """``T_ref_mov`` of a RESULT.json written by ``tiereg register``."""
    import json

    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
        return Transform(np.asarray(data["T_ref_mov"], dtype=np.float64).reshape(4, 4))
    except FileNotFoundError:
        raise InputError(f"{p}: --result: no such file; give the RESULT.json of "
                         "`tiereg register`") from None
    except (OSError, ValueError, KeyError, TypeError):
        raise InputError(f"{p}: --result is not a RESULT.json with a 4x4 T_ref_mov; give the "
                         "file `tiereg register -o` wrote") from None


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


def _per_camera_rms(rec) -> dict[int, float]:
    res, cams = _reprojection(rec)
    return {int(c): _rms(res[cams == c]) for c in np.unique(cams)}


def calibrate(model, reference, *, refine=REFINE_KINDS, T_ref_mov=None, result=None,
              reference_format: str | None = None, tolerance: Tolerance = TOLERANCE,
              max_rounds: int = MAX_ROUNDS) -> CalibrationResult:
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
    """
    t0 = time.perf_counter()
    refine = _parse_refine(refine)
    if T_ref_mov is None and result is not None:
        T_ref_mov = load_transform(result)
    rec = read_model(model)
    start = {cid: np.array(c.params, dtype=np.float64) for cid, c in rec.cameras.items()}
    T, reg_ok, ref, reg_reasons = _registration(Path(model), reference, T_ref_mov,
                                                reference_format)
    transform_model(rec, Transform.from_translation(-ref.origin) @ T)
    rms0 = _per_camera_rms(rec)
    res0, _ = _reprojection(rec)
    sigma_px = max(nmad(res0.ravel()), 0.05)
    ids, xyz0 = _points(rec)
    lidar = LidarPatches.read(ref, xyz0)
    p0 = lidar.at(xyz0)
    check = _check_split(xyz0) & p0.ok
    base = dict(T_ref_mov=T, registration_confident=reg_ok, reprojection_rms_before_px=_rms(res0),
                pixel_sigma_px=sigma_px, check_before=_stats(p0, check),
                n_check=int(check.sum()), refined=refine,
                inputs={"model": str(model), "reference": str(reference)})
    control = _control(p0, check)
    reasons = [f"registration: {r}" for r in reg_reasons] if not reg_ok else []
    if control.sum() < MIN_CONTROL:
        reasons.append(f"only {int(control.sum())} tie points lie on planar, smooth lidar "
                       f"patches (at least {MIN_CONTROL} needed): nothing to calibrate against")
    if reasons:
        return _not_run(rec, start, base, reasons, rms0, t0)
    return _rounds(rec, start, ref, lidar, ids, check, control, p0, base, refine, sigma_px,
                   tolerance, max_rounds, rms0, t0)


def _not_run(rec, start, base: dict, reasons: list[str], rms0: dict, t0: float):
    """The result of a calibration that could not run: the input intrinsics, not confident."""
    cams = _camera_results(rec, start, np.zeros((0, 0)), [], {}, rms0, rms0,
                           _images_per_camera(rec))
    return CalibrationResult(
        confident=False, reasons=tuple(reasons), cameras=cams,
        reprojection_rms_after_px=base["reprojection_rms_before_px"], check_after=None,
        control_before=None, control_after=None, n_control=0, rounds=0,
        seconds=time.perf_counter() - t0, model=None, **base)


def _images_per_camera(rec) -> dict[int, int]:
    out: dict[int, int] = {}
    for iid in rec.reg_image_ids():
        cid = int(rec.images[iid].camera_id)
        out[cid] = out.get(cid, 0) + 1
    return out


@dataclass
class _State:
    """What changes from round to round of the adjustment."""

    control: np.ndarray
    patches: Patches
    spread_m: float
    sigma_px: float
    rounds: int = 0
    iterations: int = 0
    termination: str = ""
    params: np.ndarray | None = None  # the intrinsics after the previous round
    start: dict = None  # the input intrinsics per camera


def _settle(rec, lidar: LidarPatches, ids, check, st: _State, refine_idx, priors, refine_poses,
            max_rounds: int) -> tuple[bool, Adjustment]:
    """Rounds of adjustment and control point selection until the control set and the lidar
    residuals' spread settle: whether they did, and the last adjustment."""
    for _ in range(max_rounds):
        st.rounds += 1
        planes = _planes(st.patches, st.control, ids, st.spread_m)
        adj = Adjustment(rec, st.sigma_px, dict(refine_idx), planes, priors, refine_poses,
                         focal_start={cid: float(v[0]) for cid, v in st.start.items()})
        summary = adj.solve()
        st.iterations += len(summary.ceres_summary.iterations) if hasattr(
            summary.ceres_summary, "iterations") else 0
        st.termination = str(summary.termination_type).rsplit(".", 1)[-1]
        st.patches = lidar.at(_points(rec)[1])
        new = _control(st.patches, check, st.control)
        spread = _spread(st.patches, check)
        changed = int((new != st.control).sum())
        params = np.concatenate([np.asarray(c.params) for _, c in sorted(rec.cameras.items())])
        moved = np.max(np.abs(params - st.params) / np.maximum(np.abs(params), 1e-3)) \
            if st.params is not None else np.inf
        st.params = params
        # settled: the control set hardly changes, or the intrinsics no longer move
        settled = abs(spread - st.spread_m) <= 0.25 * st.spread_m and (
            changed <= 0.02 * new.sum() or moved < SETTLED_CHANGE)
        log.info("round %d: %d control points (%d changed), lidar spread %.3f, %s", st.rounds,
                 int(new.sum()), changed, spread, st.termination)
        st.control, st.spread_m = new, spread
        st.sigma_px = max(nmad(_reprojection(rec)[0].ravel()), 0.05)
        if settled:
            return True, adj
    return False, adj


def _rounds(rec, start, ref, lidar: LidarPatches, ids, check, control, p0: Patches, base: dict,
            refine, sigma_px: float, tol: Tolerance, max_rounds: int, rms0: dict, t0: float):
    """Settle the adjustment; hold what it does not determine and settle again."""
    refine_idx = {cid: refine_indices(c.model.name, refine) for cid, c in rec.cameras.items()}
    priors = {iid: np.array(rec.images[iid].projection_center()) for iid in rec.reg_image_ids()}
    held: dict[tuple[int, int], str] = {}
    st = _State(control, p0, _spread(p0, check), sigma_px, start=start)
    for _ in range(3):
        converged, adj = _settle(rec, lidar, ids, check, st, refine_idx, priors,
                                 "poses" in refine, max_rounds)
        cov, labels = reduced_covariance(adj)
        new = {**_to_hold(cov, labels, rec, tol), **_at_bound(rec, start, refine_idx)}
        if not new:
            break
        _hold(rec, start, refine_idx, new, held)
    weak = _to_hold(cov, labels, rec, tol, flag=True)
    return _finish(rec, start, ref, check, p0, control, st, converged, cov, labels, held, weak,
                   base, rms0, max_rounds, t0)


def _finish(rec, start, ref, check, p0: Patches, control0, st: _State, converged: bool, cov,
            labels, held, weak, base: dict, rms0: dict, max_rounds: int, t0: float):
    res1, _ = _reprojection(rec)
    check_after = _stats(st.patches, check)
    reasons = []
    if not converged:
        reasons.append(f"the control points did not settle in {max_rounds} rounds")
    cb, ca = base["check_before"], check_after
    if cb is not None and ca is not None and ca.rmse_z > 1.05 * cb.rmse_z:
        reasons.append(f"the height residuals at the check points grew ({cb.rmse_z:.3f} -> "
                       f"{ca.rmse_z:.3f}): the lidar and the images disagree")
    transform_model(rec, Transform.from_translation(ref.origin))
    cams = _camera_results(rec, start, cov, labels, held, rms0, _per_camera_rms(rec),
                           _images_per_camera(rec))
    solver = {"name": "ceres (pycolmap cost functions, pyceres)", "rounds": st.rounds,
              "termination": st.termination}
    residuals = {"xyz": _points(rec)[1], "check": check, "control": st.control,
                 "control_before": control0, "dz_before": p0.dz_m, "dz_after": st.patches.dz_m}
    from .result import PARAM_NAMES as names

    warnings = tuple(f"camera {c}: {names[rec.cameras[c].model.name][i]}: {r}"
                     for (c, i), r in sorted(weak.items()))
    return CalibrationResult(
        confident=not reasons, reasons=tuple(reasons), cameras=cams, warnings=warnings,
        reprojection_rms_after_px=_rms(res1), check_after=check_after,
        control_before=_stats(p0, control0), control_after=_stats(st.patches, st.control),
        n_control=int(st.control.sum()), rounds=st.rounds, seconds=time.perf_counter() - t0,
        solver=solver, model=rec, residuals=residuals, **base)
