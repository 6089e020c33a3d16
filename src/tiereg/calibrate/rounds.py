"""Rounds of adjustment and control-point selection, and the intrinsics held between them.

A round solves the self-calibrating bundle adjustment (:class:`~tiereg.calibrate.adjust.
Adjustment`) with the current control points, then fits the lidar patches again where the tie
points now are and selects the control points anew: a tie point whose lidar residual is more
than :data:`REJECT_SIGMAS` expected standard deviations off the median is left out (canopy,
moved objects, blunders). The robust loss of the lidar constraints is as wide as the check
points' spread, so the first round (a bent model: metres) takes no point for an outlier. Rounds
run until the control set and the spread settle (:func:`settle`); then the covariance says which
intrinsics the block does not determine (:mod:`tiereg.calibrate.degenerate`): they are held and
the rounds run again (:func:`run_rounds`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..robust import nmad
from .adjust import FOCAL_BOUND, Adjustment, PlaneConstraints, reduced_covariance
from .degenerate import TOLERANCE, Tolerance, at_bound, hold, to_hold, weakly_determined
from .lidar import LidarPatches, Patches
from .model import Observations, poses_points, reprojection
from .result import PARAM_NAMES

log = logging.getLogger(__name__)

CHECK_EVERY = 4  # one tie point in four on a strict planar patch is a held-out check point
REJECT_SIGMAS = 3.0
MAX_ROUNDS = 5
MAX_HOLDS = 4  # rounds of holding what the block does not determine
SETTLED_CHANGE = 2e-5  # largest relative change of an intrinsic between settled rounds
MIN_PIXEL_SIGMA = 0.05


def check_split(xyz: np.ndarray) -> np.ndarray:
    """Every ``CHECK_EVERY``-th point in a spatial order (a boustrophedon over a 64 x 64 grid):
    check points spread evenly over the block."""
    lo, hi = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
    cell = np.floor((xyz[:, :2] - lo) / np.maximum(hi - lo, 1e-9) * 64).clip(0, 63).astype(int)
    order = np.lexsort((cell[:, 1] * (1 - 2 * (cell[:, 0] % 2)), cell[:, 0]))
    check = np.zeros(len(xyz), bool)
    check[order[CHECK_EVERY // 2 :: CHECK_EVERY]] = True
    return check


def spread(patches: Patches, check: np.ndarray, floor_m: float) -> float:
    """The robust spread of the lidar residuals of points no plane holds (the check points):
    what the tie points' heights are worth against the lidar now."""
    ok = patches.ok & check
    return max(nmad(patches.distance_m[ok]) if ok.sum() >= 5 else 0.0, floor_m, 1e-3)


def select_control(patches: Patches, check: np.ndarray, spread_m: float,
                   previous: np.ndarray | None = None) -> np.ndarray:
    """The control points: usable patches (or control points of the ``previous`` round, whose
    patch may have just missed a rule where the point moved), not check points, lidar residual
    within ``REJECT_SIGMAS`` times the expected spread (``spread_m`` and the patch's own
    ``sigma_m``) of the median."""
    cand = patches.usable if previous is None else (patches.usable | previous)
    cand = cand & ~check & np.isfinite(patches.distance_m)
    if not cand.any():
        return cand
    d, s = patches.distance_m[cand], patches.sigma_m[cand]
    keep = np.abs(d - np.median(d)) <= REJECT_SIGMAS * np.hypot(spread_m, s)
    out = np.zeros_like(cand)
    out[np.flatnonzero(cand)[keep]] = True
    return out


def plane_constraints(patches: Patches, control: np.ndarray, ids: np.ndarray,
                      spread_m: float | None) -> PlaneConstraints:
    """The control points' planes. With ``spread_m`` (the first round: the model's whole
    deformation), a robust loss that wide, so that no point is taken for an outlier; then at
    their own standard deviations (an adjusted tie point's residual is smaller than its plane's
    standard deviation: the images and the plane share it)."""
    rows = np.flatnonzero(control)
    sigma = patches.sigma_m[rows]
    wide = 1.0 if spread_m is None else max(1.0, spread_m / float(np.median(sigma)))
    return PlaneConstraints(ids[rows], patches.centroid[rows], patches.normal[rows], sigma, wide)


def pixel_sigma(rec, obs: Observations) -> float:
    """The image measurements' noise: the NMAD of the reprojection residuals, scaled up for the
    degrees of freedom the adjustment takes from them (3 per point, 6 per image: with 4 rays a
    point the residuals are a fifth smaller than the noise, and so were the standard deviations
    of the intrinsics computed from them)."""
    n_res = 2 * len(obs.uv)
    n_par = 3 * len(obs.point_ids) + 6 * len(obs.image_ids)
    dof = np.sqrt(n_res / max(n_res - n_par, 0.1 * n_res))
    return max(nmad(reprojection(rec, obs)[0].ravel()) * dof, MIN_PIXEL_SIGMA)


