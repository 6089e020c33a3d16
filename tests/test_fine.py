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


def _flipping(step_m):
    """The smooth surface seen through a piecewise observer: it reads ``step_m`` low while the
    points' mean height is below the surface's and ``step_m`` high otherwise, so that
    Gauss-Newton steps back and forth between two poses ``2 * step_m`` apart for ever."""

    def observe(q):
        r, g, ok = _vertical(q)
        return r + (-step_m if np.mean(r) < 0 else step_m), g, ok

    return observe


def test_a_fit_stepping_between_two_poses_within_its_precision_has_converged():
    p = _points(np.random.default_rng(11), 800)
    q0 = TRUTH.inverse.apply(p) + np.random.default_rng(12).normal(0, [0, 0, 0.3], p.shape)
    clean = solve_helmert(q0, _vertical, hold_displacement=5.0)
    fit = solve_helmert(q0, _flipping(0.01), hold_displacement=5.0)  # 2 cm apart, tol 5 mm
    assert fit.converged and fit.iterations < 40
    # either pose of the cycle: within the cycle's 2 cm of where a smooth observer ends
    assert np.abs(fit.T.apply(q0) - clean.T.apply(q0)).max() < 0.025  # metres
    # the same cycle with steps far beyond the fit's precision (0.17 m at most) is no answer
    wide = solve_helmert(q0, _flipping(0.5), hold_displacement=5.0)
    assert not wide.converged and wide.iterations == 40


@pytest.mark.slow
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
    assert rms(fine) < 0.25  # metres; the lidar is sparse here (0.075 points per m^2)
    data = json.loads(fine.to_json())
    assert data["stages"][-1]["name"] == "fine" and data["stages"][-1]["method"] == "lsm"
    assert all(v is not None for v in data["precision"]["translation"])
    assert data["precision"]["scale"] is not None


@pytest.fixture(scope="module")
def scene_with_shift():
    from scenes import make_scene

    return make_scene(seed=8, T_mov_ref=Transform.from_translation((-500.0, 300.0, 20.0)),
                      lidar_points=300_000)


def test_fine_starts_from_an_initial_pose(tmp_path, scene_with_shift):
    from tiereg import register
    from tiereg.cli import main

    scene = scene_with_shift
    truth = scene.T_ref_mov.apply(scene.tie_mov)
    c = truth.mean(axis=0)  # turn about the block, not about the far-away origin
    off = (Transform.from_translation(c + [1.2, -0.8, 0.4])
           @ Transform.from_parameters(kappa=np.radians(0.05)) @ Transform.from_translation(-c))
    start = off @ scene.T_ref_mov  # about 1.5 m off, as from GNSS/IMU or an earlier run

    def rms(T):
        return float(np.sqrt(np.mean(np.sum((T.apply(scene.tie_mov) - truth) ** 2, axis=1))))

    result = register(scene.tie_mov, scene.lidar, coarse="none", initial=start)
    assert rms(start) > 1.0
    assert rms(result.T_ref_mov) < 0.25  # metres, as from the coarse stage's answer
    assert np.allclose(json.loads(result.to_json())["T_initial"], start.matrix)
    # the command line takes the same start from a matrix file
    np.savetxt(tmp_path / "start.txt", start.matrix)
    np.savetxt(tmp_path / "ties.xyz", scene.tie_mov)
    np.savetxt(tmp_path / "lidar.xyz", scene.lidar)
    code = main(["register", str(tmp_path / "ties.xyz"), str(tmp_path / "lidar.xyz"), "-q",
                 "-o", str(tmp_path / "R.json"), "--coarse", "none",
                 "--initial", str(tmp_path / "start.txt")])
    assert code == 0
    saved = Transform(np.array(json.loads((tmp_path / "R.json").read_text())["T_ref_mov"]))
    assert rms(saved) < 0.25


