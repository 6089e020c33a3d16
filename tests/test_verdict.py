"""The verdict's rules on refined poses whose residuals are known."""

from __future__ import annotations

import numpy as np

from tiereg.transform import Transform
from tiereg.verdict import MAX_UNEXPLAINED, NOISE_MULTIPLE, RefinedPose, verdict_of


def _pose(dz_spread_m: float, *, n: int = 800, on: float = 1.0, seed: int = 0) -> RefinedPose:
    """A converged pose over a surface of 30 m relief (NMAD) whose height residuals have the
    given NMAD, ``on`` of its tie points on the surface."""
    rng = np.random.default_rng(seed)
    surface_z = rng.normal(100.0, 30.0, n)
    dz = rng.normal(0.0, dz_spread_m, n)
    off = rng.random(n) > on
    dz[off], surface_z[off] = np.nan, np.nan
    return RefinedPose(Transform.identity(), Transform.identity(), True, 0.1, dz, surface_z)


def test_an_answer_that_explains_its_heights_and_stands_out_is_confident():
    poses = (_pose(1.0), _pose(8.0, seed=1))
    verdict = verdict_of(poses, 0, (700.0, 200.0), (np.nan, 9.0), poses[0].unexplained)
    assert verdict.confident and not verdict.reasons
    assert verdict.confidence > 0.5


def test_an_answer_far_looser_than_another_pose_is_not_confident():
    # the answer explains the most tie points, but a pose on a fifth of the block fits them
    # five times more tightly: the evidence is divided, whatever the counts say
    tight, loose = _pose(1.5, on=0.2, seed=2), _pose(8.0, seed=3)
    assert 0.2 < loose.unexplained < MAX_UNEXPLAINED  # it would pass on its own
    noise = tight.unexplained
    assert loose.unexplained > NOISE_MULTIPLE * noise
    verdict = verdict_of((tight, loose), 1, (100.0, 600.0), (9.0, np.nan), noise)
    assert not verdict.confident and verdict.confidence < 0.5
    assert len(verdict.reasons) == 1 and "far more tightly" in verdict.reasons[0]


def test_an_answer_that_leaves_much_of_the_relief_unexplained_is_not_confident():
    poses = (_pose(12.0), _pose(20.0, seed=1))  # 0.4 of the relief's spread left
    verdict = verdict_of(poses, 0, (500.0, 100.0), (np.nan, 9.0), poses[0].unexplained)
    assert poses[0].unexplained > MAX_UNEXPLAINED and not verdict.confident
    assert any("disagree with the reference surface" in r for r in verdict.reasons)
