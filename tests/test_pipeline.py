"""End to end: known shifts recovered, honest confidence, the RESULT.json contract."""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest
from scenes import make_scene

from tiereg import InputError, PointSet, Transform
from tiereg.demo import make_tie_points, run_demo, sample_lidar, sample_model
from tiereg.files import grid_to_geotiff
from tiereg.io import open_points, write_points
from tiereg.pipeline import register

SHIFT = Transform.from_translation((-12345.6, 2345.7, -50.0))  # reference -> moving


def horizontal_error_cells(result, scene):
    centre = scene.tie_mov.mean(axis=0, keepdims=True)
    err = (result.T_ref_mov.apply(centre) - scene.T_ref_mov.apply(centre))[0]
    return np.hypot(err[0], err[1]) / result.cell_size, err


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow),
                                  pytest.param(2, marks=pytest.mark.slow)])
def test_recovers_a_known_shift_at_projected_coordinates(seed):
    scene = make_scene(seed=seed, T_mov_ref=SHIFT, lidar_points=200_000,
                       block_offset=(100.0 * seed, -80.0 * seed))
    result = register(scene.tie_mov, scene.lidar)
    cells, err = horizontal_error_cells(result, scene)
    assert result.confident
    assert cells < 0.1  # sub-cell refinement: a tenth of a (20 m) cell
    assert abs(err[2]) < 0.1  # metres; tie-point height noise is 0.3 m over 2,000 points
    assert result.quality.nmad_dz < 0.6  # 0.3 m noise, 0.05 m lidar noise, gridding
    assert result.quality_before.n_used == 0  # 12 km off before registration: no overlap


@pytest.mark.slow
def test_demo_registers_the_colmap_model_as_the_truth_has_it(tmp_path):
    """The shipped COLMAP model (73 ft per model unit, upside down) onto the shipped lidar with
    no initial guess: within 2 deg and 2 % of the truth, 1.5 GSD RMS over its points (the
    tolerances of the structure-from-motion benchmark)."""
    outcome = run_demo(tmp_path)
    assert outcome.result.confident, outcome.result.reasons
    assert outcome.rotation_error_deg <= 2.0
    assert abs(outcome.result.T_ref_mov.scale / outcome.T_ref_mov_true.scale - 1) <= 0.02
    assert outcome.rms_gsd <= 1.5
    assert outcome.error_cells < 0.5
    saved = json.loads((tmp_path / "RESULT.json").read_text())
    assert np.allclose(saved["T_ref_mov"], outcome.result.T_ref_mov.matrix)
    # consistent: registered again from its own answer, the block stays where it is (RMS at
    # its points within a twentieth of the registration's cell)
    xyz = open_points(sample_model()).read().xyz
    again = register(xyz, outcome.result.reference, coarse="none",
                     initial=outcome.result.T_ref_mov)
    moved = again.T_ref_mov.apply(xyz) - outcome.result.T_ref_mov.apply(xyz)
    assert np.sqrt(np.mean(np.sum(moved**2, axis=1))) < outcome.result.cell_size / 20


@pytest.mark.parametrize("T_mov_ref", [
    Transform.from_parameters(kappa=np.radians(3.0), translation=(-500.0, 300.0, 0.0)),
    Transform.from_parameters(kappa=np.radians(30.0), translation=(-500.0, 300.0, 0.0)),
    Transform.from_parameters(scale=1.1, translation=(-500.0, 300.0, 0.0)),
    Transform.from_parameters(scale=1 / 0.3048, translation=(-500.0, 300.0, 0.0)),  # feet
], ids=["kappa3", "kappa30", "scale1.1", "feet"])
def test_translation_only_never_answers_rotation_or_scale_confidently(T_mov_ref):
    scene = make_scene(seed=4, T_mov_ref=T_mov_ref, lidar_points=200_000)
    result = register(scene.tie_mov, scene.lidar, coarse="pomf")
    assert not result.confident
    assert result.confidence < 0.5
    assert result.reasons


@functools.cache
def _beyond_the_edge(seed: int):
    return make_scene(seed=seed, block_offset=(2600.0, 300.0), lidar_points=200_000)