def test_a_far_start_reads_the_lidar_again_where_the_tie_points_end():
    # a start 3 degrees and 1 % off moves the block's edges 18-25 m, beyond the lidar first read
    # around the tie points (5-8 m here): there they would observe nothing (623 of 1,000 observed
    # when it was read only once), or only the near side of their surface; read again, all do
    from tiereg import register

    def surface(x, y):
        return _surface(x, y) + 2 * np.sin(x / 6) * np.cos(y / 8)

    rng = np.random.default_rng(3)
    g = np.arange(-450.0, 450.0, 1.0)
    gx, gy = (a.ravel() + rng.uniform(-0.3, 0.3, a.size) for a in np.meshgrid(g, g))
    lidar = np.column_stack([gx, gy, surface(gx, gy)])
    xy = rng.uniform(-350, 350, (1000, 2))
    p = np.column_stack([xy, surface(xy[:, 0], xy[:, 1]) + rng.normal(0, 0.1, len(xy))])
    start = (Transform.from_translation((3.0, -4.0, 0.0))
             @ Transform.from_parameters(scale=1.01, kappa=np.radians(3.0)))
    result = register(p, lidar, coarse="none", initial=start)
    assert result.fine is not None and not result.fine.refused
    assert result.fine.fit.n_observed == len(p)
    d = result.T_ref_mov.apply(p) - p
    assert np.sqrt(np.mean(np.sum(d**2, axis=1))) < 0.1  # metres, from 16 m off


@pytest.mark.parametrize("kind", ["point", "plane"])
def test_icp_observers_recover_a_known_similarity(kind):
    from tiereg.fine.icp import plane_observer_icp, point_observer

    # dense lidar on a 0.5 m grid of the smooth surface; tie points on it, moved off by TRUTH
    g = np.arange(-320.0, 320.0, 0.5)
    gx, gy = np.meshgrid(g, g)
    lidar = np.column_stack([gx.ravel(), gy.ravel(), _surface(gx, gy).ravel()])
    p = _points(np.random.default_rng(4), 1500, half=250.0)
    q0 = TRUTH.inverse.apply(p)
    observe = point_observer(lidar) if kind == "point" else plane_observer_icp(lidar)
    fit = solve_helmert(q0, observe, hold_displacement=5.0)
    d = fit.T.apply(q0) - p
    if kind == "plane":
        assert np.sqrt(np.mean(np.sum(d**2, axis=1))) < 0.05  # metres, from 2.6 m off
    else:
        # point-to-point slides along a smooth surface (its nearest points follow the point): it
        # finds the height, 0.7 m off at the start, but hardly the 2.5 m horizontal offset
        assert np.sqrt(np.mean(d[:, 2] ** 2)) < 0.1


def test_a_fit_continued_from_its_answer_stays_there():
    # a second pass from the answer with the biweight from the start: no Huber phase pulls it
    # towards the blunders again, so it stops at once where it was
    rng = np.random.default_rng(14)
    p = _points(rng, 800)
    q0 = TRUTH.inverse.apply(p) + rng.normal(0, [0, 0, 0.3], p.shape)
    q0[:80, 2] += rng.uniform(5, 20, 80)  # 10 % blunders, all above the surface
    fit = solve_helmert(q0, _vertical, hold_displacement=5.0)
    assert fit.converged
    q1 = fit.T.apply(q0)
    again = solve_helmert(q1, _vertical, hold_displacement=5.0, biweight_from_start=True)
    assert again.converged and again.iterations <= 3
    assert np.abs(again.T.apply(q1) - q1).max() < 0.01  # metres


def test_tie_points_beyond_the_lidars_edge_observe_nothing():
    # the lidar covers the west half of the block only (0.5 m grid); the east half's tie points
    # would see planes up to 250 m away, half the observations: more than robust weights trim
    from tiereg.fine.icp import nearest_plane_observer

    g = np.arange(-320.0, 0.0, 0.5)
    gx, gy = np.meshgrid(g, np.arange(-320.0, 320.0, 0.5))
    lidar = np.column_stack([gx.ravel(), gy.ravel(), _surface(gx, gy).ravel()])
    p = _points(np.random.default_rng(13), 1500, half=250.0)
    q0 = TRUTH.inverse.apply(p)
    observe = nearest_plane_observer(lidar, weighted=True, reach=2.5 * 0.5)
    ok = observe(p)[2]
    assert ok[p[:, 0] < -1].all() and not ok[p[:, 0] > 1].any()  # the edge at -0.5 m
    fit = solve_helmert(q0, observe, hold_displacement=5.0)
    assert fit.converged
    west = p[:, 0] < 0
    assert np.sqrt(np.mean(np.sum((fit.T.apply(q0) - p)[west] ** 2, axis=1))) < 0.05  # metres
    unbounded = solve_helmert(q0, nearest_plane_observer(lidar, weighted=True),
                              hold_displacement=5.0)
    assert np.sqrt(np.mean(np.sum((unbounded.T.apply(q0) - p)[west] ** 2, axis=1))) > 0.5


