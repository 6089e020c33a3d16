"""The verdict's rules on refined poses whose residuals are known."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scenes import make_scene

import tiereg
import tiereg.verdict as verdict_module
from tiereg import PointSet
from tiereg.io import as_point_source
from tiereg.transform import Transform
from tiereg.verdict import (
    MAX_SMOOTH_SPREAD,
    NOISE_MULTIPLE,
    SETTLED_CELLS,
    RefinedPose,
    own_scatter,
    refine,
    verdict_of,
)

RELIEF_M = 30.0  # the NMAD of the surface heights under every test pose


def _pose(dz_spread_m: float, *, n: int = 800, on: float = 1.0, seed: int = 0,
          rough_share: float = 0.0, rough_spread_m: float = 0.0) -> RefinedPose:
    """A converged pose over a surface of 30 m relief (NMAD) whose height residuals have the
    given NMAD where the surface is smooth (roughness 0.1 m), ``on`` of its tie points on the
    surface; ``rough_share`` of them land where the surface is rough (10 m within a cell: roof
    edges, trees) and leave residuals of ``rough_spread_m`` there."""
    rng = np.random.default_rng(seed)
    surface_z = rng.normal(100.0, RELIEF_M, n)
    dz = rng.normal(0.0, dz_spread_m, n)
    roughness = np.full(n, 0.1)
    rough = rng.random(n) < rough_share
    dz[rough] = rng.normal(0.0, rough_spread_m, rough.sum())
    roughness[rough] = 10.0
    off = rng.random(n) > on
    dz[off], surface_z[off] = np.nan, np.nan
    return RefinedPose(Transform.identity(), Transform.identity(), True, 0.1, dz, surface_z,
                       roughness)


def _tightest(*poses: RefinedPose) -> float:
    return min(p.noise for p in poses)


def test_an_answer_that_explains_its_heights_and_stands_out_is_confident():
    poses = (_pose(1.0), _pose(8.0, seed=1))
    verdict = verdict_of(poses, 0, (700.0, 200.0), (np.nan, 9.0), _tightest(*poses))
    assert verdict.confident and not verdict.reasons
    assert verdict.confidence > 0.5


def test_residuals_where_the_surface_is_rough_do_not_count_against_an_answer():
    # three quarters of the tie points at edges and in trees, residuals of 12 m there: the
    # residual spread over the relief is far above what smooth ground would leave, yet on the
    # smooth quarter the tie points sit within their noise of the surface
    answer = _pose(0.5, rough_share=0.75, rough_spread_m=12.0, seed=4)
    assert answer.unexplained > 0.25  # the whole block's spread is a large part of the relief
    assert answer.smooth_unexplained < 0.05
    poses = (answer, _pose(20.0, seed=5))
    verdict = verdict_of(poses, 0, (600.0, 150.0), (np.nan, 8.0), _tightest(*poses))
    assert verdict.confident, verdict.reasons


def test_an_answer_far_looser_than_another_pose_is_not_confident():
    # the answer explains the most tie points, but a pose on a fifth of the block fits them
    # five times more tightly on smooth ground: the evidence is divided, whatever the counts say
    tight, loose = _pose(1.5, on=0.2, seed=2), _pose(8.0, seed=3)
    assert 0.2 < loose.smooth_unexplained < MAX_SMOOTH_SPREAD  # it would pass on its own
    noise = _tightest(tight, loose)
    assert loose.noise > NOISE_MULTIPLE * noise
    verdict = verdict_of((tight, loose), 1, (100.0, 600.0), (9.0, np.nan), noise)
    assert not verdict.confident and verdict.confidence < 0.5
    assert len(verdict.reasons) == 1 and "far more tightly" in verdict.reasons[0]


def test_an_answer_that_leaves_the_smooth_grounds_heights_unexplained_is_not_confident():
    poses = (_pose(18.0), _pose(30.0, seed=1))  # 0.6 of the relief's spread left
    verdict = verdict_of(poses, 0, (500.0, 100.0), (np.nan, 9.0), _tightest(*poses))
    assert poses[0].smooth_unexplained > MAX_SMOOTH_SPREAD and not verdict.confident
    assert any("disagree with the reference surface" in r for r in verdict.reasons)


def test_an_answer_whose_heights_lie_farther_than_the_tie_points_own_scatter_is_not_confident():
    # every pose may be wrong: the tightest refined fit's spread then says nothing of the tie
    # points' noise, their own scatter about their neighbours does (a negative in the mountains,
    # matched elsewhere at 5.6 times that scatter, was confident so)
    poses = (_pose(1.0), _pose(8.0, seed=1))
    args = (poses, 0, (700.0, 200.0), (np.nan, 9.0), _tightest(*poses))
    assert verdict_of(*args, scatter=2.0).confident
    refused = verdict_of(*args, scatter=0.5)  # roughness 0.1 there: 0.51 allowed, 1.0 left
    assert not refused.confident and refused.confidence < 0.5
    assert len(refused.reasons) == 1 and "own scatter" in refused.reasons[0]
    assert refused.to_dict()["scatter"] == 0.5
    assert verdict_of(*args).confident and verdict_of(*args).to_dict()["scatter"] is None


def test_the_surfaces_roughness_on_smooth_ground_is_allowed_beside_the_tie_points_scatter():
    # precise tie points (0.5) over a surface 1.5 rough even where it is smoothest (lidar noise,
    # grass): a spread of 1.0 there is the surface's, not a wrong pose's
    poses = (_pose(1.0), _pose(8.0, seed=1))
    rough = replace(poses[0], roughness=np.full(len(poses[0].dz), 1.5))
    verdict = verdict_of((rough, poses[1]), 0, (700.0, 200.0), (np.nan, 9.0),
                         _tightest(rough, poses[1]), scatter=0.5)
    assert verdict.confident, verdict.reasons


def _slow_scatter(xyz: np.ndarray, k: int) -> float:
    """Per point: the plane through its k nearest neighbours by SVD, its distance."""
    xyz = xyz - xyz.mean(axis=0)
    r = []
    for p in xyz:
        nb = xyz[np.argsort(np.linalg.norm(xyz - p, axis=1), kind="stable")[1:k + 1]]
        c = nb.mean(axis=0)
        normal = np.linalg.svd(nb - c)[2][-1]
        r.append(abs(float((p - c) @ normal)))
    return 1.4826 * float(np.median(r))


def test_own_scatter_is_the_tie_noise_in_any_orientation_and_matches_a_slow_reference():
    rng = np.random.default_rng(7)
    xy = rng.uniform(0.0, 1000.0, (600, 2))  # about 40 m apart
    ground = 0.02 * xy[:, 0] + 5.0 * np.sin(xy[:, 1] / 200.0)  # a few cm of curvature between
    noise_m = 0.3
    xyz = np.column_stack([xy, ground + rng.normal(0.0, noise_m, len(xy))])
    a, b = np.radians(70.0), np.radians(130.0)  # turned over and about: any orientation
    R = (np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
         @ np.array([[np.cos(b), -np.sin(b), 0], [np.sin(b), np.cos(b), 0], [0, 0, 1]]))
    turned = xyz @ R.T + [4e6, 5e5, 300.0]
    assert own_scatter(turned, k=10) == pytest.approx(_slow_scatter(xyz, 10), rel=1e-6)
    # the noise, a little more (the planes are fitted to noisy neighbours): 1.0-1.26 times it
    # over seeds 0-7, the median of 600 distances known to about 5 %
    assert 0.9 * noise_m <= own_scatter(turned) <= 1.35 * noise_m
    assert own_scatter(turned, max_points=200) == pytest.approx(own_scatter(turned), rel=0.3)
    # a point given twice is one point: its copy is no neighbour that pulls the plane onto it
    assert own_scatter(np.vstack([turned, turned])) == own_scatter(turned)
    assert np.isnan(own_scatter(turned[:10]))


def test_too_few_tie_points_on_the_surface_measure_no_noise():
    pose = _pose(1.0, n=30)
    assert pose.smooth_spread == np.inf
    verdict = verdict_of((pose, _pose(8.0, seed=1)), 0, (30.0, 5.0), (np.nan, 9.0), 1.0)
    assert not verdict.confident


# --------------------------------------------------------------- the refined fit of one pose
CELL_M = 20.0  # the registration's cell of the refine tests


@pytest.fixture(scope="module")
def placed_scene():
    """Tie points and the lidar's surface of a scene in the reference's local frame: the
    tie points centred, with the pose that puts them on the surface."""
    s = make_scene(seed=5, lidar_points=150_000, tie_points=1500)
    ref = tiereg.prepare_reference(as_point_source(PointSet(s.lidar), role="reference"))
    local = s.T_ref_mov.apply(s.tie_mov) - ref.origin
    centre = local.mean(axis=0)
    return local - centre, Transform.from_translation(centre), ref.surface()


def _ends_at_the_limit(monkeypatch, wander_m: float) -> None:
    """The refined fit ends at its iteration limit, its last steps ``wander_m`` apart."""
    real = verdict_module.solve_helmert

    def stepping(*args, **kwargs):
        return replace(real(*args, **kwargs), converged=False, wander=wander_m)

    monkeypatch.setattr(verdict_module, "solve_helmert", stepping)


def test_a_fit_stepping_about_within_a_quarter_cell_at_its_limit_is_kept(placed_scene,
                                                                          monkeypatch):
    # a start a cell and a half off and 2 % too large: the fit brings it back; that it ends at
    # its iteration limit stepping back and forth by a fifth of a cell does not undo that
    moving, T_true, surface = placed_scene
    T_start = (Transform.from_translation((24.0, -18.0, 3.0)) @ T_true
               @ Transform.from_parameters(scale=1.02))
    _ends_at_the_limit(monkeypatch, wander_m=0.2 * CELL_M)
    pose = refine(moving, surface, T_start, cell=CELL_M)
    assert pose.converged
    error = np.sqrt(np.mean(np.sum((pose.T.apply(moving) - T_true.apply(moving)) ** 2, axis=1)))
    assert error < 0.5  # metres, at the tie points (the start: 30 m)
    assert pose.T.scale == pytest.approx(1.0, abs=0.002)


def test_a_fit_still_wandering_by_more_than_a_quarter_cell_leaves_the_start(placed_scene,
                                                                             monkeypatch):
    moving, T_true, surface = placed_scene
    T_start = Transform.from_translation((24.0, -18.0, 3.0)) @ T_true
    _ends_at_the_limit(monkeypatch, wander_m=SETTLED_CELLS * CELL_M * 1.2)
    pose = refine(moving, surface, T_start, cell=CELL_M)
    assert not pose.converged
    assert np.allclose(pose.T.matrix, T_start.matrix)
