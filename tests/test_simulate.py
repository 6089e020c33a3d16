"""The simulator itself: the truth is true, seeds reproduce, rates are as asked."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from tiereg.cli import main
from tiereg.errors import MissingDependencyError
from tiereg.io import read_points
from tiereg.robust import nmad
from tiereg.simulate import HiddenTransform, ImageBlock, LidarSurvey, SceneSpec, make_scene
from tiereg.simulate.world import find_corners
from tiereg.transform import Transform

SMALL = dict(world_size_m=3000.0, lidar_size_m=2000.0,
             block=ImageBlock(side_m=1500.0, blunder_fraction=0.05),
             survey=LidarSurvey(density_per_m2=0.5))


@pytest.fixture(scope="module")
def scene():
    return make_scene(SceneSpec(kind="suburban", seed=4, overlap=0.6, **SMALL))


def test_truth_maps_tie_points_onto_the_surface_within_the_noise(scene):
    block = scene.spec.block
    georef = np.asarray(scene.spec.georef)
    in_ref = scene.T_ref_mov.apply(scene.moving) - georef  # back into the world frame
    ok = ~scene.tie_points.blunder
    d_xy = in_ref[ok, :2] - scene.tie_points.true_xyz[ok, :2]
    d_z = in_ref[ok, 2] - scene.tie_points.true_xyz[ok, 2]
    # noise as simulated: 0.15 m horizontally, 0.3 m vertically (NMAD within 15 %)
    assert nmad(d_xy.ravel()) == pytest.approx(block.noise_xy_m, rel=0.15)
    assert nmad(d_z) == pytest.approx(block.noise_z_m, rel=0.15)
    assert abs(np.median(d_z)) < 0.05
    # and the true points lie on the visible surface
    from tiereg.simulate import make_world

    world = make_world("suburban", size_m=3000.0, seed=4)
    t = scene.tie_points.true_xyz
    assert np.allclose(world.sample("dsm", t[:, 0], t[:, 1]), t[:, 2])


def test_same_seed_same_scene(scene):
    again = make_scene(SceneSpec(kind="suburban", seed=4, overlap=0.6, **SMALL))
    assert np.array_equal(again.moving, scene.moving)
    assert np.array_equal(again.lidar.xyz, scene.lidar.xyz)
    assert again.T_ref_mov.isclose(scene.T_ref_mov)
    other = make_scene(SceneSpec(kind="suburban", seed=5, overlap=0.6, **SMALL))
    assert not np.array_equal(other.moving[:10], scene.moving[:10])


def test_rates_and_densities_are_as_asked(scene):
    n = len(scene.moving)
    expected = 350.0 * 1.5**2  # tie points per km2 over the 1.5 km block
    assert n == pytest.approx(expected, rel=0.02)
    blunders = scene.tie_points.blunder.mean()  # binomial: 5 % of ~790, sd 0.8 %
    assert abs(blunders - 0.05) < 0.025
    assert scene.overlap == pytest.approx(0.6, abs=0.03)
    lidar_first = (scene.lidar.return_number == 1).sum() / 2000.0**2
    assert lidar_first == pytest.approx(0.5, rel=0.1)  # pulses per m2, strip overlap included
    assert scene.tie_points.rays.min() >= 2  # every tie point is seen in two images or more


def test_hidden_transform_is_the_one_asked():
    hidden = HiddenTransform(heading_deg=37.0, scale=3.2808, tilt_deg=(0.2, -0.1),
                             model_origin=(10.0, 20.0, 30.0))
    sc = make_scene(SceneSpec(kind="farmland", seed=1, hidden=hidden, **SMALL))
    p = sc.T_ref_mov.inverse.parameters()
    assert p.scale == pytest.approx(3.2808)
    assert np.degrees(p.kappa) == pytest.approx(37.0, abs=0.01)
    assert np.degrees(p.omega) == pytest.approx(0.2, abs=0.01)


@pytest.mark.parametrize("kind", ["farmland", "urban", "forest", "mountains"])
def test_every_kind_builds_with_its_character(kind):
    sc = make_scene(SceneSpec(kind=kind, seed=2, **SMALL))
    z = sc.lidar.xyz[:, 2]
    relief = np.percentile(z, 95) - np.percentile(z, 5)
    veg = (sc.lidar.classification == 5).mean()
    if kind == "mountains":
        assert relief > 300
    if kind == "forest":
        assert veg > 0.4  # mostly canopy returns
    if kind == "urban":
        assert (sc.lidar.classification == 6).mean() > 0.1  # many building returns
    assert len(sc.moving) > 700


def test_cli_writes_a_scene(tmp_path, capsys):
    code = main(["simulate", str(tmp_path), "--kind", "urban", "--seed", "3",
                 "--world-size", "3000", "--lidar-size", "2000", "--block-size", "1500",
                 "--lidar-density", "0.3", "--overlap", "0.8", "--heading", "45",
                 "--scale", "0.5"])
    assert code == 0
    truth = json.loads((tmp_path / "truth.json").read_text())
    T = Transform.from_dict(truth)
    lidar = read_points(tmp_path / "reference.laz").xyz
    ties = read_points(tmp_path / "tiepoints.xyz").xyz
    assert len(lidar) > 1_000_000 and 700 < len(ties) < 900
    assert T.scale == pytest.approx(2.0) and truth["overlap_fraction"] == pytest.approx(0.8,
                                                                                          abs=0.03)


def test_without_scikit_image_the_simulator_says_which_extra_installs_it(tmp_path, monkeypatch,
                                                                          capsys):
    for name in ("skimage", "skimage.feature"):
        monkeypatch.setitem(sys.modules, name, None)
    image = np.zeros((32, 32))
    image[8:24, 8:24] = 1.0  # a square: four corners
    with pytest.raises(MissingDependencyError, match=r"tiereg\[simulate\]"):
        find_corners(image)
    code = main(["simulate", str(tmp_path / "scene"), "--kind", "farmland",
                 "--world-size", "800", "--lidar-size", "600", "--block-size", "400"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "tiereg[simulate]" in err[0]
    assert not (tmp_path / "scene").exists()