def test_a_fine_answer_that_moves_the_block_too_far_or_fits_worse_is_refused():
    from tiereg.fine.lsm import _refusal

    p = _points(np.random.default_rng(5), 800)
    observe = _vertical
    start_spread = 0.3  # metres: the spread of the distances at the coarse pose
    near = TRUTH.inverse.apply(p)  # about 2.6 m off: the fine stage may move it there
    fit = solve_helmert(near, observe, hold_displacement=5.0)
    assert _refusal(fit, near, observe, start_spread=1.0, max_move=10.0) == ("", False)
    far = p + [0.0, 0.0, 40.0]  # 40 m above: more than the coarse stage's uncertainty
    fit = solve_helmert(far, observe, hold_displacement=5.0)
    why, contradicts = _refusal(fit, far, observe, start_spread=1.0, max_move=10.0)
    assert "move the block" in why and contradicts  # the two stages disagree
    # an answer that leaves the points farther from the surface than they started
    fit = solve_helmert(near, observe, hold_displacement=5.0)
    worse = fit.__class__(**{**fit.__dict__, "T": Transform.from_parameters(
        kappa=np.radians(3.0))})
    why, contradicts = _refusal(worse, p, observe, start_spread, max_move=1e6)
    assert "farther from the lidar surface" in why and not contradicts
    # a fit stopped at its iteration limit is no answer
    stopped = solve_helmert(near, observe, hold_displacement=5.0, max_iterations=2)
    why, contradicts = _refusal(stopped, near, observe, start_spread=1.0, max_move=10.0)
    assert "did not converge" in why and not contradicts


def test_lsm_finds_the_canopy_surface_where_the_grid_mean_is_metres_off():
    # tie points of a forest sit in gaps and on crowns; the 5 m grid's mean height is metres
    # above the gaps, so vertical distances to it are biased. The surface model is not.
    from tiereg import register
    from tiereg.simulate import HiddenTransform, ImageBlock, LidarSurvey, SceneSpec, make_scene

    scene = make_scene(SceneSpec(
        kind="forest", seed=41, world_size_m=1500.0, lidar_size_m=1200.0,
        block=ImageBlock(side_m=1000.0), survey=LidarSurvey(density_per_m2=1.0),
        hidden=HiddenTransform(heading_deg=30.0, scale=1.0), block_heading_deg=0.0))
    truth = scene.T_ref_mov.apply(scene.moving)
    c = truth.mean(axis=0)
    off = (Transform.from_translation(c + [0.6, -0.5, 8.0])
           @ Transform.from_parameters(kappa=np.radians(0.03)) @ Transform.from_translation(-c))
    start = off @ scene.T_ref_mov  # as the coarse stage leaves it in a forest: 8 m too high

    def rms(T):
        return float(np.sqrt(np.mean(np.sum((T.apply(scene.moving) - truth) ** 2, axis=1))))

    result = register(scene.moving, scene.lidar.xyz, coarse="none", initial=start,
                      cell_size=20.0)
    assert result.fine is not None and not result.fine.refused
    assert rms(result.T_ref_mov) < 0.3  # metres (tie noise 0.15 m / 0.3 m, lidar 1 per m^2)


def test_tie_points_on_crowns_do_not_pull_the_fine_heights(tmp_path):
    """A third of a suburb's tie points sit on trees, 0.6 m above the lidar's first returns
    there (an image sees the crowns' tops). The fine stage takes that lift off them: the block
    placed 0.5 m high comes down onto the open ground (the lift left in, by 0.2 m too far)."""
    import laspy
    from scipy.spatial import cKDTree

    from tiereg import register
    from tiereg.simulate import HiddenTransform, ImageBlock, LidarSurvey, SceneSpec, make_scene

    scene = make_scene(SceneSpec(
        kind="suburban", seed=7, world_size_m=1200.0, lidar_size_m=1000.0,
        block=ImageBlock(side_m=700.0), survey=LidarSurvey(density_per_m2=2.0),
        hidden=HiddenTransform(heading_deg=0.0, scale=1.0), block_heading_deg=0.0))
    lidar = scene.lidar
    truth = scene.T_ref_mov.apply(scene.moving)
    first = lidar.return_number == 1
    nearest = cKDTree(lidar.xyz[first]).query(truth)[1]
    on_crown = lidar.classification[first][nearest] == 5
    assert 0.25 < on_crown.mean() < 0.45
    moving = scene.T_ref_mov.inverse.apply(truth + np.outer(np.where(on_crown, 0.6, 0.0),
                                                            [0.0, 0.0, 1.0]))
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.offsets, header.scales = np.floor(lidar.xyz.min(axis=0)), np.full(3, 0.001)
    las = laspy.LasData(header)
    las.x, las.y, las.z = lidar.xyz.T
    las.return_number, las.number_of_returns = lidar.return_number, lidar.number_of_returns
    las.classification = lidar.classification
    las.write(str(tmp_path / "lidar.las"))
    start = Transform.from_translation((0.3, -0.2, 0.5)) @ scene.T_ref_mov
    result = register(moving, tmp_path / "lidar.las", coarse="none", initial=start,
                      cell_size=10.0)
    assert result.fine is not None and not result.fine.refused
    error = result.T_ref_mov.apply(moving) - truth
    assert abs(float(np.median(error[~on_crown, 2]))) < 0.1  # metres (tie noise 0.3 m)
    assert float(np.median(error[on_crown, 2])) == pytest.approx(0.6, abs=0.1)


