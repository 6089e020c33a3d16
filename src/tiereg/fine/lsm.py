"""Least-squares surface matching of tie points to the lidar (the fine stage).

Two observation models feed the one solver (:func:`~tiereg.fine.solver.solve_helmert`):

1. **vertical**: the height difference to the gridded lidar surface (bilinear heights and
   gradients of the reference's base grid, :meth:`~tiereg.reference.Reference.surface`;
   Rosenholm & Torlegard 1988), where it is gently sloped.
   It needs no lidar points, only the grid, and it pulls a block a cell or two off back in.
2. **surface**: the normal distance to the lidar's local surface at the nearest first return
   (LS3D, Gruen & Akca 2005), each patch weighted by how rough it is, the crowns' lift taken
   off the tie points on vegetation (:class:`~tiereg.fine.icp.NearestPlanes`). The lidar is read
   once more, and only the points near the tie points are kept.

``lsm`` runs the vertical model, keeps its answer only when it brings the tie points closer to the
lidar's surface (on rough ground, forest or steep relief, a grid cell's mean height is not the
surface a tie point sits on), then solves the surface model from there and settles it pass by pass
(:func:`_settle`), reading the lidar again where the tie points have gone. A final guard refuses a
fine answer that leaves the tie points farther from the surface than the coarse pose did, that
moves the block by more than the coarse stage's uncertainty, or that rests mostly on vegetation
(:func:`_on_canopy`): the coarse answer then stands, and the result says so. Tie points sit on the
visible surface, so both models use first returns; robust weights keep edges and blunders from
pulling the answer, and a tie point beyond the lidar's edge observes nothing
(:data:`NEAR_SPACINGS`). An accepted answer's precision includes how far it depends on the model of
the lidar's surface (:func:`_with_model_error`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..reference import Reference
from ..robust import nmad
from ..surface import SurfaceSampler
from ..transform import Transform
from .icp import NearestPlanes, nearest_plane_observer, plane_observer_icp, point_observer
from .planes import SegmentPlanes
from .solver import PARAMETERS, HelmertFit, Observer, increment, solve_helmert

# The vertical model on gently sloped surfaces only (roofs, ground; cf. Gneeniss et al. 2015): at
# steeper ones (walls, the step at a roof's edge) a tie point's horizontal error biases the height
# difference, and tie points gather at exactly such edges (image corners).
MAX_SLOPE = 1.0  # rise over run: 45 degrees
SURFACE_POINTS = 8  # lidar neighbours of a surface patch (lsm)
# a tie point's surface is the lidar within this many of its mean spacings in plan; one with no
# lidar point that near lies beyond the lidar's edge (or over a gap) and observes nothing
NEAR_SPACINGS = 2.5
# the lidar is read within this many reaches of the tie points, and again around them once one
# has moved out of the region read by more than one reach (a pass moves the block by at most
# about one; from a start 1 degree off a 3 km block's edges are 26 m away): read every other pass
READ_REACHES = 3
MIN_LIDAR = 50  # fewer lidar points near the tie points than this: no surface model
MAX_MOVE_CELLS = 2.0  # a fine answer moving the block farther than this (RMS) is refused
# the fine stage's outer passes (a fresh lidar selection and linearisation each): from a start
# 5 m, 1 degree and 0.5 % off, one pass stopped 0.07-1.55 m short (benchmarks/results/fine-far.md)
MAX_PASSES = 10
SETTLED_SD = 1.0
# more of the tie points near the lidar on vegetation than this: the fine answer is refused (the
# crowns' lift is taken off, so the open ground sets the height; less than half of the block is
# too little to trust, and the lift and the height cannot be told apart)
MAX_CANOPY_SHARE = 0.5
_MODEL = {"lsm": "surface", "planes": "planes"}  # the observation model after the vertical one


@dataclass(frozen=True)
class FineResult:
    """The fine stage's answer: an increment in the local reference frame and its precision."""

    T_increment: Transform  # local reference frame: applies after the coarse pose
    method: str
    model: str  # the observation model of the final solution
    fit: HelmertFit
    n_lidar: int  # lidar points read near the tie points
    seconds: float
    refused: str = ""  # why the fine answer was refused (the coarse pose stands); "" if accepted
    # refused because it would move the block farther than the coarse stage's uncertainty: the
    # two stages contradict each other, so the coarse answer cannot be trusted either
    contradicts_coarse: bool = False
    # the lidar points it read near the tie points (local frame), for the quality statistics;
    # the pipeline drops them once used
    lidar: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def held(self) -> tuple[str, ...]:
        return self.fit.held

    def precision(self, scale: float) -> dict[str, Any]:
        """One standard deviation per parameter (RESULT.json ``precision``); ``None`` if held.

        Angles and the scale are those of the whole transform; the translation's is that of the
        block centroid (the transform's own translation, far from the data, is not meaningful).
        """
        s = self.fit.sigma if not self.refused else np.full(7, np.nan)

        def val(i: int, factor: float = 1.0) -> float | None:
            return None if not np.isfinite(s[i]) else float(s[i] * factor)

        return {
            "scale": val(0, scale),
            "omega_deg": val(1, 180 / math.pi),
            "phi_deg": val(2, 180 / math.pi),
            "kappa_deg": val(3, 180 / math.pi),
            "translation": [val(4), val(5), val(6)],
            "translation_at": "block centroid",
        }

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": "fine",
            "method": self.method,
            "model": self.model,
            "seconds": round(self.seconds, 3),
            "converged": self.fit.converged,
            "iterations": self.fit.iterations,
            "sigma0": self.fit.sigma0,
            "n_observed": self.fit.n_observed,
            "n_used": self.fit.n_used,
            "n_lidar": self.n_lidar,
            "held": list(self.fit.held),
            "refused": self.refused or None,
            "parameters": list(PARAMETERS),
        }


