"""The prepared reference: exact aggregation, first returns, reuse across registrations."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pytest
from scenes import make_scene

from tiereg import Reference, Transform, register
from tiereg.grid import GridSpec, rasterize
from tiereg.io import open_points
from tiereg.io.base import ArraySource
from tiereg.points import PointSet
from tiereg.reference import aggregate, prepare_reference


@pytest.mark.parametrize("k", [2, 3, 8])
def test_aggregation_equals_gridding_at_the_coarse_cell(rng, k):
    xyz = np.column_stack([rng.uniform(-503, 497, 20000), rng.uniform(-251, 749, 20000),
                           rng.normal(50, 10, 20000)])
    base = rasterize(xyz, GridSpec.from_bounds(-503, -251, 497, 749, 5.0), stats=("mean",))
    coarse = aggregate(base, k)
    direct_spec = GridSpec.from_bounds(-503, -251, 497, 749, 5.0 * k)
    direct = rasterize(xyz, direct_spec, stats=("mean",))
    # same lattice (corners snapped to multiples of the coarse cell), same numbers
    assert coarse.spec.x0 == direct_spec.x0 and coarse.spec.y0 == direct_spec.y0
    r, c = direct.count.shape
    assert np.array_equal(coarse.count[:r, :c], direct.count)
    assert coarse.count[r:, :].sum() == 0 and coarse.count[:, c:].sum() == 0
    assert np.allclose(coarse["mean"][:r, :c], direct["mean"], equal_nan=True, atol=1e-9)


@pytest.mark.parametrize("k", [1, 3])
def test_aggregated_max_is_the_highest_base_cell_of_each_block(rng, k):
    xyz = np.column_stack([rng.uniform(-103, 97, 3000), rng.uniform(-51, 149, 3000),
                           rng.normal(50, 10, 3000)])
    base = rasterize(xyz, GridSpec.from_bounds(-103, -51, 97, 149, 5.0), stats=("mean",))
    coarse = aggregate(base, k, stats=("mean", "max"))
    expected = np.full(coarse.count.shape, np.nan)
    rows, cols = np.nonzero(base.mask)
    x, y = base.spec.xy(rows, cols)
    cr = np.floor((coarse.spec.y0 - y) / coarse.spec.cell_size).astype(int)
    cc = np.floor((x - coarse.spec.x0) / coarse.spec.cell_size).astype(int)
    for r, c, z in zip(cr, cc, base["mean"][rows, cols]):  # slow and obvious
        expected[r, c] = z if np.isnan(expected[r, c]) else max(expected[r, c], z)
    assert np.array_equal(coarse["max"], expected, equal_nan=True)


def test_first_returns_only(tmp_path):
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = np.array([0.01, 0.01, 0.01])
    data = laspy.LasData(header)
    xy = np.repeat(np.array([[0.5, 0.5], [1.5, 0.5]]), 2, axis=0)
    data.x, data.y = xy[:, 0], xy[:, 1]
    data.z = np.array([20.0, 2.0, 30.0, 3.0])  # canopy first returns, ground last returns
    data.return_number = np.array([1, 2, 1, 2])
    data.number_of_returns = np.array([2, 2, 2, 2])
    data.write(str(tmp_path / "r.las"))
    ref = prepare_reference(open_points(tmp_path / "r.las"), base_cell=1.0)
    assert ref.first_returns_only
    heights = ref.base["mean"][ref.base.mask] + ref.origin[2]  # the grid is in local coordinates
    assert sorted(heights.tolist()) == [20.0, 30.0]


@pytest.mark.parametrize("version, point_format", [("1.2", 1), ("1.4", 6)])
def test_noise_and_withheld_points_are_not_the_surface(tmp_path, version, point_format):
    """Low points (class 7), high noise (class 18) and withheld points hundreds of metres off
    the ground would pull whole cells: the grid and the points the fine stage reads leave them
    out."""
    header = laspy.LasHeader(version=version, point_format=point_format)
    header.scales = np.array([0.01, 0.01, 0.01])
    data = laspy.LasData(header)
    x, y = np.meshgrid(np.arange(0.5, 10.0), np.arange(0.5, 10.0))
    ground = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 100.0)])
    stray = ground[::7] + [0.0, 0.0, 700.0]  # birds and multipath echoes
    xyz = np.vstack([ground, stray, stray - [0.0, 0.0, 900.0], stray + [0.0, 0.0, 50.0]])
    data.x, data.y, data.z = xyz.T
    k = len(stray)
    data.classification = np.array([2] * len(ground) + [18] * k + [7] * k + [1] * k, np.uint8)
    data.withheld = np.array([0] * (len(ground) + 2 * k) + [1] * k, bool)
    data.return_number = np.ones(len(xyz), np.uint8)
    data.number_of_returns = np.ones(len(xyz), np.uint8)
    data.write(str(tmp_path / "noisy.las"))
    ref = prepare_reference(open_points(tmp_path / "noisy.las"), base_cell=1.0)
    heights = ref.base["mean"][ref.base.mask] + ref.origin[2]
    assert ref.base.count.sum() == len(ground) and np.all(heights == 100.0)
    kept = np.vstack(list(ref.local_chunks())) + ref.origin
    assert len(kept) == len(ground) and np.all(kept[:, 2] == 100.0)


@pytest.mark.slow
def test_a_prepared_reference_serves_many_registrations():
    scene = make_scene(seed=8, T_mov_ref=Transform.from_translation((-3000.0, 700.0, 10.0)),
                       lidar_points=200_000)
    # 200,000 points over 2 km x 2 km: 4.5 m spacing, so a 5 m base cell (coarse cell 20 m)
    ref = prepare_reference(ArraySource(PointSet(scene.lidar)), base_cell=5.0)
    for shift in ((0.0, 0.0, 0.0), (123.4, -56.7, 8.9)):
        moving = scene.tie_mov + shift
        result = register(moving, ref)
        truth = scene.T_ref_mov @ Transform.from_translation(shift).inverse
        c = moving.mean(axis=0, keepdims=True)
        err = result.T_ref_mov.apply(c) - truth.apply(c)
        assert result.confident and np.hypot(*err[0, :2]) < 0.1 * result.cell_size


AUTZEN_LAS = Path(__file__).parent / "data" / "autzen-bmx-2010.las"


@pytest.fixture
def grid_passes(monkeypatch) -> list:
    """The passes over a reference's points (``_grid`` calls), one entry each."""
    import tiereg.reference as reference_module

    passes: list = []
    real_grid = reference_module._grid
    monkeypatch.setattr(reference_module, "_grid",
                        lambda *args: passes.append(1) or real_grid(*args))
    return passes