@pytest.mark.slow
@pytest.mark.parametrize("where", ["beyond the edge", "another world"])
@pytest.mark.parametrize(("seed", "method"), [(0, "pomf"), (1, "auto")])
def test_no_overlap_is_not_confident(seed, method, where):
    # tie points on terrain 1.6 km beyond the lidar's edge, or from another world entirely
    outside = _beyond_the_edge(seed)
    ties = (outside if where == "beyond the edge"
            else make_scene(seed=seed + 50, lidar_points=1000)).tie_mov
    assert not register(ties, outside.lidar, coarse=method).confident


@pytest.mark.slow
def test_reference_as_geotiff_dsm(tmp_path):
    scene = make_scene(seed=5, T_mov_ref=SHIFT, lidar_points=300_000)
    write_points(tmp_path / "lidar.laz", scene.lidar)
    grid_to_geotiff(tmp_path / "lidar.laz", tmp_path / "dsm.tif", cell_size=4.0)
    result = register(PointSet(scene.tie_mov), tmp_path / "dsm.tif")
    cells, err = horizontal_error_cells(result, scene)
    assert result.confident and cells < 0.1 and abs(err[2]) < 0.15
    assert result.inputs.reference_format == "geotiff"


def test_json_writes_numbers_that_are_not_finite_as_null():
    from tiereg._json import dumps_json

    data = {"ratio": float("inf"), "row": [1.5, float("nan")], "n": np.float64(-np.inf),
            "deep": {"ok": np.float32(2.5), "flag": True, "count": 3}, "pair": (0.5, np.inf)}
    assert json.loads(dumps_json(data)) == {"ratio": None, "row": [1.5, None], "n": None,
                                            "deep": {"ok": 2.5, "flag": True, "count": 3},
                                            "pair": [0.5, None]}


@pytest.mark.slow
def test_result_json_follows_the_contract():
    scene = make_scene(seed=6, T_mov_ref=SHIFT, lidar_points=100_000)
    data = json.loads(register(scene.tie_mov, scene.lidar).to_json())
    for key in ("tiereg_version", "T_ref_mov", "parameters", "precision", "confident",
                "confidence", "stages", "quality", "inputs"):
        assert key in data
    T = np.array(data["T_ref_mov"])
    p = data["parameters"]
    rebuilt = Transform.from_parameters(scale=p["scale"], omega=np.radians(p["omega_deg"]),
                                        phi=np.radians(p["phi_deg"]),
                                        kappa=np.radians(p["kappa_deg"]),
                                        translation=p["translation"])
    assert np.allclose(rebuilt.matrix, T, rtol=0, atol=1e-9)
    precision = data["precision"]  # filled by the fine stage, one sigma per parameter
    assert {"scale", "omega_deg", "phi_deg", "kappa_deg", "translation"} <= set(precision)
    assert 0.0 < precision["translation"][2] < 0.1  # metres: 0.3 m height noise, 100 k lidar
    assert [s["name"] for s in data["stages"]] == ["coarse", "verdict", "fine"]
    assert data["stages"][0]["method"] == "auto" and data["stages"][2]["method"] == "lsm"
    verdict = data["stages"][1]  # the refined fits that decided: the answer first, its rivals
    assert verdict["confident"] is data["confident"] and verdict["chosen"] == "coarse answer"
    assert verdict["poses"][0]["unexplained"] < 0.5 and len(verdict["poses"]) >= 2
    assert {"n_moving", "n_used", "rmse_z", "median_dz", "nmad_dz"} <= set(data["quality"])
    assert 0.0 <= data["confidence"] <= 1.0
    exports = data["exports"]  # paste-ready for PDAL and CloudCompare
    assert np.array_equal(Transform.from_text(exports["pdal_filters_transformation_matrix"]).matrix,
                          T)
    assert np.array_equal(Transform.from_text("\n".join(exports["cloudcompare_matrix"])).matrix, T)


def test_coarse_none_keeps_the_input_position():
    scene = make_scene(seed=7, lidar_points=100_000)  # already aligned
    result = register(scene.tie_mov, scene.lidar, coarse="none", fine="none")
    assert result.T_ref_mov.isclose(Transform.identity())
    assert result.quality.n_used == len(scene.tie_mov)


