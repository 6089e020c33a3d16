"""tiereg calibrate on small simulated blocks with known cameras (a few seconds each)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")
pytest.importorskip("pyceres")

from tiereg.calibrate import calibrate  # noqa: E402
from tiereg.simulate import ImageBlock, LidarSurvey, SceneSpec, make_scene, make_world  # noqa: E402
from tiereg.simulate.cameras import (  # noqa: E402
    CameraModel,
    FlightPlan,
    fitted_registration,
    flat_world,
    flawed_model,
    make_camera_block,
)

CAMERA = CameraModel(2000, 1500, 2000.0, 1003.0, 748.0, k1=-0.03, k2=0.005)


def _scene(kind: str, *, flat: bool = False):
    spec = SceneSpec(kind=kind, seed=4, world_size_m=1400, lidar_size_m=1000,
                     survey=LidarSurvey(density_per_m2=1.5, gap_probability=0.0),
                     block=ImageBlock(side_m=700, tie_points_per_km2=6000,
                                      blunder_fraction=0.02),
                     block_heading_deg=20.0)
    world = make_world(kind, size_m=spec.world_size_m, cell=spec.world_cell_m, seed=spec.seed)
    return make_scene(spec, world=flat_world(world) if flat else world)


@pytest.fixture(scope="module")
def hilly():
    return _scene("farmland")


def _model(scene, tmp_path, name, *, plan, focal_error=0.02, ignore=True, camera=CAMERA):
    """A flawed model on disk and its registration (fitted to the true camera centres)."""
    block = make_camera_block(scene, plan, camera, max_points=2500)
    rec, _ = flawed_model(block, focal_error=focal_error, ignore_distortion=ignore)
    folder = tmp_path / name
    folder.mkdir()
    rec.write_binary(str(folder))
    return folder, fitted_registration(rec, block)


CROSS = FlightPlan(strips=3, images_per_strip=5, flying_height_m=300.0, cross=True, tilt_deg=8)


@pytest.mark.slow
def test_focal_and_distortion_recovered(hilly, tmp_path):
    folder, T = _model(hilly, tmp_path, "m", plan=CROSS)
    r = calibrate(folder, hilly.lidar.xyz, T_ref_mov=T)
    cam = r.camera()
    assert r.confident, r.reasons
    assert not cam.is_held("f") and not cam.is_held("k1")
    # from 2 % off and no distortion: focal within 0.3 %, k1 within 10 %
    assert abs(cam.value("f") / CAMERA.focal_px - 1) < 3e-3
    assert abs(cam.value("k1") / CAMERA.k1 - 1) < 0.10
    assert abs(cam.value("f", after=False) / CAMERA.focal_px - 1) > 0.019
    assert r.check_after.rmse_z < 0.5 * r.check_before.rmse_z


@pytest.mark.slow
def test_nothing_to_calibrate_stays(hilly, tmp_path):
    folder, T = _model(hilly, tmp_path, "m", plan=CROSS, focal_error=0.0, ignore=False)
    cam = calibrate(folder, hilly.lidar.xyz, T_ref_mov=T).camera()
    for name in ("f", "k1", "k2"):
        change = cam.value(name) - cam.value(name, after=False)
        sigma = cam.sigma[cam.names.index(name)]
        assert sigma is not None and abs(change) < 4 * sigma, (name, change, sigma)


@pytest.mark.slow
def test_flat_nadir_block_holds_the_focal_length(tmp_path):
    scene = _scene("farmland", flat=True)
    plan = FlightPlan(strips=3, images_per_strip=5, flying_height_m=300.0)
    folder, T = _model(scene, tmp_path, "m", plan=plan)
    r = calibrate(folder, scene.lidar.xyz, T_ref_mov=T)
    cam = r.camera()
    assert cam.is_held("f")
    assert "flying height" in dict(cam.held)["f"]
    assert cam.value("f") == cam.value("f", after=False)  # held at its input value
    assert cam.to_dict()["intrinsics"]["f"]["held"] is True
    # nothing silently wrong: every refined intrinsic within 3 sigma of the truth, or flagged
    flagged = {w.split(": ")[1] for w in r.warnings}
    for name, true in zip(cam.names, CAMERA.params):
        if cam.is_held(name) or name in flagged:
            continue
        sigma = cam.sigma[cam.names.index(name)]
        assert abs(cam.value(name) - true) <= 3 * sigma, (name, cam.value(name), true, sigma)
    # the first version held k1 at 0 and refined k2 to -0.066 (true 0.005) with a small sigma
    assert "k2" in flagged or cam.is_held("k2") or abs(cam.value("k2") - CAMERA.k2) < 0.005


def test_cli_bad_input_one_line(tmp_path):
    out = subprocess.run([sys.executable, "-m", "tiereg.cli", "calibrate", str(tmp_path / "no"),
                          str(tmp_path / "lidar.laz"), "-o", str(tmp_path / "out")],
                         capture_output=True, text=True)
    assert out.returncode == 2
    assert len(out.stderr.strip().splitlines()) == 1
    assert "MODEL" in out.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_cli_outputs_readable(hilly, tmp_path):
    import laspy

    folder, T = _model(hilly, tmp_path, "m", plan=CROSS)
    (tmp_path / "RESULT.json").write_text(json.dumps({"T_ref_mov": T.matrix.tolist()}))
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = np.array([0.001] * 3)
    header.offsets = np.floor(hilly.lidar.xyz.min(axis=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = hilly.lidar.xyz.T
    las.write(str(tmp_path / "lidar.laz"))
    out = tmp_path / "out"
    run = subprocess.run([sys.executable, "-m", "tiereg.cli", "calibrate", str(folder),
                          str(tmp_path / "lidar.laz"), "-o", str(out), "--report", "-q",
                          "--result", str(tmp_path / "RESULT.json")],
                         capture_output=True, text=True)
    assert run.returncode in (0, 3), run.stderr
    data = json.loads((out / "CALIBRATION.json").read_text())
    assert data["cameras"][0]["intrinsics"]["f"]["after"] > 0
    rec = pycolmap.Reconstruction(str(out / "model"))
    assert rec.num_reg_images() == 30
    assert (out / "model" / "cameras.txt").is_file()
    centre = np.mean([rec.images[i].projection_center() for i in rec.reg_image_ids()], axis=0)
    assert np.hypot(*(centre[:2] - hilly.lidar.xyz[:, :2].mean(axis=0))) < 600  # lidar frame
    assert "data:image/png;base64" in (out / "report" / "report.html").read_text()


def test_plane_cost_is_the_normal_distance():
    """The native lidar cost: weight x normal distance; along the plane next to nothing."""
    import pyceres

    from tiereg.calibrate.adjust import plane_cost

    normal = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    on_plane = np.array([10.0, -4.0, 2.0])
    for x in ([10.5, -3.0, 2.7], [11.0, -4.0, 2.0] + 5 * np.cross(normal, [1.0, 0, 0])):
        xyz = np.array(x, dtype=np.float64)
        problem = pyceres.Problem()
        problem.add_residual_block(plane_cost(normal, on_plane, 4.0), None, [xyz])
        r = np.asarray(problem.evaluate_residuals())
        expected = 4.0 * normal @ (xyz - on_plane)
        assert np.linalg.norm(r) == pytest.approx(abs(expected), abs=1e-3 + 1e-6 * abs(expected))


def test_quadric_follows_curved_ground_a_plane_does_not():
    """On a crest (z = 5 - 0.05 r^2) the quadratic surface gives the height at the point; a
    plane through the same patch passes 5 cm below it."""
    from tiereg.calibrate.lidar import fit_quadrics
    from tiereg.surface import fit_planes, plane_heights

    rng = np.random.default_rng(1)
    xy = rng.uniform(-2, 2, (1, 12, 2))
    z = 5.0 + 0.2 * xy[..., 0] - 0.05 * (xy[..., 0] ** 2 + xy[..., 1] ** 2)
    patch = np.concatenate([xy, z[..., None]], axis=-1)
    at = np.zeros((1, 2))
    height, slope, rough = fit_quadrics(patch, at)
    assert height[0] == pytest.approx(5.0, abs=1e-5)
    assert slope[0] == pytest.approx([0.2, 0.0], abs=1e-5)
    assert rough[0] < 1e-5
    c, n, _ = fit_planes(patch)
    assert plane_heights(c, n, np.zeros((1, 3)))[0] < 5.0 - 0.03


def _camera_rec():
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(
        model="RADIAL", width=2000, height=1500, params=[2000.0, 1000.0, 750.0, -0.03, 0.005],
        camera_id=1))
    return rec


def test_degenerate_focal_is_held_first_then_distortion_kept():
    """f undetermined and correlated with k1: holding f (the worst) leaves k1 determined, so
    only f is held; k2 is held with a held k1."""
    from tiereg.calibrate.degenerate import to_hold

    rec = _camera_rec()
    labels = [(1, 0), (1, 3), (1, 4)]  # f, k1, k2
    sf, sk1, sk2 = 200.0, 0.01, 0.0005  # f: 10 %; k1 alone undetermined through f
    r = 0.9999
    cov = np.array([[sf**2, r * sf * sk1, 0.0], [r * sf * sk1, sk1**2, 0.0],
                    [0.0, 0.0, sk2**2]])
    held = to_hold(cov, labels, rec)
    assert set(held) == {(1, 0)}
    assert "flying height" in held[(1, 0)]
    cov_k1 = np.diag([1e-8, 0.05**2, sk2**2])  # k1 itself undetermined: k2 goes with it
    assert set(to_hold(cov_k1, labels, rec)) == {(1, 3), (1, 4)}