def test_reference_open_reads_headers_now_and_grids_once_on_first_use(grid_passes):
    passes, path = grid_passes, AUTZEN_LAS
    ref = Reference.open(str(path))
    assert passes == []  # the header alone: where the points lie and the base grid's cells
    same = prepare_reference(open_points(str(path)))
    n = len(passes)
    assert ref.source_args == (str(path.resolve()),)  # where it came from, for RESULT.json
    assert np.array_equal(ref.origin, same.origin)
    assert ref.base_cell == same.base_cell  # the first use grids the points
    assert len(passes) == 2 * n
    assert np.array_equal(ref.base["mean"], same.base["mean"], equal_nan=True)
    assert ref.first_returns_only == same.first_returns_only
    ref.grid(4 * ref.base_cell)
    ref.surface()
    assert len(passes) == 2 * n  # and never again


def test_an_opened_reference_sent_to_another_process_is_gridded_once_before(grid_passes):
    """Pickled (to a worker) before its first use, an opened reference is gridded in the sender,
    once, and the copies carry the grid: the workers read no point to have it."""
    import pickle

    ref = Reference.open(str(AUTZEN_LAS))
    copies = [pickle.loads(pickle.dumps(ref)) for _ in range(3)]
    n = len(grid_passes)
    assert n >= 1
    for copy in copies:
        assert np.array_equal(copy.base["mean"], ref.base["mean"], equal_nan=True)
    assert len(grid_passes) == n


def _forest_edge(tmp_path):
    """A 1 m grid of lidar: open ground (class 2, one return a pulse) west of x = 20 m, a
    canopy east of it (its first returns classed 5, of pulses that split in two) 15 m up."""
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = np.array([0.01, 0.01, 0.01])
    data = laspy.LasData(header)
    x, y = np.meshgrid(np.arange(0.5, 40.0), np.arange(0.5, 40.0))
    x, y = x.ravel(), y.ravel()
    canopy = x > 20
    data.x, data.y, data.z = x, y, np.where(canopy, 115.0, 100.0)
    data.classification = np.where(canopy, 5, 2).astype(np.uint8)
    data.return_number = np.ones(len(x), np.uint8)
    data.number_of_returns = np.where(canopy, 2, 1).astype(np.uint8)
    data.write(str(tmp_path / "edge.las"))
    return prepare_reference(open_points(tmp_path / "edge.las"), base_cell=1.0)


def test_open_ground_leaves_out_vegetation_and_split_pulses(tmp_path):
    ref = _forest_edge(tmp_path)
    everything = np.vstack(list(ref.local_chunks())) + ref.origin
    solid = np.vstack(list(ref.local_chunks(open_ground=True))) + ref.origin
    assert len(everything) == 1600 and len(solid) == 800
    assert np.all(solid[:, 0] < 20) and np.all(solid[:, 2] == 100.0)


def test_solid_near_flags_the_points_on_open_ground(tmp_path):
    ref = _forest_edge(tmp_path)
    xy = np.array([[10.0, 20.0], [30.0, 20.0]]) - ref.origin[:2]
    points, solid = ref.solid_near(xy, 5.0)
    assert np.array_equal(points, ref.points_near(xy, 5.0))
    world = points + ref.origin
    assert solid.any() and (~solid).any()
    assert np.array_equal(solid, world[:, 0] < 20)


def test_the_fine_answer_on_a_canopy_is_refused(tmp_path):
    from tiereg.fine.lsm import _on_canopy

    ref = _forest_edge(tmp_path)
    lidar, solid = ref.solid_near(np.array([[0.0, 0.0]]), 40.0)
    rng = np.random.default_rng(0)
    west = np.column_stack([rng.uniform(1, 18, 60), rng.uniform(1, 39, 60), np.full(60, 100.0)])
    east = west + [21.0, 0.0, 15.0]  # on the crowns
    assert _on_canopy(west - ref.origin, lidar, solid, reach=2.5) == ""
    assert _on_canopy(np.vstack([west, east[:50]]) - ref.origin, lidar, solid, reach=2.5) == ""
    why = _on_canopy(east - ref.origin, lidar, solid, reach=2.5)
    assert "(100%) sit on vegetation" in why
    assert _on_canopy(east - ref.origin, lidar, None, reach=2.5) == ""  # no classes: open