def vertical_observer(sampler: SurfaceSampler) -> Observer:
    """``r = z - Z(x, y)`` and ``g = (-Z_x, -Z_y, 1)`` against a gridded surface, where its slope
    is at most :data:`MAX_SLOPE`."""

    def observe(q: np.ndarray):
        z, ok = sampler.sample(q[:, 0], q[:, 1])
        zx, zy = sampler.gradient(q[:, 0], q[:, 1])
        g = np.column_stack([-zx, -zy, np.ones(len(q))])
        return q[:, 2] - z, g, ok & (np.hypot(zx, zy) <= MAX_SLOPE)

    return observe


def register_fine(
    placed: np.ndarray,
    reference: Reference,
    *,
    cell_size: float,
    method: str = "lsm",
) -> FineResult:
    """Fine registration of tie points ``placed`` by the coarse stage (local reference frame).

    ``cell_size``: the registration's grid cell; parameters that move the block by more than a
    quarter of it (one standard deviation) are not determined and are held. ``method``: ``lsm``
    (vertical, then surface; see the module docstring), ``planes`` (vertical, then planar
    segments: :mod:`tiereg.fine.planes`), ``icp-point`` or ``icp-plane`` (:mod:`tiereg.fine.icp`).
    """
    t0 = time.perf_counter()
    hold = cell_size / 4
    reach = NEAR_SPACINGS * reference.spacing
    radius = max(READ_REACHES * reach, cell_size / 4)
    lidar, solid = _read(reference, placed[:, :2], radius, method=method)
    observe = _surface_observer(method, lidar, placed, reference, solid, lift=False)
    # mostly on trees: no lift (it cannot be told from the height), and refused below
    lift = _canopy_share(placed, lidar, solid, reach=reach, observe=observe) <= MAX_CANOPY_SHARE
    if lift and isinstance(observe, NearestPlanes):
        observe.fix_lift(placed)
    start_spread = _spread(observe, placed)
    model, start, fit = method, Transform.identity(), None
    if method in ("lsm", "planes"):
        sampler = reference.surface()
        vertical = solve_helmert(placed, vertical_observer(sampler), hold_displacement=hold)
        if observe is _no_observations:  # no lidar points near the tie points: the grid alone
            model, fit, observe = "vertical", vertical, vertical_observer(sampler)
            start_spread = _spread(observe, placed)
        elif vertical.converged and _spread(observe, vertical.T.apply(placed)) < start_spread:
            model, start = f"vertical+{_MODEL[method]}", vertical.T
        else:
            model = _MODEL[method]
    if fit is None:
        fit = solve_helmert(start.apply(placed), observe, hold_displacement=hold)
        fit = replace(fit, T=fit.T @ start)
    end_observe = observe
    if method in ("lsm", "planes") and model != "vertical" and fit.n_observed >= 10:
        first = lidar
        fit, lidar, solid = _settle(fit, placed, lidar, solid, reference, method=method,
                                    hold=hold, radius=radius, lift=lift)
        if lidar is not first:  # read again around where the tie points went: judged there
            end_observe = _surface_observer(method, lidar, fit.T.apply(placed), reference,
                                            solid, lift=lift)
    refused, contradicts = _refusal(fit, placed, observe, start_spread,
                                    MAX_MOVE_CELLS * cell_size,
                                    require_convergence=method in ("lsm", "planes"),
                                    end_observe=end_observe)
    if not refused and method in ("lsm", "planes"):
        refused = _on_canopy(fit.T.apply(placed), lidar, solid, reach=reach,
                             observe=end_observe)
    if not refused and method == "lsm" and model != "vertical":
        fit = _with_model_error(fit, fit.T.apply(placed), end_observe, hold=hold)
    return FineResult(fit.T, method, model, fit, len(lidar), time.perf_counter() - t0, refused,
                      contradicts, lidar)