@pytest.mark.slow
def test_a_starting_pose_the_fine_stage_cannot_confirm_is_not_confident():
    """With --coarse none only the fine stage vouches for the given pose: a pose within a cell
    of the truth is refined and confident; one it would have to move farther than the coarse
    stage's uncertainty (two cells), or cannot refine at all, is reported as not confident."""
    tie = make_tie_points(open_points(sample_lidar()).read().xyz)
    truth = register(tie, sample_lidar())
    centre = tie.mean(axis=0, keepdims=True)
    for off_cells, confident, why in ((1.0, True, ""), (2.5, False, "contradicts the starting"),
                                      (5.0, False, "could not confirm")):
        start = Transform.from_translation((off_cells * truth.cell_size, 0.0, 0.0))
        result = register(tie, sample_lidar(), coarse="none", initial=start @ truth.T_ref_mov)
        assert result.confident is confident, off_cells
        assert why in " ".join(result.reasons)
        if confident:  # refined back onto the truth, to a tenth of a cell
            err = result.T_ref_mov.apply(centre) - truth.T_ref_mov.apply(centre)
            assert np.hypot(*err[0, :2]) < 0.1 * truth.cell_size


@pytest.mark.slow
def test_stray_points_far_outside_the_block_are_left_out_of_the_estimation():
    """A nodata height (-9999) and a point left at the origin among the tie points: the
    registration is that of the others, both are named in the warnings, and every row is still
    reported (the residuals keep the file's rows)."""
    tie = make_tie_points(open_points(sample_lidar()).read().xyz)
    clean = register(tie, sample_lidar())
    stray = tie.copy()
    stray[7, 2] = -9999.0
    stray[300] = 0.0
    result = register(stray, sample_lidar())
    assert result.confident
    centre = tie.mean(axis=0, keepdims=True)
    err = result.T_ref_mov.apply(centre) - clean.T_ref_mov.apply(centre)
    assert np.abs(err).max() < 0.05 * clean.cell_size
    assert "row(s) 7, 300" in " ".join(result.warnings)
    assert len(result.residuals.xyz) == len(tie) and np.isnan(result.residuals.weight[[7, 300]]
                                                               ).all()


def test_gross_outliers_are_strays_not_the_relief():
    from tiereg.points import gross_outliers

    rng = np.random.default_rng(3)
    xyz = np.column_stack([rng.uniform(0, 3000, 2000) + 5e5, rng.uniform(0, 3000, 2000) + 5e6,
                           rng.normal(100, 0.3, 2000)])  # level farmland
    xyz[:15, 2] += 25.0  # trees and farmsteads: the relief, not strays
    xyz[20, 2], xyz[21] = -9999.0, 0.0
    assert np.flatnonzero(gross_outliers(xyz)).tolist() == [20, 21]
    xyz[30:60, 2] = -9999.0  # 1.6 % of the points down there: part of the data, not strays
    assert np.flatnonzero(gross_outliers(xyz)).tolist() == [21]
    xyz[60:72, 2], xyz[72:84, 2] = -9999.0, 9999.0  # 2.9 % off either way: none are strays
    xyz[30:60, 2] = 100.0
    assert not gross_outliers(xyz).any()


@pytest.mark.parametrize("points, fragment", [
    (np.zeros((0, 3)), "empty"),
    (np.random.default_rng(0).uniform(0, 100, (10, 3)), "at least"),
    (np.column_stack([np.arange(100.0), np.arange(100.0), np.zeros(100)]), "line"),
    (np.ones((100, 3)), "one horizontal position"),
    (np.vstack([np.random.default_rng(0).uniform(0, 100, (99, 3)), [[np.nan, 0, 0]]]), "NaN"),
])
def test_unusable_moving_points_are_rejected(points, fragment):
    scene = make_scene(seed=0, lidar_points=10_000)
    with pytest.raises(InputError, match=fragment):
        register(points, scene.lidar)


def test_unknown_methods_are_rejected():
    with pytest.raises(InputError, match="coarse method"):
        register(np.zeros((50, 3)), np.zeros((50, 3)), coarse="magic")
    with pytest.raises(InputError, match="fine method"):
        register(np.zeros((50, 3)), np.zeros((50, 3)), fine="magic")
