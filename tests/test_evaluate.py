"""tiereg.evaluate: the tie points' heights against the lidar at a given pose."""

from __future__ import annotations

import numpy as np
import pytest
from scenes import make_scene

import tiereg
from tiereg import PointSet, Transform
from tiereg.io import as_point_source

NOISE_Z = 0.3  # the scene's tie-point height noise (m)


@pytest.fixture(scope="module")
def scene():
    T_mov_ref = Transform.from_parameters(scale=2.0, kappa=np.radians(30.0),
                                          translation=(-1_000_000.0, 400_000.0, 50.0))
    s = make_scene(seed=3, T_mov_ref=T_mov_ref, lidar_points=150_000, tie_points=1500)
    return s, tiereg.prepare_reference(as_point_source(PointSet(s.lidar), role="reference"))


def test_at_the_true_pose_the_tie_points_sit_on_the_lidar_within_their_noise(scene):
    s, ref = scene
    q = tiereg.evaluate(ref, s.tie_mov, s.T_ref_mov)
    assert q.surface == "lidar points"
    # the whole block lies on the lidar; a point counts where its 8 nearest lidar points lie
    # within 2 spacings, which uniformly random lidar misses about once in ten (Poisson)
    assert q.overlap_fraction > 0.88
    assert abs(q.stats.median_dz) < 0.05  # metres: the bias of the local planes
    assert q.stats.nmad_dz == pytest.approx(NOISE_Z, rel=0.25)
    # the placed points are the true ones (to float64 rounding in projected coordinates)
    assert np.allclose(q.xyz, s.T_ref_mov.apply(s.tie_mov), atol=1e-6)


def test_a_known_height_error_is_measured_and_a_shifted_block_leaves_the_lidar(scene):
    s, ref = scene
    up = Transform.from_translation((0.0, 0.0, 0.5)) @ s.T_ref_mov  # the block 0.5 m too high
    q = tiereg.evaluate(ref, s.tie_mov, up.matrix)  # a plain 4 x 4 matrix is accepted too
    assert q.stats.median_dz == pytest.approx(-0.5, abs=0.05)  # dz = Z_lidar - z
    # 1,000 m east: of the block (x from -450 to 750 m about the lidar's centre, which spans
    # -1,000 to 1,000 m) the part from 550 to 1,000 m stays on the lidar: 450 of 1,200 m
    away = Transform.from_translation((1000.0, 0.0, 0.0)) @ s.T_ref_mov
    q_away = tiereg.evaluate(ref, s.tie_mov, away)
    q = tiereg.evaluate(ref, s.tie_mov, s.T_ref_mov)
    assert q_away.overlap_fraction / q.overlap_fraction == pytest.approx(450 / 1200, abs=0.03)
    assert np.isnan(q_away.dz).sum() == len(q_away.dz) - q_away.stats.n_used