def _read(reference: Reference, xy: np.ndarray, radius: float, *,
          method: str) -> tuple[np.ndarray, np.ndarray | None]:
    """The lidar within ``radius`` of ``xy`` and, for ``lsm`` and ``planes``, which of its
    points lie on a solid surface (:meth:`~tiereg.reference.Reference.solid_near`)."""
    if method in ("lsm", "planes"):
        return reference.solid_near(xy, radius)
    return reference.points_near(xy, radius), None


def _surface_observer(method: str, lidar: np.ndarray, q: np.ndarray, reference: Reference,
                      solid: np.ndarray | None = None, *, lift: bool = True) -> Observer:
    """The observation model of ``method`` on ``lidar`` (the points read around ``q``); with
    ``lift``, ``lsm`` takes the crowns' lift, measured at ``q``, off the tie points on
    vegetation where ``solid`` tells which lidar points lie on a solid surface
    (:class:`~tiereg.fine.icp.NearestPlanes`)."""
    if len(lidar) < MIN_LIDAR:
        return _no_observations
    if method == "icp-point":
        return point_observer(lidar)
    if method == "icp-plane":
        return plane_observer_icp(lidar)
    if method == "planes":
        return SegmentPlanes(lidar, q, spacing=reference.spacing)
    observe = nearest_plane_observer(lidar, neighbours=SURFACE_POINTS, weighted=True,
                                     reach=NEAR_SPACINGS * reference.spacing, solid=solid)
    if lift:
        observe.fix_lift(q)
    return observe


