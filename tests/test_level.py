"""Models in any orientation: the vertical from cameras or points, then the level problem."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tiereg import register
from tiereg.level import levelling, vertical_from_cameras, vertical_from_points
from tiereg.simulate import (
    HiddenTransform,
    ImageBlock,
    LidarSurvey,
    SceneSpec,
    make_scene,
    oriented_model,
)


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def test_levelling_turns_up_onto_z_about_the_centre():
    rng = np.random.default_rng(0)
    for _ in range(20):
        up, c = _unit(rng.normal(size=3)), rng.normal(0, 1e5, 3)
        T = levelling(up, c)
        R = T.matrix[:3, :3]
        np.testing.assert_allclose(R @ up, [0, 0, 1], atol=1e-12)
        np.testing.assert_allclose(T.apply(c[None])[0], c, atol=1e-6)
        assert np.isclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(levelling([0, 0, -1], np.zeros(3)).matrix[:3, :3] @ [0, 0, -1],
                               [0, 0, 1])


def test_vertical_from_points_and_cameras():
    rng = np.random.default_rng(1)
    # a rolling block 2 km wide, 30 m of relief, tilted so that its up is n
    xy = rng.uniform(-1000, 1000, (3000, 2))
    z = 15 * np.sin(xy[:, 0] / 300) + rng.normal(0, 0.3, 3000)
    n = _unit([0.5, -0.3, 0.8])
    R = levelling(n, np.zeros(3)).matrix[:3, :3].T  # +z -> n
    pts = np.column_stack([xy, z]) @ R.T
    v = vertical_from_points(pts)
    assert not v.sign_known and not v.ambiguous
    # the dominant plane is the terrain's mean plane: this one leans by about a degree
    assert np.degrees(np.arccos(abs(np.dot(v.up, n)))) < 2.0
    # nadir cameras 800 m above, looking along -n
    centres = (np.column_stack([rng.uniform(-1000, 1000, (40, 2)), np.full(40, 800.0)]) @ R.T)
    dirs = np.tile(-n, (40, 1)) + rng.normal(0, 0.01, (40, 3))
    vc = vertical_from_cameras(centres, dirs / np.linalg.norm(dirs, axis=1)[:, None], pts)
    assert vc is not None and vc.sign_known
    assert np.degrees(np.arccos(np.dot(vc.up, n))) < 1.0
    # a ball of points has no dominant plane
    assert vertical_from_points(rng.normal(size=(2000, 3))).ambiguous


@pytest.fixture(scope="module")
def suburb():
    spec = SceneSpec(kind="suburban", seed=7, world_size_m=2500.0, lidar_size_m=2000.0,
                     block=ImageBlock(side_m=1400.0), survey=LidarSurvey(density_per_m2=1.0),
                     hidden=HiddenTransform(heading_deg=0.0, scale=2.0), block_heading_deg=20.0)
    return make_scene(spec)


def _rms(T_est, T_true, xyz):
    d = T_est.apply(xyz) - T_true.apply(xyz)
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))


@pytest.mark.slow
@pytest.mark.parametrize("cameras", [True, False])
def test_model_in_any_orientation_registers(suburb, tmp_path, cameras):
    model = oriented_model(suburb, (55.0, -30.0, 140.0))
    folder = model.write_colmap(tmp_path / "sparse", cameras=cameras)
    result = register(folder, suburb.lidar.xyz)
    assert result.confident
    assert result.levelling.source == ("cameras" if cameras else "points")
    assert _rms(result.T_ref_mov, model.T_ref_mov, model.xyz) < 0.5  # metres, after fine
    data = json.loads(result.to_json())
    assert data["levelling"]["tilt_deg"] > 40
    # cameras know up from down; points try up, then down, and the model as it is, far from
    # level, only as a last resort: the first confident orientation ends the search
    chosen = data["levelling"]["chosen"]
    assert data["levelling"]["tried"] == (1 if cameras else 1 + ["up", "down"].index(chosen))
    assert data["T_initial"] is None


@pytest.mark.slow
def test_level_data_are_registered_as_they_are(suburb):
    # aerial-triangulation tie points are level already: the points as they are come first and,
    # registered confidently, are the only orientation tried (the points turned over, for a
    # model upside down and level, only when they are not)
    result = register(suburb.moving, suburb.lidar.xyz, fine="none")
    assert result.confident
    assert result.levelling.chosen == "as is" and result.levelling.tried == 1
    assert result.levelling.confident_answers == 1
    assert _rms(result.T_ref_mov, suburb.T_ref_mov, suburb.moving) < 10.0  # metres, coarse only


@pytest.mark.slow
@pytest.mark.parametrize("cameras", [True, False])
def test_a_model_upside_down_and_level_is_turned_over(suburb, tmp_path, cameras):
    # COLMAP's frame follows a camera's axes: a nadir block comes out upside down, within a few
    # degrees of level. The cameras' viewing direction says so; without them the reference does
    model = oriented_model(suburb, (177.0, 2.0, 30.0))
    folder = model.write_colmap(tmp_path / "sparse", cameras=cameras)
    result = register(folder, suburb.lidar.xyz, fine="none")
    assert result.confident, result.reasons
    assert result.levelling.source == ("cameras" if cameras else "points")
    assert result.levelling.chosen == ("up" if cameras else "down")
    assert _rms(result.T_ref_mov, model.T_ref_mov, model.xyz) < 10.0  # metres, coarse only


@pytest.mark.slow
def test_level_mountain_blocks_stay_level():
    # a small block on steep ground: its dominant plane leans by 61 degrees though the tie points
    # are level; the model as it is must still be tried, and win (levelled by that plane, the
    # model is 61 degrees off: 594 m off, not confident, when only the two senses were tried).
    # Nor is that plane dominant (the block is about as thick as it is wide), so the points as
    # they are come first and, registered confidently, are the only orientation tried (up,
    # down, then as they are before)
    from tiereg.level import vertical_from_points

    spec = SceneSpec(kind="mountains", seed=61, world_size_m=3000.0, lidar_size_m=2000.0,
                     block=ImageBlock(side_m=800.0, tie_points_per_km2=1000.0),
                     survey=LidarSurvey(density_per_m2=0.5),
                     hidden=HiddenTransform(heading_deg=75.0, scale=1.5), block_heading_deg=0.0)
    scene = make_scene(spec)
    vertical = vertical_from_points(scene.tie_points.xyz)
    assert vertical.tilt_deg > 45 and vertical.ambiguous  # the premises
    result = register(scene.moving, scene.lidar.xyz, fine="none")
    assert result.confident and result.levelling.tried == 1
    assert result.levelling.chosen == "as is"
    assert _rms(result.T_ref_mov, scene.T_ref_mov, scene.moving) < 5.0  # metres, coarse only


def test_points_are_tried_as_they_are_whatever_their_plane_leans():
    from tiereg.level import Vertical, starting_poses

    centre = np.array([10.0, -5.0, 2.0])
    for tilt_deg in (2.0, 30.0, 70.0):
        t = np.radians(tilt_deg)
        v = Vertical((float(np.sin(t)), 0.0, float(np.cos(t))), "points", False, 0.05)
        poses = {p.name: p for p in starting_poses(v, centre)}
        assert set(poses) == ({"as is", "down"} if tilt_deg < 15 else {"as is", "up", "down"})
        as_is = poses["as is"]
        np.testing.assert_array_equal(as_is.T.matrix, np.eye(4))
        assert not as_is.free_tilt  # level data: no plane fitted to their heights
        # beyond MAX_GROUND_TILT_DEG (40) the points as they are come last, as a last resort
        assert as_is.last_resort == (tilt_deg > 40)
        assert (list(poses)[-1] == "as is") == (tilt_deg > 40)
        for name in poses.keys() - {"as is"}:  # each levelled pose turns its normal onto +z
            sense = 1.0 if name == "up" else -1.0
            R = poses[name].T.matrix[:3, :3]
            np.testing.assert_allclose(R @ (sense * np.array(v.up)), [0, 0, 1], atol=1e-12)
            assert not poses[name].last_resort
    cams = Vertical((0.6, 0.0, 0.8), "cameras", True, 0.05)
    assert [p.name for p in starting_poses(cams, centre)] == ["up"]
    assert [p.name for p in starting_poses(cams, centre, as_is_first=True)] == ["up"]


def test_where_the_plane_says_nothing_the_points_as_they_are_come_first():
    from tiereg.level import Vertical, starting_poses

    centre = np.array([500.0, -20.0, 80.0])
    for tilt_deg in (2.0, 30.0, 70.0):
        t = np.radians(tilt_deg)
        v = Vertical((float(np.sin(t)), 0.0, float(np.cos(t))), "points", False, 0.05)
        poses = starting_poses(v, centre, as_is_first=True)
        assert poses[0].name == "as is" and not poses[0].last_resort
        assert [p.name for p in poses[1:]] == ["as is, turned over"] + (
            ["down"] if tilt_deg < 15 else ["up", "down"])
        assert all(p.last_resort for p in poses[1:])
        over = poses[1].T  # half a turn about x through the centre: z and y change sense
        np.testing.assert_allclose(over.matrix[:3, :3], np.diag([1.0, -1.0, -1.0]))
        np.testing.assert_allclose(over.apply(centre[None])[0], centre)
        assert not poses[1].free_tilt


def test_steep_ground_is_told_by_its_dominant_plane():
    from tiereg.level import is_steep_ground

    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 1000, (20000, 2))
    bumps = 5.0 * np.sin(xy[:, 0] / 50.0) * np.cos(xy[:, 1] / 70.0)  # metres of relief
    for slope_deg, steep in ((0.0, False), (10.0, False), (20.0, True), (50.0, True)):
        z = np.tan(np.radians(slope_deg)) * xy[:, 0] + bumps
        assert is_steep_ground(np.column_stack([xy, z])) == steep, slope_deg
    # a massif as high as it is wide has no dominant plane: steep
    r = np.hypot(xy[:, 0] - 500, xy[:, 1] - 500)
    assert is_steep_ground(np.column_stack([xy, 900.0 * np.exp(-(r / 300.0) ** 2)]))
    assert not is_steep_ground(np.zeros((2, 3)))