@dataclass
class Rounds:
    """The calibration's state from round to round (the model ``rec`` changes in place)."""

    rec: object
    obs: Observations
    lidar: LidarPatches
    check: np.ndarray  # (N,) held-out check points
    control: np.ndarray  # (N,) control points now
    patches: Patches  # the lidar patches where the tie points are now
    spread_m: float
    sigma_px: float
    start: dict[int, np.ndarray]  # the input intrinsics per camera
    refine_idx: dict[int, tuple[int, ...]]  # per camera: the params refined
    priors: dict[int, np.ndarray]  # image id -> registered camera centre
    refine_poses: bool = True
    num_threads: int = 0
    rounds: int = 0
    iterations: int = 0
    solve_seconds: float = 0.0
    termination: str = ""
    params: np.ndarray | None = None  # the intrinsics after the previous round
    held: dict[tuple[int, int], str] = field(default_factory=dict)

    def adjust(self) -> Adjustment:
        """One round: solve, then fit the patches and select the control points again."""
        self.rounds += 1
        planes = plane_constraints(self.patches, self.control, self.obs.point_ids,
                                   self.spread_m if self.rounds == 1 else None)
        adj = Adjustment(self.rec, self.sigma_px, dict(self.refine_idx), planes, self.priors,
                         self.refine_poses, num_threads=self.num_threads,
                         focal_start={c: float(v[0]) for c, v in self.start.items()})
        summary = adj.solve().ceres_summary
        n_it = summary.num_successful_steps + summary.num_unsuccessful_steps
        self.iterations += n_it
        self.solve_seconds += summary.total_time_in_seconds
        self.termination = str(summary.termination_type).rsplit(".", 1)[-1]
        self.patches = self.lidar.at(poses_points(self.rec, self.obs)[2])
        log.info("round %d: %d control points, %s after %d iterations (%.1f s)", self.rounds,
                 int(self.control.sum()), self.termination, n_it, summary.total_time_in_seconds)
        return adj

    def settled(self) -> bool:
        """Select the control points anew; whether the control set settled (or the intrinsics
        no longer move) after the first round's wide loss."""
        new_spread = spread(self.patches, self.check, self.lidar.floor_m)
        new = select_control(self.patches, self.check, new_spread, self.control)
        changed = int((new != self.control).sum())
        params = np.concatenate([np.asarray(c.params)
                                 for _, c in sorted(self.rec.cameras.items())])
        moved = np.inf if self.params is None else float(
            np.max(np.abs(params - self.params) / np.maximum(np.abs(params), 1e-3)))
        out = self.rounds > 1 and (changed <= 0.02 * new.sum() or moved < SETTLED_CHANGE)
        log.info("  %d control points (%d changed), lidar spread %.3f -> %.3f", int(new.sum()),
                 changed, self.spread_m, new_spread)
        self.params, self.control, self.spread_m = params, new, new_spread
        self.sigma_px = pixel_sigma(self.rec, self.obs)
        return out


def settle(st: Rounds, max_rounds: int) -> tuple[bool, Adjustment]:
    """Rounds until the control set and the lidar residuals' spread settle: whether they did,
    and the last adjustment."""
    for _ in range(max_rounds):
        adj = st.adjust()
        if st.settled():
            return True, adj
    return False, adj


@dataclass(frozen=True, eq=False)
class Outcome:
    """What the rounds found: whether they settled, the covariance of the refined intrinsics
    (``labels``: camera id and parameter index of each row), the weakly determined ones."""

    converged: bool
    cov: np.ndarray = field(repr=False)
    labels: list
    weak: dict


def run_rounds(st: Rounds, *, tolerance: Tolerance = TOLERANCE,
               max_rounds: int = MAX_ROUNDS) -> Outcome:
    """Settle the adjustment; hold what it does not determine and settle again."""
    for attempt in range(MAX_HOLDS):
        converged, adj = settle(st, max_rounds)
        cov, labels = reduced_covariance(adj)
        new = {**to_hold(cov, labels, st.rec, tolerance),
               **at_bound(st.rec, st.start, st.refine_idx, FOCAL_BOUND)}
        if not new or attempt == MAX_HOLDS - 1:
            break  # (the last time round, what is still undetermined is flagged below)
        hold(st.rec, st.start, st.refine_idx, new, st.held)
    weak = weakly_determined(cov, labels, st.rec, PARAM_NAMES, tolerance)
    return Outcome(converged, cov, labels, weak)