def _settle(fit: HelmertFit, placed: np.ndarray, lidar: np.ndarray, solid: np.ndarray | None,
            reference: Reference, *, method: str, hold: float, radius: float, lift: bool
            ) -> tuple[HelmertFit, np.ndarray, np.ndarray | None]:
    """Again from where the fit ended, until the pose stops moving: each pass re-selects the
    lidar right around the tie points (far from the answer the nearest point in 3-D may lie
    beside a tie point, up a slope or on the next crown; ``planes``: segmented again around
    where the tie points now are) and re-linearises there, continuing the biweight (no new
    Huber phase). The lidar was read within ``radius`` of where the tie points were placed; a
    tie point that has moved farther than ``radius`` less the reach of its neighbourhood would
    see only the part of its surface on the near side, so the lidar is then read again around
    where the tie points are (:data:`READ_REACHES`; without it, a start 5 m, 1 degree and 0.5 %
    off ended twice as far from the truth as a start from the coarse answer).
    Settled when a pass moves the block (RMS) by less than :data:`SETTLED_SD` of the fit's own
    standard deviations of that displacement: a move the data cannot tell from none (a fresh
    selection of neighbours moves a settled fit back and forth by a third of one or more); a
    fit still moving after :data:`MAX_PASSES` passes has not converged, and its precision means
    nothing. A fit whose pass brings the block back (by the same test) to where it was two
    passes before steps between two poses that the fresh selections of the lidar favour in turn
    (each re-measures the crowns' lift): the data cannot choose between them, so the answer is
    the pose halfway and its precision is widened by half the step (:func:`_between`).
    ``lift``: whether the crowns' lift is taken off (:func:`_surface_observer`).
    Returns the fit and the lidar last read, with its solid flags."""
    reach = NEAR_SPACINGS * reference.spacing
    read_at = placed[:, :2]
    poses = [fit.T]
    for _ in range(MAX_PASSES):
        q = fit.T.apply(placed)
        if np.max(np.hypot(*(q[:, :2] - read_at).T)) > radius - reach:
            read_at, radius = q[:, :2], READ_REACHES * reach
            lidar, solid = _read(reference, read_at, radius, method=method)
        close = _within(lidar, q[:, :2], reach)
        if close.sum() < MIN_LIDAR:
            return fit, lidar, solid
        # planes segments the lidar read; lsm's patches see only the lidar within a reach
        near = (_surface_observer(method, lidar, q, reference) if method == "planes"
                else _surface_observer(method, lidar[close], q, reference,
                                       None if solid is None else solid[close], lift=lift))
        again = solve_helmert(q, near, hold_displacement=hold, biweight_from_start=True)
        if again.n_observed < 10:
            return fit, lidar, solid
        moved = float(np.sqrt(np.mean(np.sum((again.T.apply(q) - q) ** 2, axis=1))))
        before, fit = fit, replace(again, T=again.T @ fit.T)
        settled = max(hold / 1000, SETTLED_SD * _displacement_sd(again, q))
        if moved < settled:
            return fit, lidar, solid
        if len(poses) >= 2 and _rms_apart(fit.T, poses[-2], placed) < settled:
            return _between(before, again), lidar, solid
        poses.append(fit.T)
    return replace(fit, converged=False), lidar, solid


def _rms_apart(A: Transform, B: Transform, points: np.ndarray) -> float:
    """The RMS distance between the points placed by ``A`` and by ``B``."""
    return float(np.sqrt(np.mean(np.sum((A.apply(points) - B.apply(points)) ** 2, axis=1))))


def _between(before: HelmertFit, step: HelmertFit) -> HelmertFit:
    """The pose halfway along ``step`` (a settling pass's fit, an increment of the pose of
    ``before``), its standard deviations widened in quadrature by half the step, parameter by
    parameter: the two poses are equally the data's answer (:func:`_settle`)."""
    c = step.centre
    p = step.T.parameters()
    move = np.array([p.scale - 1.0, p.omega, p.phi, p.kappa, *(step.T.apply(c[None])[0] - c)])
    half = increment(move / 2, c)
    return replace(step, T=half @ before.T, sigma=np.hypot(step.sigma, move / 2))


def _with_model_error(fit: HelmertFit, q: np.ndarray, whole: Observer, *,
                      hold: float) -> HelmertFit:
    """The fit with its standard deviations widened by how much its answer ``q`` depends on the
    model of the lidar's surface. The settling passes see the lidar cut to a reach around each
    tie point, so patches at the cut have fewer neighbours; ``whole`` has them complete. Both
    are fair models and the data do not choose between them: one more pass with ``whole`` from
    the answer moves it by as much as they disagree, and that move, parameter by parameter, is
    added to the standard deviation in quadrature. In our simulator's forests it was 0.09-0.10 m
    in height against a formal 0.035-0.043 m (the answer 0.11-0.13 m off), over its buildings
    0.015-0.025 m against 0.011-0.013 m."""
    other = solve_helmert(q, whole, hold_displacement=hold, biweight_from_start=True)
    if other.n_observed < 10:
        return fit
    c = other.centre
    p = other.T.parameters()
    move = np.array([p.scale - 1.0, p.omega, p.phi, p.kappa, *(other.T.apply(c[None])[0] - c)])
    return replace(fit, sigma=np.hypot(fit.sigma, move))


