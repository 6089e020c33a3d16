"""Checks of the far-start fine benchmark's helpers (fine_far.py, fine_far_peers.py); not part of
the main suite, about a second.

    .venv/bin/python -m pytest -q benchmarks/test_fine_far.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fine_far import FAR_HEADING_DEG, FAR_SCALE, FAR_SHIFT_M, far_start  # noqa: E402
from fine_far_peers import lidar_dsm, similarity_from_pairs  # noqa: E402

from tiereg.transform import Transform  # noqa: E402


def test_similarity_from_pairs_recovers_a_known_similarity():
    rng = np.random.default_rng(0)
    a = rng.normal(0, 300, (500, 3))
    T = Transform.from_parameters(scale=1.004, omega=0.01, phi=-0.02, kappa=2.0,
                                  translation=(12.0, -7.0, 3.0))
    est = similarity_from_pairs(a, T.apply(a))
    assert np.allclose(est, T.matrix, atol=1e-9)


def test_far_start_is_off_by_the_stated_amounts_about_the_block():
    rng = np.random.default_rng(1)
    moving = rng.normal(0, 1000, (300, 3)) * [1, 1, 0.01] + [1e4, 2e4, 50]
    T_true = Transform.from_parameters(scale=0.3048, kappa=1.0,
                                       translation=(500_000.0, 5_000_000.0, 100.0))
    T_far = far_start(T_true, moving, rng)
    E = T_far @ T_true.inverse  # reference -> reference
    p = E.parameters()
    assert abs(p.scale - 1) == pytest.approx(FAR_SCALE, rel=1e-9)
    assert abs(np.degrees(p.kappa)) == pytest.approx(FAR_HEADING_DEG, rel=1e-9)
    c = T_true.apply(moving).mean(axis=0)
    assert np.linalg.norm(E.apply(c[None])[0] - c) == pytest.approx(FAR_SHIFT_M, rel=1e-6)


def test_lidar_dsm_is_the_mean_of_the_returns_in_each_cell():
    xdem = pytest.importorskip("xdem")
    pts = np.array([[500_000.5, 5_000_003.5, 10.0], [500_001.5, 5_000_002.5, 12.0],
                    [500_002.5, 5_000_000.5, 20.0], [500_003.9, 5_000_000.1, 30.0]])
    dem = lidar_dsm(pts, 32632)
    assert isinstance(dem, xdem.DEM) and dem.res == (2.0, 2.0)
    data = dem.data
    assert data[0, 0] == pytest.approx(11.0)  # the two returns of the upper-left cell
    assert np.ma.is_masked(data[0, 1]) and data[1, 1] == pytest.approx(25.0)