def test_the_observer_takes_the_crowns_lift_against_the_open_ground_off():
    """Level lidar, its east half on vegetation; tie points 0.5 m above it there and 0.1 m
    above it in the west: the lift is 0.4 m whatever the block's height, and the tie points on
    the crowns observe 0.1 m like the others."""
    from tiereg.fine.icp import NearestPlanes

    x, y = np.meshgrid(np.arange(0.0, 60.0), np.arange(0.0, 60.0))
    lidar = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    solid = lidar[:, 0] < 30
    rng = np.random.default_rng(2)
    x_tie = rng.uniform(2, 28, 200) + np.where(rng.random(200) < 0.5, 0.0, 30.0)
    q = np.column_stack([x_tie, rng.uniform(2, 58, 200), np.zeros(200)])
    q[:, 2] = np.where(q[:, 0] < 30, 0.1, 0.5)
    observe = NearestPlanes(lidar, neighbours=8, reach=2.0, solid=solid)
    for height in (0.0, 3.0):  # metres: the lift does not follow the block's height
        assert observe.fix_lift(q + [0.0, 0.0, height]) == pytest.approx(0.4, abs=1e-9)
    r, _, ok = observe(q)
    assert ok.all()
    assert np.allclose(r, 0.1, atol=1e-9)
    assert np.isnan(NearestPlanes(lidar, neighbours=8, reach=2.0).fix_lift(q))
    # a lift below the open ground (no crown's top is under its first returns), or one within
    # the noise, is not taken off
    below = q.copy()
    below[:, 2] = np.where(q[:, 0] < 30, 0.5, 0.1)
    assert np.isnan(observe.fix_lift(below))
    noisy = q.copy()
    noisy[:, 2] = np.where(q[:, 0] < 30, 0.0, 0.05) + rng.normal(0.0, 0.5, len(q))
    assert np.isnan(observe.fix_lift(noisy))  # 0.05 m against a standard error of 0.09 m


def test_crown_lift_is_the_median_height_over_steady_patches():
    from tiereg.fine.icp import MIN_CROWNS, crown_lift

    rng = np.random.default_rng(3)
    m = 40
    tilt = rng.uniform(0.0, 0.5, m)  # normals within 27 degrees of the vertical
    n = np.column_stack([np.sin(tilt), np.zeros(m), np.cos(tilt)])
    height = rng.normal(0.7, 0.1, m)
    r = height * n[:, 2]  # a point `height` above the patch, along its normal
    crown = np.arange(m) < 30
    assert crown_lift(r, n, crown) == pytest.approx(float(np.median(height[:30])))
    steep = n.copy()
    steep[:15] = [np.sin(1.3), 0.0, np.cos(1.3)]  # 74 degrees: left out of the estimate
    assert crown_lift(r, steep, crown) == pytest.approx(float(np.median(height[15:30])))
    assert np.isnan(crown_lift(r, n, np.arange(m) < MIN_CROWNS - 1))


