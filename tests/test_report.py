"""The report: its files and numbers, control points against the true surface, the browser view."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from tiereg import register
from tiereg.cli import main
from tiereg.demo import make_tie_points, sample_lidar
from tiereg.errors import MissingDependencyError
from tiereg.io import open_points
from tiereg.report import write_report


@pytest.fixture(scope="module")
def demo_result():
    tie = make_tie_points(open_points(sample_lidar()).read().xyz)
    return register(tie, sample_lidar())


@pytest.fixture(scope="module")
def report(demo_result, tmp_path_factory):
    return write_report(demo_result, tmp_path_factory.mktemp("report"))


@pytest.mark.slow
def test_report_writes_maps_tables_and_a_self_contained_page(report, demo_result):
    out = report.directory
    for name in ("report.html", "dz_before.png", "dz_after.png", "residual_histogram.png",
                 "coarse_candidates.png", "coarse_correlation.png", "dz_before.tif",
                 "dz_after.tif", "residuals.csv",
                 "control_points.csv", "control_points.txt", "control_points_colmap.txt"):
        assert (out / name).stat().st_size > 0, name
    page = (out / "report.html").read_text()
    assert page.count("data:image/png;base64,") == 5  # maps, histogram, coarse evidence
    assert "http://" not in page and "https://" not in page and "<script" not in page
    assert "Registered and confident" in page
    # per-point residuals: one row per tie point, the same numbers as the result's statistics
    rows = (out / "residuals.csv").read_text().splitlines()
    assert rows[0] == "x,y,z,dz_before,dz_after,weight,blunder"
    assert len(rows) == 1 + len(demo_result.residuals.xyz)
    dz = np.array([float(r.split(",")[4]) for r in rows[1:] if r.split(",")[4]])
    assert np.median(dz) == pytest.approx(demo_result.quality.median_dz, abs=1e-4)
    # the correlation picture's surface peaks within a cell of the answer
    from tiereg.coarse.scoring import score_around
    from tiereg.report import PICTURE_CELLS

    placed = demo_result.residuals.xyz - demo_result.reference.origin
    w = score_around(placed, demo_result.reference, demo_result.cell_size, cells=PICTURE_CELLS)
    peak = np.array(np.unravel_index(int(np.argmax(w)), w.shape)) - PICTURE_CELLS
    assert np.abs(peak).max() <= 1
    # the blunders the demo planted (2 %, tens of feet) are flagged
    assert 0.01 < demo_result.residuals.blunder.mean() < 0.06


def test_height_difference_geotiff_is_georeferenced(report, demo_result):
    import rasterio

    with rasterio.open(report.directory / "dz_after.tif") as ds:
        assert ds.crs is not None
        band = ds.read(1, masked=True)
        left, bottom, right, top = ds.bounds
    xy = demo_result.residuals.xyz[:, :2]
    assert left <= xy[:, 0].min() and right >= xy[:, 0].max()  # feet, State Plane
    assert bottom <= xy[:, 1].min() and top >= xy[:, 1].max()
    assert abs(float(np.ma.median(band))) < 0.5  # feet: registered, centred on zero


def test_control_points_sit_on_the_true_surface():
    # a simulated suburb: the control points' lidar heights against the world's true surface
    from tiereg.simulate import (
        GEOREF,
        HiddenTransform,
        ImageBlock,
        LidarSurvey,
        SceneSpec,
        make_scene,
        make_world,
    )

    spec = SceneSpec(kind="urban", seed=42, world_size_m=1500.0, lidar_size_m=1200.0,
                     block=ImageBlock(side_m=1000.0), survey=LidarSurvey(density_per_m2=1.0),
                     hidden=HiddenTransform(heading_deg=20.0, scale=1.0), block_heading_deg=0.0)
    world = make_world(spec.kind, size_m=spec.world_size_m, cell=spec.world_cell_m, seed=spec.seed)
    scene = make_scene(spec, world=world)
    result = register(scene.moving, scene.lidar.xyz, coarse="none", initial=scene.T_ref_mov,
                      cell_size=20.0)
    from tiereg.control import select_control_points

    cps = select_control_points(result.residuals.xyz - result.reference.origin, result.reference,
                                blunder=result.residuals.blunder)
    assert len(cps) >= 20
    xyz = np.array([p.xyz for p in cps])
    true = world.sample("dsm", xyz[:, 0] - GEOREF[0], xyz[:, 1] - GEOREF[1])
    assert np.mean(np.abs(xyz[:, 2] - true) <= 0.1) >= 0.95  # metres
    # spread over the block: control points in most of the 12 x 12 cells that have tie points
    assert len({(int(x // 100), int(y // 100)) for x, y in xyz[:, :2]}) >= 10
    assert {p.kind for p in cps} <= {"height", "xyz"}


def test_a_registration_that_failed_still_gets_its_report(demo_result, tmp_path):
    """Tie points that no shift near the answer lays on the lidar (here moved off it by more
    than the block's width): the report is written, without a correlation picture."""
    xyz = demo_result.residuals.xyz
    off = replace(demo_result, residuals=replace(
        demo_result.residuals, xyz=xyz + [1.2 * np.ptp(xyz[:, 0]), 0.0, 0.0]))
    write_report(off, tmp_path)
    assert (tmp_path / "report.html").exists() and (tmp_path / "dz_after.png").exists()
    assert not (tmp_path / "coarse_correlation.png").exists()


@pytest.mark.slow
def test_register_report_option_and_report_command(tmp_path):
    ties = tmp_path / "ties.xyz"
    np.savetxt(ties, make_tie_points(open_points(sample_lidar()).read().xyz))
    code = main(["register", str(ties), str(sample_lidar()), "-o", str(tmp_path / "R.json"),
                 "--report", str(tmp_path / "rep"), "-q"])
    assert code == 0 and (tmp_path / "rep" / "report.html").exists()
    first = (tmp_path / "rep" / "residuals.csv").read_text().splitlines()
    assert main(["report", str(tmp_path / "R.json"), str(tmp_path / "again"), "-q"]) == 0
    again = (tmp_path / "again" / "residuals.csv").read_text().splitlines()
    assert len(again) == len(first)
    # the same final heights (the fine weights are not in RESULT.json: the last columns differ)
    a = np.array([[float(v) if v else np.nan for v in r.split(",")[:5]] for r in first[1:]])
    b = np.array([[float(v) if v else np.nan for v in r.split(",")[:5]] for r in again[1:]])
    np.testing.assert_allclose(a[:, 4], b[:, 4], atol=2e-4, equal_nan=True)
    # sloped control points carry the registration's horizontal precision either way (RESULT.json
    # keeps it), which also enters their height's
    def sloped_sx(folder):
        rows = [r.split(",") for r in (tmp_path / folder / "control_points.csv").read_text()
                .splitlines()[1:]]
        return {r[4] for r in rows if r[7] == "xyz"}

    assert sloped_sx("rep") and sloped_sx("again") == sloped_sx("rep") != {""}


def test_report_command_bad_input_is_one_line(tmp_path, capsys):
    code = main(["report", str(tmp_path / "missing.json"), str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "RESULT.json" in err[0]
    assert not (tmp_path / "out").exists()


def _browser() -> str | None:
    return next((shutil.which(b) for b in ("chromium", "chromium-browser", "google-chrome")
                 if shutil.which(b)), None)


def test_report_renders_in_a_headless_browser(report, tmp_path):
    browser = _browser()
    if browser is None:
        if os.environ.get("CI"):
            pytest.fail("no headless Chromium: `make test` installs the Debian package chromium")
        pytest.skip("no Chromium here (make test installs it)")
    shot = tmp_path / "shot.png"
    subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    "--window-size=1200,1800", f"--screenshot={shot}",
                    (report.directory / "report.html").as_uri()],
                   check=True, capture_output=True, timeout=120)
    from matplotlib.image import imread

    img = imread(shot)[:, :, :3]
    assert img.shape[0] >= 1000 and img.shape[1] >= 1000
    # the maps are there: strong reds and blues of the diverging colour scale, and they cover
    # a fair part of the page (a page without its pictures is nearly all white)
    red = (img[:, :, 0] > 0.6) & (img[:, :, 2] < 0.35) & (img[:, :, 1] < 0.35)
    blue = (img[:, :, 2] > 0.5) & (img[:, :, 0] < 0.3)
    assert red.sum() > 500 and blue.sum() > 500
    assert np.mean(img.sum(axis=2) < 2.7) > 0.03


def test_without_matplotlib_the_report_names_its_extra_and_writes_nothing(demo_result, tmp_path,
                                                                           monkeypatch):
    # an installation without the `report` extra: importing matplotlib fails
    for name in ("matplotlib", "matplotlib.pyplot"):
        monkeypatch.setitem(sys.modules, name, None)
    with pytest.raises(MissingDependencyError, match=r"tiereg\[report\]"):
        write_report(demo_result, tmp_path / "report")
    assert not (tmp_path / "report").exists()