def _canopy_share(q: np.ndarray, lidar: np.ndarray, solid: np.ndarray | None, *,
                  reach: float, observe: Observer | None = None) -> float:
    """The share of the tie points ``q`` with a lidar point within ``reach`` in plan whose
    nearest one (in 3-D) is not on a solid surface (:func:`~tiereg.reference.open_ground_mask`);
    0 without ``solid`` (no classes or returns: open ground) or with fewer than 10 such.
    ``observe``: a :class:`~tiereg.fine.icp.NearestPlanes` over ``lidar`` whose tree finds the
    nearest points (else one is built)."""
    if solid is None or solid.all() or len(q) < 10 or len(lidar) == 0:
        return 0.0
    idx = (observe.nearest(q) if isinstance(observe, NearestPlanes)
           else cKDTree(lidar).query(q)[1])
    near = np.hypot(*(q[:, :2] - lidar[idx, :2]).T) <= reach
    return 1.0 - float(solid[idx[near]].mean()) if near.sum() >= 10 else 0.0


def _on_canopy(q: np.ndarray, lidar: np.ndarray, solid: np.ndarray | None, *,
               reach: float, observe: Observer | None = None) -> str:
    """Why the fine answer's heights cannot be trusted where more than
    :data:`MAX_CANOPY_SHARE` of the tie points ``q`` near the lidar sit on vegetation
    (:func:`_canopy_share`; "" where they do not). The crowns' lift above the lidar is taken off
    (:class:`~tiereg.fine.icp.NearestPlanes`) so that the open ground sets the block's height;
    with most of the block on trees, too little open ground is left, and the lift cannot be told
    from the height."""
    canopy = _canopy_share(q, lidar, solid, reach=reach, observe=observe)
    if canopy <= MAX_CANOPY_SHARE:
        return ""
    return (f"most of the tie points ({canopy:.0%}) sit on vegetation, where the lidar's "
            "first returns fill the crowns' depth and an image sees their tops: too few are "
            "left to settle the block's heights")


def _displacement_sd(fit: HelmertFit, q: np.ndarray) -> float:
    """One standard deviation of the fit's displacement of the block (RMS over its points):
    the translation's and, at the points' mean distance from the centre, the rotations' and
    the scale's; held parameters count nothing."""
    sd = np.nan_to_num(fit.sigma, nan=0.0)
    radius = float(np.sqrt(np.mean(np.sum((q - fit.centre) ** 2, axis=1))))
    return float(np.sqrt(np.sum(sd[4:] ** 2) + np.sum((sd[:4] * radius) ** 2)))


def _within(points: np.ndarray, xy: np.ndarray, radius: float) -> np.ndarray:
    """Which of ``points`` lie within ``radius`` (in plan) of any of ``xy``."""
    dist, _ = cKDTree(xy).query(points[:, :2], distance_upper_bound=radius)
    return np.isfinite(dist)


def _spread(observe: Observer, q: np.ndarray) -> float:
    """The robust spread (NMAD) of the distances of ``q`` to the surface; inf without any."""
    r, _, ok = observe(q)
    r = r[ok & np.isfinite(r)]
    return nmad(r) if len(r) >= 10 else math.inf


def _refusal(fit: HelmertFit, placed: np.ndarray, observe: Observer, start_spread: float,
             max_move: float, *, require_convergence: bool = True,
             end_observe: Observer | None = None) -> tuple[str, bool]:
    """Why the fine answer must not replace the coarse pose ("" when it may), and whether it is
    because the two contradict each other (the fine answer moves the block farther than the
    coarse stage's uncertainty). The classic ICP variants, run for comparison, often end at the
    iteration limit still creeping along a surface; they are judged by where they end, without
    ``require_convergence``."""
    if fit.n_observed < 10:
        return "too few tie points have a lidar surface near them", False
    if require_convergence and not fit.converged:
        return f"it did not converge in {fit.iterations} iterations", False
    moved = float(np.sqrt(np.mean(np.sum((fit.T.apply(placed) - placed) ** 2, axis=1))))
    if not math.isfinite(moved) or moved > max_move:
        return (f"it would move the block by {moved:.3g} (RMS), more than the coarse stage's "
                f"uncertainty ({max_move:.3g})"), True
    end_spread = _spread(end_observe or observe, fit.T.apply(placed))
    if not end_spread <= start_spread * 1.02:
        return (f"it leaves the tie points farther from the lidar surface (spread "
                f"{end_spread:.3g} against {start_spread:.3g} at the coarse pose)"), False
    return "", False


def _no_observations(q: np.ndarray):
    return np.full(len(q), np.nan), np.zeros((len(q), 3)), np.zeros(len(q), bool)