def _jackknife_by_refitting(A, w, r, label):
    """Slow, obvious reference: solve the weighted least squares again without each group, then
    the delete-a-group jackknife for unequal groups (Busing et al. 1999)."""
    def solve(keep):
        sw = np.sqrt(w[keep])
        return np.linalg.lstsq(A[keep] * sw[:, None], -r[keep] * sw, rcond=None)[0]

    full = solve(np.ones(len(r), bool))
    groups = np.unique(label)
    d = np.array([solve(label != k) for k in groups])
    h = np.array([w.sum() / w[label == k].sum() for k in groups])[:, None]
    pseudo = h * full - (h - 1) * d
    d_J = len(groups) * full - np.sum((1 - 1 / h) * d, axis=0)
    return np.sqrt(np.sum((pseudo - d_J) ** 2 / (h - 1), axis=0) / len(groups)), d


def test_jackknife_matches_refitting_without_each_block():
    from tiereg.fine.solver import jackknife_sd, spatial_blocks

    rng = np.random.default_rng(6)
    xy = rng.uniform(0, 100, (400, 2))
    A = np.column_stack([np.ones(400), xy[:, 0] / 100, xy[:, 1] / 100])
    r = rng.normal(0, 1, 400) + np.where(xy[:, 0] > 60, 0.5, 0.0)  # an error correlated in space
    w = rng.uniform(0.5, 1.0, 400)
    # blocks: a 4 x 4 grid over the points' bounding box
    u = (xy - xy.min(axis=0)) / (xy.max(axis=0) - xy.min(axis=0))
    label = (np.minimum(u[:, 0] * 4 // 1, 3) * 4 + np.minimum(u[:, 1] * 4 // 1, 3)).astype(int)
    assert np.array_equal(spatial_blocks(xy), label)
    expected, _ = _jackknife_by_refitting(A, w, r, label)
    np.testing.assert_allclose(jackknife_sd(A, w, r, label), expected, rtol=1e-9)
    # equal groups: the classic (G - 1) / G sum (d_j - mean)^2
    equal = np.arange(400) % 5
    w1 = np.ones(400)
    _, d = _jackknife_by_refitting(A, w1, r, equal)
    classic = np.sqrt(4 / 5 * np.sum((d - d.mean(axis=0)) ** 2, axis=0))
    np.testing.assert_allclose(jackknife_sd(A, w1, r, equal), classic, rtol=1e-9)


def test_a_small_group_does_not_make_the_jackknife_explode():
    # one group holds 95 % of the points: deleting it leaves a noisy rest, which the unequal-
    # groups estimator weighs by its size; the answer stays near the formal precision
    from tiereg.fine.solver import jackknife_sd

    rng = np.random.default_rng(7)
    A = np.column_stack([np.ones(2000), rng.normal(size=2000)])
    r = rng.normal(0, 1, 2000)
    w = np.ones(2000)
    label = np.where(np.arange(2000) < 1900, 0, 1 + np.arange(2000) % 3)
    formal = np.sqrt(np.diag(np.linalg.inv(A.T @ A)))
    assert np.all(jackknife_sd(A, w, r, label) < 3 * formal)


def test_precision_covers_an_error_that_is_correlated_in_space():
    # one corner of the block (a sixteenth: a forest stand, a construction site) is 1 m higher
    # than the points believe: the height offset is biased by far more than independent noise
    # allows; the formal precision would not say so, the reported one does
    rng = np.random.default_rng(7)
    p = _points(rng, 800)
    q0 = p + rng.normal(0, [0.0, 0.0, 0.3], p.shape)

    def misfit(q):
        r, g, ok = _vertical(q)
        return r - np.where((q[:, 0] > 150) & (q[:, 1] > 150), 1.0, 0.0), g, ok

    clean = solve_helmert(q0, _vertical, hold_displacement=5.0)
    fit = solve_helmert(q0, misfit, hold_displacement=5.0)
    tz = PARAMETERS.index("tz")
    err_z = fit.T.apply(fit.centre[None])[0, 2] - fit.centre[2]  # the truth: no move at all
    assert abs(err_z) > 5 * 0.3 / np.sqrt(len(p))  # metres: not explained by the noise alone
    assert abs(err_z) <= 3 * fit.sigma[tz]
    assert fit.sigma[tz] > 2 * clean.sigma[tz]


def _egg_crate(rng: np.random.Generator, *, noise_m: float = 0.03) -> np.ndarray:
    """Lidar on a 1 m grid of crests, troughs and saddles (3 m high, 24 m apart)."""
    g = np.arange(-150.0, 150.0, 1.0)
    gx, gy = np.meshgrid(g, g)
    z = 3.0 * np.sin(2 * np.pi * gx / 24) * np.sin(2 * np.pi * gy / 24)
    return np.column_stack([gx.ravel(), gy.ravel(), z.ravel()]) + rng.normal(0, noise_m,
                                                                           (g.size**2, 3))


def test_surface_class_tells_creases_from_crests():
    from tiereg.fine.icp import NearestPlanes

    observe = NearestPlanes(_egg_crate(np.random.default_rng(10), noise_m=0.0), neighbours=8)
    # a trough (concave), a crest (convex), a saddle point between them (flat on average)
    q = np.array([[-6.0, 6.0, -3.0], [6.0, 6.0, 3.0], [0.0, 0.0, 0.0]])
    assert list(observe.surface_class(q)) == [0, 2, 1]


def test_precision_covers_a_bias_shared_by_one_kind_of_surface():
    # tie points in the troughs sit 0.3 m below the lidar's surface (as in the creases between
    # crowns): the estimated height is biased, everywhere in the block alike, so spatial blocks
    # cannot see it; the groups by the surface's bend can
    from tiereg.fine.icp import NearestPlanes

    rng = np.random.default_rng(11)
    observe = NearestPlanes(_egg_crate(rng), neighbours=8, weighted=True)
    xy = rng.uniform(-120, 120, (1500, 2))
    q = np.column_stack([xy, 3.0 * np.sin(2 * np.pi * xy[:, 0] / 24)
                         * np.sin(2 * np.pi * xy[:, 1] / 24)])
    trough = observe.surface_class(q) == 0
    q += rng.normal(0, 0.1, q.shape)
    q[trough, 2] -= 0.3
    centre = q.mean(axis=0, keepdims=True)
    for obs, honest in ((observe, True), (lambda p: observe(p), False)):  # with, without classes
        fit = solve_helmert(q, obs, hold_displacement=5.0)
        tz_error = fit.T.apply(centre)[0, 2] - centre[0, 2]  # the truth is the identity
        assert abs(tz_error) > 0.02  # metres: the bias is there
        assert bool(abs(tz_error) <= 3 * fit.sigma[6]) == honest


def test_precision_widens_by_how_far_the_answer_depends_on_the_surface_model():
    from tiereg.fine.lsm import _with_model_error

    rng = np.random.default_rng(15)
    p = _points(rng, 800)
    q0 = p + rng.normal(0, [0.0, 0.0, 0.1], p.shape)
    fit = solve_helmert(q0, _vertical, hold_displacement=5.0)
    q = fit.T.apply(q0)

    def higher(points):  # another fair model of the same surface, 0.1 m higher
        r, g, ok = _vertical(points)
        return r - 0.1, g, ok

    tz = PARAMETERS.index("tz")
    wide = _with_model_error(fit, q, higher, hold=5.0)
    assert wide.sigma[tz] == pytest.approx(np.hypot(fit.sigma[tz], 0.1), rel=0.05)
    assert np.array_equal(wide.T.matrix, fit.T.matrix)  # the answer stays; only its precision
    same = _with_model_error(fit, q, _vertical, hold=5.0)  # the models agree: nothing to add
    assert same.sigma[tz] == pytest.approx(fit.sigma[tz], rel=0.05)


def test_segment_planes_finds_the_roof_and_the_ground_at_its_edge():
    from tiereg.fine.planes import segment_planes

    # lidar 1 m apart: ground sloping 5 % east, a gable roof (30 %) west of x = 0, 6 m up
    g = np.arange(-20.0, 20.0, 1.0) + 0.5
    gx, gy = np.meshgrid(g, g)
    roof = gx < 0
    z = np.where(roof, 6.0 + 0.3 * gy, 0.05 * gx)
    lidar = np.column_stack([gx.ravel(), gy.ravel(), z.ravel()])
    _, normal, rough, _ = segment_planes(lidar, np.array([[0.0, 2.0]]), spacing=1.0)
    expected = {"roof": np.array([0.0, -0.3, 1.0]), "ground": np.array([-0.05, 0.0, 1.0])}
    found = sorted(normal[0].tolist())
    assert len(found) == 2 and np.all(rough[0] < 1e-6)
    for n in expected.values():
        n = n / np.linalg.norm(n)
        assert min(np.linalg.norm(np.array(f) - n) for f in found) < 1e-6


def test_planes_recovers_a_known_similarity_on_a_suburb():
    from tiereg import register
    from tiereg.simulate import HiddenTransform, ImageBlock, LidarSurvey, SceneSpec, make_scene

    scene = make_scene(SceneSpec(
        kind="suburban", seed=43, world_size_m=1500.0, lidar_size_m=1200.0,
        block=ImageBlock(side_m=1000.0), survey=LidarSurvey(density_per_m2=1.0),
        hidden=HiddenTransform(heading_deg=-50.0, scale=2.0), block_heading_deg=20.0))
    truth = scene.T_ref_mov.apply(scene.moving)
    c = truth.mean(axis=0)
    off = (Transform.from_translation(c + [0.8, -0.6, 0.5])
           @ Transform.from_parameters(kappa=np.radians(0.05)) @ Transform.from_translation(-c))
    result = register(scene.moving, scene.lidar.xyz, coarse="none", fine="planes",
                      initial=off @ scene.T_ref_mov, cell_size=20.0)
    assert result.fine is not None and not result.fine.refused
    assert "planes" in result.fine.model
    err = result.T_ref_mov.apply(scene.moving) - truth
    assert np.sqrt(np.mean(np.sum(err**2, axis=1))) < 0.3  # metres, from 1.1 m off


def _plane_observer(*, seen: int | None = None):
    """Vertical distances to the plane z = 0 (a level surface); only the first ``seen`` points
    observe it where given."""
    def observe(q):
        ok = np.ones(len(q), bool)
        if seen is not None:
            ok[seen:] = False
        return q[:, 2].copy(), np.tile([0.0, 0.0, 1.0], (len(q), 1)), ok
    return observe


def test_a_converged_fit_has_settled_and_one_that_broke_off_has_settled_nowhere():
    rng = np.random.default_rng(3)
    q = np.column_stack([rng.uniform(-500, 500, (400, 2)), rng.normal(2.0, 0.05, 400)])
    fit = solve_helmert(q, _plane_observer(), hold_displacement=5.0)
    assert fit.converged
    assert abs(np.median(fit.T.apply(q)[:, 2])) < 0.01  # metres: the block is on the plane
    assert fit.wander < 0.05  # the last iterates lie within a few centimetres of the answer
    broke = solve_helmert(q, _plane_observer(seen=5), hold_displacement=5.0)
    assert not broke.converged and broke.wander == np.inf


def _step_fit(T, centre, n):
    """A settling pass's fit: increment ``T`` with 5 cm standard deviations in the shifts."""
    from tiereg.fine.solver import HelmertFit

    sigma = np.array([0.0, 0.0, 0.0, 0.0, 0.05, 0.05, 0.05])
    return HelmertFit(T, centre, sigma, (), 0.1, n, n, np.ones(n), np.zeros(n), 3, True, 0.0)


@pytest.mark.parametrize("cycle", [True, False])
def test_settling_that_steps_between_two_poses_ends_halfway(monkeypatch, cycle):
    # each pass's fit steps the block 0.3 m, six of its standard deviations: back and forth
    # (a 2-cycle) it has settled between the two poses, which the data favour in turn; the
    # answer is halfway, 0.15 m, known to hypot(0.05, 0.15) m. Stepping always the same way,
    # it never settles
    import types

    from tiereg.fine import lsm

    rng = np.random.default_rng(21)
    placed = _points(rng, 200, half=50.0)
    lidar = _points(rng, 4000, half=60.0)
    centre = placed.mean(axis=0)
    passes = []

    def step(q0, observe, **kw):
        sign = -1.0 if cycle and len(passes) % 2 else 1.0
        passes.append(sign)
        return _step_fit(Transform.from_translation((0.3 * sign, 0.0, 0.0)), centre, len(q0))

    monkeypatch.setattr(lsm, "solve_helmert", step)
    start = _step_fit(Transform.identity(), centre, len(placed))
    reference = types.SimpleNamespace(spacing=1.5)
    fit, _, _ = lsm._settle(start, placed, lidar, None, reference, method="lsm", hold=5.0,
                            radius=1000.0, lift=False)
    tx = PARAMETERS.index("tx")
    if cycle:
        assert fit.converged and len(passes) == 2
        assert fit.T.apply(centre[None])[0] - centre == pytest.approx([0.15, 0.0, 0.0], abs=1e-9)
        assert fit.sigma[tx] == pytest.approx(np.hypot(0.05, 0.15), rel=1e-9)
    else:
        assert not fit.converged and len(passes) == lsm.MAX_PASSES
