"""The verdict: is a registration reliable? Decided by what the refined poses explain.

The coarse stage proposes an answer and the distinct poses its searches considered. The answer
and its strongest genuinely different rivals are each refined by the fine stage's first model: a
robust 7-parameter fit of the tie points' heights to the reference surface
(:func:`~tiereg.fine.lsm.vertical_observer`, :func:`~tiereg.fine.solver.solve_helmert`). Then:

1. **Noise.** Each tie point's residual has two sources: the tie points' own noise, and the
   surface's roughness where the point lands (how far the reference rises or falls within a
   cell of it: a roof edge, a tree, a steep slope), which a sub-cell shift or the grid's blur
   turns into metres of height. On the smoothest quarter of the block's ground the second
   vanishes: the tightest refined fit's robust spread there (NMAD of its height residuals), in
   the model's units (divided by the pose's scale), is the tie noise the data allow. A tie point
   is *explained* by a pose when its height lies within ``NOISE_MULTIPLE`` times that noise (at
   the pose's scale: a pose that shrinks the block onto a flat patch shrinks the noise with it)
   plus the surface's roughness under it.
2. **The answer** is the pose that explains the most independent tie points (where only the
   refined fits tell two poses apart, they decide).
3. **Distinctness.** Against each rival, the tie points one pose explains and the other does
   not are counted both ways, ``b`` and ``c``, each tie point as a share of the registration's
   cell it lands in (points crowded into one cell sample one piece of surface); if the two poses
   were equally good each such point would be a fair coin, so ``z = (b - c) / sqrt(b + c)`` is
   a standard normal under that hypothesis (McNemar 1947). The answer must stand out from every
   rival by :data:`MIN_Z`. On flat, featureless ground every pose explains the heights alike and
   ``z`` stays small: the verdict then says so instead of guessing.
4. **Settled.** The answer's refined fit stays near it (within the fine stage's
   :data:`~tiereg.fine.lsm.MAX_MOVE_CELLS`): a fit that runs away says the heights fit best
   elsewhere.
5. **Explained.** On the smooth ground, where roughness excuses nothing, the answer's residual
   spread must be a small part of the spread of the surface heights under the tie points
   (:data:`MAX_SMOOTH_SPREAD`): a pose that explains tie points only as well as any height would
   is no answer, however it compares with its rivals. Nor is one whose smooth-ground spread is
   more than ``NOISE_MULTIPLE`` times the tightest refined fit's: another pose then fits part of
   the tie points far more tightly, and the evidence is divided. Nor, last, is one whose
   smooth-ground spread is more than the tie points' own scatter about the planes through their
   nearest neighbours (:func:`own_scatter`) and the surface's roughness there together allow
   (added in quadrature, :data:`MAX_SPREAD_SCATTER`): that scatter is their noise plus the
   ground's curvature between them, an upper bound on their noise that needs no reference, so
   heights left farther from the surface are not the tie points' noise, whatever the poses'
   spreads say of each other (all of them can be wrong).

6. **Precise.** Once the fine stage has polished the answer, its own uncertainty at the block
   centre (one standard deviation, 3-D) must be at most :data:`MAX_UNCERTAINTY_NOISE` times the
   noise the data allow (in reference units): flat ground leaves the block free to slide, and a
   pose known only to metres is found, not registered to the tie points' precision
   (:func:`imprecision`).

The constants, what they guard and the benchmark figures that set them are listed in
``docs/constants.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from .coarse.refine import height_offset
from .coarse.result import CoarseResult
from .coarse.scoring import MIN_OVERLAP, Hypothesis
from .coarse.search import RIVAL_KAPPA_DEG, RIVAL_SCALE, RIVAL_SHIFT_TIE_CELLS
from .errors import InputError
from .fine.lsm import MAX_MOVE_CELLS, vertical_observer
from .fine.solver import solve_helmert
from .reference import Reference
from .robust import NMAD_FACTOR, nmad
from .surface import SurfaceSampler, fit_planes
from .transform import Transform

RIVALS = 3  # genuinely different poses refined beside the answer
NOISE_MULTIPLE = 3.0  # a tie point within this many noise spreads of the surface is explained
MIN_Z = 4.0  # the answer explains more tie points than any rival, z standard errors apart
SMOOTH_SHARE = 0.25  # the share of a pose's tie points, the least rough, that measure its noise
MAX_SMOOTH_SPREAD = 0.4  # smooth-ground residual spread over the spread of the surface heights
# a refined fit whose last steps wander within this share of a cell has settled: the verdict
# tells poses apart at a cell (the fine stage goes on from its answer), and a parameter whose
# standard deviation moves the block a quarter of a cell is held as not determined. On a
# gridded surface the fit can step back and forth for ever between poses a metre apart (a
# COLMAP model of farmland: 2-cycles of 1.9 m at a 20 m cell, its scale 2 % better than the
# search's), which the solver's cycle test, made for centimetres, does not close
SETTLED_CELLS = 0.25
# the fine answer's 1-sigma uncertainty at the block centre (3-D) over the noise the data allow:
# beyond it the pose is not known to the tie points' precision (a suburban block of 887 tie
# points: 0.48 m against 0.20 m of noise, the answer 0.34 m off with 0.17 m of tie noise)
MAX_UNCERTAINTY_NOISE = 2.0
# the answer's smooth-ground spread over what the tie points' own scatter about their
# neighbours' planes (which bounds their noise from above) and the surface's roughness there
# allow, in quadrature: a pose that leaves more does not explain them (rule 5; the development
# half: right answers at most 0.62 of the scatter alone, a negative accepted at 5.6)
MAX_SPREAD_SCATTER = 1.0
SCATTER_NEIGHBOURS = 10  # the tie points' nearest neighbours whose plane a point is measured from
SCATTER_POINTS = 20_000  # at most this many tie points (evenly chosen) measure the scatter


@dataclass(frozen=True, eq=False)
class RefinedPose:
    """A pose after the refined fit, and what it explains."""

    T_start: Transform  # local reference frame <- centred moving frame
    T: Transform  # after the fit (the start where the fit ran away)
    converged: bool  # the refined fit settled: converged, or wandered within SETTLED_CELLS
    moved_cells: float  # how far the fit moved the block (RMS), in cells
    dz: np.ndarray = field(repr=False)  # surface height - tie point height; NaN off the surface
    surface_z: np.ndarray = field(repr=False)  # the surface's heights under the tie points
    roughness: np.ndarray = field(repr=False)  # the surface's half-range within a cell of each

    @property
    def on_surface(self) -> float:
        """The share of the tie points that land on the reference surface."""
        return float(np.isfinite(self.dz).mean()) if len(self.dz) else 0.0

    @property
    def spread(self) -> float:
        """NMAD of the height residuals on the surface (inf with fewer than 10)."""
        dz = self.dz[np.isfinite(self.dz)]
        return nmad(dz) if len(dz) >= 10 else math.inf

    @property
    def relief(self) -> float:
        """NMAD of the surface heights under the tie points (0 with fewer than 10)."""
        z = self.surface_z[np.isfinite(self.dz)]
        return nmad(z) if len(z) >= 10 else 0.0

    @property
    def unexplained(self) -> float:
        """Residual spread over the relief under the tie points: near 0 when the pose explains
        the heights, about 1.4 when they are unrelated (rough ground leaves more)."""
        return self.spread / self.relief if self.relief > 0 else math.inf

    @cached_property
    def smooth_roughness(self) -> float:
        """The roughness below which lie the :data:`SMOOTH_SHARE` of the tie points on the
        surface where it is least rough (reference units; inf with fewer than 10 of them)."""
        on = np.isfinite(self.dz)
        if on.sum() < 10 / SMOOTH_SHARE:
            return math.inf
        return float(np.quantile(self.roughness[on], SMOOTH_SHARE))

    @cached_property
    def smooth_spread(self) -> float:
        """NMAD of the height residuals of the tie points on the surface where it is smoothest,
        those within :attr:`smooth_roughness` (inf where that cannot be measured)."""
        if not math.isfinite(self.smooth_roughness):
            return math.inf
        return nmad(self.dz[np.isfinite(self.dz) & (self.roughness <= self.smooth_roughness)])

    @property
    def noise(self) -> float:
        """:attr:`smooth_spread` in the model's units (over the pose's scale)."""
        return self.smooth_spread / self.T.scale

    @property
    def smooth_unexplained(self) -> float:
        """:attr:`smooth_spread` over the relief under the tie points."""
        return self.smooth_spread / self.relief if self.relief > 0 else math.inf

    @property
    def explains_heights(self) -> bool:
        """Where the surface is smooth, the pose leaves at most :data:`MAX_SMOOTH_SPREAD` of
        the relief unexplained (False where that cannot be measured)."""
        return self.smooth_unexplained <= MAX_SMOOTH_SPREAD


@dataclass(frozen=True)
class Verdict:
    """Which pose is the answer, whether it is reliable, and the evidence."""

    chosen: int  # index into ``poses``: 0 the coarse answer, then its rivals
    poses: tuple[RefinedPose, ...] = field(repr=False)
    confident: bool
    confidence: float
    reasons: tuple[str, ...]
    noise: float  # the tightest smooth-ground spread, model units: the noise the data allow
    explained: tuple[float, ...]  # independent observations (cells) each pose explains
    z: tuple[float, ...]  # the answer against each pose (nan for itself)
    scatter: float = math.nan  # the tie points' own scatter, model units (:func:`own_scatter`)

    @property
    def best(self) -> RefinedPose:
        return self.poses[self.chosen]

    def to_dict(self) -> dict:
        return {
            "chosen": "coarse answer" if self.chosen == 0 else f"rival {self.chosen}",
            "confident": self.confident, "confidence": round(self.confidence, 4),
            "reasons": list(self.reasons), "noise": self.noise,
            "scatter": None if not math.isfinite(self.scatter) else self.scatter,
            "explained_within": NOISE_MULTIPLE * self.noise,  # model units, plus the roughness
            "poses": [{
                "kappa_deg": math.degrees(p.T.parameters().kappa) % 360.0,
                "scale": p.T.parameters().scale,
                "converged": p.converged, "moved_cells": p.moved_cells,
                "on_surface": p.on_surface, "spread": p.spread, "relief": p.relief,
                "unexplained": p.unexplained, "smooth_spread": p.smooth_spread,
                "roughness": _median(p.roughness[np.isfinite(p.dz)]),
                "explained": n, "z": None if not math.isfinite(z) else z,
            } for p, n, z in zip(self.poses, self.explained, self.z)],
        }


def rival_poses(answer: Transform, hypotheses: tuple[Hypothesis, ...], *, tie_cell: float,
                k: int = RIVALS) -> list[Hypothesis]:
    """The ``k`` best-scored hypotheses genuinely different from the answer and from each
    other: another heading (:data:`~tiereg.coarse.search.RIVAL_KAPPA_DEG`), scale
    (:data:`~tiereg.coarse.search.RIVAL_SCALE`) or place
    (:data:`~tiereg.coarse.search.RIVAL_SHIFT_TIE_CELLS` tie cells)."""
    p = answer.parameters()
    centre = answer.apply(np.zeros((1, 3)))[0]
    mine = Hypothesis(p.kappa, p.scale, float(centre[0]), float(centre[1]), math.inf, 0.0, 1.0, 1)
    out: list[Hypothesis] = []
    for h in sorted(hypotheses, key=lambda h: -h.score):
        if all(h.distinct_from(o, kappa_deg=RIVAL_KAPPA_DEG, log_sigma=math.log(RIVAL_SCALE),
                               shift=RIVAL_SHIFT_TIE_CELLS * tie_cell * min(h.sigma, o.sigma))
               for o in (mine, *out)):
            out.append(h)
            if len(out) == k:
                break
    return out


def refine(moving: np.ndarray, surface: SurfaceSampler, T_start: Transform, *,
           cell: float) -> RefinedPose:
    """The refined fit from ``T_start`` (``moving``: centred model coordinates; ``cell``: the
    registration's cell, reference units): kept where it settled (converged, or ended its
    iterations stepping about within :data:`SETTLED_CELLS` of a cell) within
    :data:`~tiereg.fine.lsm.MAX_MOVE_CELLS` cells and leaves the heights closer to the
    surface (a smaller robust spread), else the start stands."""
    placed = T_start.apply(moving)
    fit = solve_helmert(placed, vertical_observer(surface), hold_displacement=cell / 4)
    moved = float(np.sqrt(np.mean(np.sum((fit.T.apply(placed) - placed) ** 2, axis=1)))) / cell
    settled = fit.converged or fit.wander <= SETTLED_CELLS * cell
    T = fit.T @ T_start if settled and moved <= MAX_MOVE_CELLS else T_start
    pose = _pose_at(T_start, T, moving, surface, settled, moved)
    if T is not T_start:  # a fit that leaves the heights farther from the surface is no fit
        start = _pose_at(T_start, T_start, moving, surface, settled, moved)
        if start.spread < pose.spread:
            return start
    return pose


def _pose_at(T_start: Transform, T: Transform, moving: np.ndarray, surface: SurfaceSampler,
             converged: bool, moved: float) -> RefinedPose:
    q = T.apply(moving)
    z, ok = surface.sample(q[:, 0], q[:, 1])
    return RefinedPose(T_start, T, bool(converged), moved, np.where(ok, z - q[:, 2], np.nan),
                       np.where(ok, z, np.nan), surface.roughness(q[:, 0], q[:, 1]))


def _median(values: np.ndarray) -> float | None:
    return float(np.median(values)) if len(values) else None


def pose_of(h: Hypothesis, moving: np.ndarray, surface: SurfaceSampler) -> Transform:
    """A search hypothesis as a pose, its height offset the median one."""
    placed = h.transform().apply(moving)
    tz = height_offset(placed, surface, np.zeros(2))
    return h.transform(tz=tz if np.isfinite(tz) else 0.0)


def decide(moving: np.ndarray, reference: Reference, starts: list[Transform], *,
           cell: float) -> Verdict:
    """The verdict on ``starts`` (the coarse answer first, then its rivals; local frames,
    ``moving`` centred): module docstring."""
    surface = reference.surface()
    poses = tuple(refine(moving, surface, T, cell=cell) for T in starts)
    scatter = own_scatter(moving)
    eligible = [i for i, p in enumerate(poses) if p.on_surface >= MIN_OVERLAP
                and np.isfinite(p.smooth_spread)]
    if not eligible:
        return Verdict(0, poses, False, 0.0, (
            f"no pose puts {MIN_OVERLAP:.0%} of the tie points on the reference surface",),
            math.nan, (0,) * len(poses), (math.nan,) * len(poses), scatter)
    # the noise in the model's units, at each pose's scale: a pose that shrinks the block onto
    # a flat patch (its heights scaled down with it) explains no more than it should
    noise = max(min(poses[i].noise for i in eligible), 1e-12)
    hits = [np.abs(np.nan_to_num(p.dz, nan=np.inf))
            <= NOISE_MULTIPLE * noise * p.T.scale + p.roughness for p in poses]
    # tie points in one cell sample the same surface: each cell is one observation
    weights = [_independence(p.T.apply(moving), cell) for p in poses]
    counts = tuple(float(np.sum(w[h])) for h, w in zip(hits, weights))
    best = max(eligible, key=lambda i: (counts[i], -poses[i].noise))
    z = tuple(math.nan if j == best else
              _mcnemar(hits[best], hits[j], weights[best], weights[j]) for j in range(len(poses)))
    return verdict_of(poses, best, counts, z, noise, scatter=scatter)


def own_scatter(xyz: np.ndarray, *, k: int = SCATTER_NEIGHBOURS,
                max_points: int = SCATTER_POINTS) -> float:
    """The tie points' scatter about their own surface: the median absolute distance (times
    :data:`~tiereg.robust.NMAD_FACTOR`, a standard deviation for normal noise) of each point
    from the plane (principal axes, any orientation) through its ``k`` nearest neighbours, at
    ``max_points`` evenly chosen points at most (repeated points counted once); NaN with fewer
    than ``k + 1`` distinct points. It is
    their noise (a little more: the plane is fitted to noisy neighbours) plus the ground's
    curvature between neighbours, in the points' own units."""
    if k < 3 or max_points < 1:
        raise InputError(f"own_scatter needs k of at least 3 (a plane) and max_points of at least "
                         f"1, got k={k}, max_points={max_points}")
    xyz = np.unique(np.asarray(xyz, dtype=np.float64), axis=0)  # a copy is no neighbour
    if len(xyz) < k + 1:
        return math.nan
    xyz = xyz - xyz.mean(axis=0)
    at = xyz[::max(1, -(-len(xyz) // max_points))]
    _, idx = cKDTree(xyz).query(at, k=k + 1)
    c, normal, _ = fit_planes(xyz[idx[:, 1:]])  # the point itself (nearest, at 0) left out
    return NMAD_FACTOR * float(np.median(np.abs(np.einsum("ij,ij->i", at - c, normal))))


def _independence(xyz: np.ndarray, cell: float) -> np.ndarray:
    """Per point, one over the number of points sharing its ``cell``-sized square: a pose that
    crowds the block into a few cells has that few independent observations."""
    ij = np.floor(xyz[:, :2] / cell).astype(np.int64)
    _, inverse, n = np.unique(ij, axis=0, return_inverse=True, return_counts=True)
    return 1.0 / n[inverse.ravel()]


def judge_refined(moving: np.ndarray, reference: Reference, coarse: CoarseResult, *,
                  tie_cell: float, cell: float) -> Verdict:
    """:func:`decide` between the coarse stage's answer (``coarse.T_ref_mov``, local frames)
    and its :data:`RIVALS` strongest genuinely different rivals (:func:`rival_poses`)."""
    surface = reference.surface()
    rivals = rival_poses(coarse.T_ref_mov, coarse.hypotheses, tie_cell=tie_cell)
    starts = [coarse.T_ref_mov, *(pose_of(h, moving, surface) for h in rivals)]
    return decide(moving, reference, starts, cell=cell)


def _mcnemar(a: np.ndarray, b: np.ndarray, w_a: np.ndarray, w_b: np.ndarray) -> float:
    """``(n(a, not b) - n(b, not a)) / sqrt(their sum)``, each point counted with its pose's
    independence weight: 0 where the two agree throughout."""
    only_a, only_b = float(np.sum(w_a[a & ~b])), float(np.sum(w_b[b & ~a]))
    return (only_a - only_b) / math.sqrt(only_a + only_b) if only_a + only_b > 0 else 0.0


def verdict_of(poses: tuple[RefinedPose, ...], best: int, counts: tuple[float, ...],
               z: tuple[float, ...], noise: float, *, scatter: float = math.nan) -> Verdict:
    """The verdict on refined ``poses`` with ``best`` the answer: ``counts`` the tie points
    each explains (weighted), ``z`` the answer's McNemar z against each (NaN for itself),
    ``noise`` the tightest smooth-ground spread and ``scatter`` the tie points' own
    (:func:`own_scatter`; NaN: not known), model units (the module docstring's rules)."""
    chosen = poses[best]
    rivals = [v for v in z if not math.isnan(v)]
    z_min = min(rivals) if rivals else math.nan
    reasons = []
    if not rivals:
        reasons.append("no other pose was considered, so none could be ruled out")
    elif z_min < MIN_Z:
        reasons.append(f"another heading, scale or position explains the tie points' heights "
                       f"almost as well (z {z_min:.1f} < {MIN_Z:g})")
    if chosen.moved_cells > MAX_MOVE_CELLS:
        reasons.append(f"the refined fit runs away from the found pose (it would move the block "
                       f"{chosen.moved_cells:.1f} cells, more than {MAX_MOVE_CELLS:g}): the tie "
                       "points' heights fit best elsewhere")
    if not chosen.explains_heights:
        reasons.append(f"the tie points' heights disagree with the reference surface at the "
                       f"found pose, even on smooth ground (residual spread "
                       f"{chosen.smooth_unexplained:.2f} of the surface's own, more than "
                       f"{MAX_SMOOTH_SPREAD:g})")
    elif chosen.noise > NOISE_MULTIPLE * noise:
        reasons.append(f"another pose fits part of the tie points far more tightly (residual "
                       f"spread on smooth ground {chosen.noise / noise:.1f} times the tightest "
                       f"refined fit's, more than {NOISE_MULTIPLE:g}): the evidence is divided")
    allowed = MAX_SPREAD_SCATTER * math.hypot(scatter, chosen.smooth_roughness / chosen.T.scale)
    if chosen.explains_heights and chosen.noise > allowed:  # False where scatter is NaN
        reasons.append(f"the tie points' heights lie farther from the reference surface at the "
                       f"found pose, even on smooth ground (spread {chosen.noise:.3g}, model "
                       f"units), than their own scatter about their neighbours ({scatter:.3g}) "
                       "and the surface's roughness there allow: that is not their noise, the "
                       "pose does not explain them")
    distinct = min(z_min / (2 * MIN_Z), 1.0) if rivals else 0.0
    fit = 1.0 - chosen.smooth_unexplained / (2 * MAX_SMOOTH_SPREAD)
    confidence = float(np.clip(min(distinct, fit), 0.0, 1.0))
    if reasons:
        confidence = min(confidence, 0.49)
    return Verdict(best, poses, not reasons, confidence, tuple(reasons), noise, counts, z,
                   scatter)


def imprecision(verdict: Verdict, sigma_xyz: np.ndarray) -> str | None:
    """Why the fine answer is not known to the tie points' precision, or None: its 1-sigma
    uncertainty at the block centre (``sigma_xyz``, reference units; NaN where a parameter is
    held) is more than :data:`MAX_UNCERTAINTY_NOISE` times the verdict's noise, at the answer's
    scale (module docstring, rule 6)."""
    noise = verdict.noise * verdict.best.T.scale
    sigma = np.asarray(sigma_xyz, dtype=np.float64)
    sigma = sigma[np.isfinite(sigma)]
    if not len(sigma) or not math.isfinite(noise) or noise <= 0.0:
        return None
    uncertainty = float(np.sqrt(np.sum(sigma**2)))
    if uncertainty <= MAX_UNCERTAINTY_NOISE * noise:
        return None
    return (f"the fine answer is uncertain by {uncertainty:.3g} at the block centre (1 sigma), "
            f"more than {MAX_UNCERTAINTY_NOISE:g} times the tie points' noise the data allow "
            f"({noise:.3g}): the block is likely found but not registered to its tie points' "
            "precision (the ground under them holds it weakly); check it, or give more tie "
            "points, a wider block or denser lidar")
