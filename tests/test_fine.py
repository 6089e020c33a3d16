"""The fine stage: the Helmert solver against known answers, degeneracy, and the pipeline."""

import json

import numpy as np
import pytest

from tiereg.fine.solver import PARAMETERS, design_matrix, increment, solve_helmert
from tiereg.transform import Transform


def _surface(x, y):
    return 8 * np.sin(x / 90) * np.cos(y / 70) + 3 * np.sin((x + y) / 37)


def _gradient(x, y):
    fx = 8 / 90 * np.cos(x / 90) * np.cos(y / 70) + 3 / 37 * np.cos((x + y) / 37)
    fy = -8 / 70 * np.sin(x / 90) * np.sin(y / 70) + 3 / 37 * np.cos((x + y) / 37)
    return fx, fy


def _vertical(q):
    fx, fy = _gradient(q[:, 0], q[:, 1])
    g = np.column_stack([-fx, -fy, np.ones(len(q))])
    return q[:, 2] - _surface(q[:, 0], q[:, 1]), g, np.ones(len(q), bool)


TRUTH = Transform.from_parameters(scale=1.002, omega=np.radians(0.05), phi=np.radians(-0.03),
                                  kappa=np.radians(0.2), translation=(1.5, -2.0, 0.7))


def _points(rng, n=2000, half=300.0):
    xy = rng.uniform(-half, half, (n, 2))
    return np.column_stack([xy, _surface(xy[:, 0], xy[:, 1])])


def test_design_matrix_is_the_derivative_of_the_distances():
    # slow, obvious reference: central differences of r(increment(theta) q) per parameter
    rng = np.random.default_rng(0)
    q = _points(rng, 50) + rng.normal(0, 0.5, (50, 3))
    centre = q.mean(axis=0)
    _, g, _ = _vertical(q)
    A = design_matrix(q, g, centre)
    h = 1e-6
    for j in range(7):
        dt = np.zeros(7)
        dt[j] = h
        plus = _vertical(increment(dt, centre).apply(q))[0]
        minus = _vertical(increment(-dt, centre).apply(q))[0]
        assert np.allclose(A[:, j], (plus - minus) / (2 * h), rtol=1e-4, atol=1e-6), PARAMETERS[j]


def test_recovers_a_known_similarity_exactly_without_noise():
    p = _points(np.random.default_rng(1))
    q0 = TRUTH.inverse.apply(p)  # the points before the fine stage
    fit = solve_helmert(q0, _vertical, hold_displacement=5.0)
    assert fit.converged and not fit.held
    assert np.abs(fit.T.apply(q0) - p).max() < 1e-6  # metres


def test_precision_is_honest_under_noise():
    # 40 noisy repetitions: the true parameters within 3 sigma for (almost) all of them
    rng = np.random.default_rng(2)
    inside = []
    for _ in range(40):
        p = _points(rng, 800)
        q0 = TRUTH.inverse.apply(p) + rng.normal(0, [0.0, 0.0, 0.3], p.shape)
        fit = solve_helmert(q0, _vertical, hold_displacement=5.0)
        centre = fit.centre
        # the error of the block centroid's position, against its standard deviation
        err = fit.T.apply(centre[None])[0] - TRUTH.apply(centre[None])[0]
        inside.append(np.all(np.abs(err) <= 3 * fit.sigma[4:7]))
    assert np.mean(inside) >= 0.9


def test_flat_ground_holds_the_horizontal_parameters():
    rng = np.random.default_rng(3)
    xy = rng.uniform(-300, 300, (1000, 2))
    q0 = np.column_stack([xy, rng.normal(0, 0.05, 1000) + 0.8])  # 0.8 m above a flat plane

    def flat(q):
        g = np.tile([0.0, 0.0, 1.0], (len(q), 1))
        return q[:, 2], g, np.ones(len(q), bool)

    fit = solve_helmert(q0, flat, hold_displacement=2.0)
    assert {"tx", "ty", "kappa"} <= set(fit.held)
    assert abs(np.median(fit.T.apply(q0)[:, 2])) < 0.02  # the height offset is still found
    assert np.isnan(fit.sigma[PARAMETERS.index("tx")])


def test_register_with_fine_reports_precision(tmp_path, scene_with_shift):
    from tiereg import register

    scene = scene_with_shift
    coarse_only = register(scene.tie_mov, scene.lidar, fine="none")
    fine = register(scene.tie_mov, scene.lidar)
    truth = scene.T_ref_mov.apply(scene.tie_mov)

    def rms(result):
        return float(np.sqrt(np.mean(np.sum((result.T_ref_mov.apply(scene.tie_mov) - truth) ** 2,
                                            axis=1))))

    assert fine.confident and fine.fine is not None
    assert rms(fine) < rms(coarse_only)
    assert rms(fine) < 0.25  # metres: a tenth of ... see the fixture's cell
    data = json.loads(fine.to_json())
    assert data["stages"][-1]["name"] == "fine" and data["stages"][-1]["method"] == "lsm"
    assert all(v is not None for v in data["precision"]["translation"])
    assert data["precision"]["scale"] is not None


@pytest.fixture(scope="module")
def scene_with_shift():
    from scenes import make_scene

    return make_scene(seed=8, T_mov_ref=Transform.from_translation((-500.0, 300.0, 20.0)),
                      lidar_points=300_000)
