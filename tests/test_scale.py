"""Models in any gauge: the scales searched come from the data, and memory does not follow them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tiereg import register
from tiereg.coarse.scoring import MAX_REFERENCE_CELLS, SCALE_STEP, ScaleRange, tie_cell_for
from tiereg.io.base import ArraySource
from tiereg.points import PointSet
from tiereg.reference import MAX_BASE_SIDE, prepare_reference
from tiereg.simulate import (
    HiddenTransform,
    ImageBlock,
    LidarSurvey,
    SceneSpec,
    make_scene,
    make_world,
)


def _reference(extent_m: float, n: int = 20_000, seed: int = 0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, extent_m, (n, 2)) + (500_000.0, 5_000_000.0)
    z = 100 + 10 * np.sin(xy[:, 0] / 97.0) + rng.normal(0, 0.1, n)
    return prepare_reference(ArraySource(PointSet(np.column_stack([xy, z]))))


@pytest.mark.parametrize("scale", [1e-3, 0.03, 1.0, 40.0, 1e3])
def test_the_scale_range_holds_a_block_in_any_gauge(scale):
    """A block a third of the reference's width, in model units of any size: the true scale
    (reference units per model unit) lies inside the range, well away from its edges."""
    ref = _reference(3000.0)
    rng = np.random.default_rng(1)
    block_m = rng.uniform(-500, 500, (2000, 3))  # 1 km in reference units
    moving = block_m / scale  # model units: ``scale`` reference units each
    scales = ScaleRange.of(moving, ref, tie_cell_for(moving))
    assert scales.lowest < scale < scales.highest
    assert not scales.at_edge(scale)
    # the range spans the same few octaves whatever the gauge
    assert math.log2(scales.highest / scales.lowest) == pytest.approx(
        math.log2(ScaleRange.of(block_m, ref, tie_cell_for(block_m)).highest
                  / ScaleRange.of(block_m, ref, tie_cell_for(block_m)).lowest), abs=0.5)


def test_the_lattice_keeps_its_steps_and_the_edges_are_a_step_wide():
    scales = ScaleRange(0.2, 5.0)
    lattice = scales.lattice(SCALE_STEP)
    np.testing.assert_allclose(np.log(lattice) / np.log(SCALE_STEP),
                               np.round(np.log(lattice) / np.log(SCALE_STEP)), atol=1e-9)
    assert 0.25 in np.round(lattice, 12) and 4.0 in np.round(lattice, 12)
    assert lattice[0] >= 0.2 and lattice[-1] <= 5.0
    assert scales.lattice(SCALE_STEP, level=2)[0] < 0.2  # a coarser level scores finer scales
    assert scales.at_edge(0.21) and scales.at_edge(4.9) and not scales.at_edge(1.0)


def test_the_base_grid_is_bounded_whatever_the_reference_or_the_request():
    wide = _reference(200_000.0)  # 200 km, sparse: the bound sets the cell
    assert max(wide.base.spec.shape) <= MAX_BASE_SIDE + 2
    asked = prepare_reference(wide.source, base_cell=0.01)  # centimetres asked for
    assert max(asked.base.spec.shape) <= MAX_BASE_SIDE + 2
    dense = _reference(300.0, n=200_000)  # 2.2 points per m2: the spacing sets the cell
    assert dense.base_cell == pytest.approx(1.25 * math.sqrt(300.0**2 / 200_000), rel=0.05)


def test_tie_grids_are_bounded_for_dense_models():
    rng = np.random.default_rng(2)
    dense = rng.uniform(0, 1000, (400_000, 3))
    cell = tie_cell_for(dense)
    assert 1000 / cell <= 1.2 * 256  # about MAX_TIE_SIDE cells a side, not 1,600


@pytest.fixture(scope="module")
def suburb_world():
    return make_world("suburban", size_m=3000.0, seed=5)


@pytest.mark.slow
@pytest.mark.parametrize("model_per_metre", [0.02, 80.0], ids=["scale50", "scale1/80"])
def test_a_model_in_a_far_gauge_registers(suburb_world, model_per_metre):
    """COLMAP puts models at tens to hundreds of reference units per model unit (and a model in
    millimetres the other way): found without being told, coarse stage only."""
    spec = SceneSpec(kind="suburban", seed=5, world_size_m=3000.0, lidar_size_m=2000.0,
                     block=ImageBlock(side_m=1200.0), survey=LidarSurvey(density_per_m2=0.5),
                     overlap=0.9, hidden=HiddenTransform(heading_deg=73.0, scale=model_per_metre))
    scene = make_scene(spec, world=suburb_world)
    result = register(scene.moving, scene.lidar.xyz, fine="none", level="none")
    est, true = result.T_ref_mov.parameters(), scene.T_ref_mov.parameters()
    assert result.confident, result.reasons
    assert abs((math.degrees(est.kappa - true.kappa) + 180) % 360 - 180) < 2.0  # degrees
    assert est.scale / true.scale == pytest.approx(1.0, abs=0.02)
    centre = scene.moving.mean(axis=0, keepdims=True)
    err = result.T_ref_mov.apply(centre) - scene.T_ref_mov.apply(centre)
    assert np.hypot(*err[0, :2]) < result.cell_size  # within a coarse cell (reference units)


@pytest.mark.slow
def test_a_block_too_small_for_the_reference_is_not_claimed(suburb_world):
    """A dense block a tenth of the reference's width, its tie cell under a 320th of it, cannot
    be told apart at the search's grid (at most MAX_REFERENCE_CELLS cells a side): the scales
    searched stop above the truth, and the answer is not confident."""
    spec = SceneSpec(kind="suburban", seed=5, world_size_m=3000.0, lidar_size_m=2800.0,
                     survey=LidarSurvey(density_per_m2=0.5))
    lidar = make_scene(spec, world=suburb_world).lidar.xyz
    centre = np.median(lidar, axis=0)
    inside = np.flatnonzero(np.all(np.abs(lidar[:, :2] - centre[:2]) < 140.0, axis=1))
    rng = np.random.default_rng(3)
    moving = lidar[rng.choice(inside, 2000, replace=False)] - centre  # 280 m, 2,000 points
    ref = prepare_reference(ArraySource(PointSet(lidar)))
    scales = ScaleRange.of(moving, ref, tie_cell_for(moving))
    assert scales.lowest > 1.0  # the premise: the true scale is finer than the grid allows
    assert 2800.0 / (MAX_REFERENCE_CELLS * tie_cell_for(moving)) == pytest.approx(
        scales.lowest, rel=0.05)
    result = register(moving, ref, fine="none", level="none")
    assert not result.confident


def test_an_answer_at_the_smallest_scale_searched_is_searched_again_with_a_coarser_tie_cell():
    """The smallest scale searched is the reference's width over MAX_REFERENCE_CELLS tie cells:
    an answer within a sweep step of it may be cut off there, so the block is searched again
    with its tie cell doubled (the smallest scale halves) while it spans MIN_TIE_SIDE cells."""
    from tiereg.stages import MIN_TIE_SIDE, coarser_tie_cell

    rng = np.random.default_rng(0)
    lidar = np.column_stack([rng.uniform(0, 2000.0, (5000, 2)), rng.normal(0, 1, 5000)])
    ref = prepare_reference(ArraySource(PointSet(lidar)))
    moving = np.column_stack([rng.uniform(0, 640.0, (4000, 2)), np.zeros(4000)])  # model units
    cell = 5.0  # 128 cells across the block
    lowest = ScaleRange.of(moving, ref, cell).lowest
    x0, y0, x1, y1 = ref.base.spec.bounds  # 2 km and the base grid's snapping
    assert lowest == pytest.approx(max(x1 - x0, y1 - y0) / (MAX_REFERENCE_CELLS * cell))
    assert coarser_tie_cell(lowest * 1.05, moving, ref, cell) == 2 * cell  # at the edge
    assert coarser_tie_cell(lowest * SCALE_STEP * 1.01, moving, ref, cell) is None  # inside
    # a block already only 2 * MIN_TIE_SIDE - 1 cells across is not gridded coarser
    narrow = 640.0 / (2 * MIN_TIE_SIDE - 1)
    edge = ScaleRange.of(moving, ref, narrow).lowest
    assert coarser_tie_cell(edge * 1.05, moving, ref, narrow) is None


def test_a_translation_search_coarsens_its_own_cell_and_refuses_a_given_one_too_fine():
    """`coarse` pomf on a dense block over a wide lidar: the tie cell (1 m) would grid the
    2 km reference at 2,000 cells a side; unasked, the grid is coarsened to the bound (320 a
    side); a `cell_size` that fine given by the caller is refused, naming the parameter."""
    from tiereg.errors import InputError
    from tiereg.stages import translation_grid

    ref = _reference(2000.0, n=400_000)  # base cell about 4 m
    block = np.column_stack([np.random.default_rng(1).uniform(0, 200, (500, 2)), np.zeros(500)])
    grid = translation_grid(ref, block, cell_size=None, tie_cell=1.0)
    least = 2000.0 / MAX_REFERENCE_CELLS
    assert least <= grid.spec.cell_size < least + ref.base_cell  # whole base cells
    assert max(grid.spec.shape) <= MAX_REFERENCE_CELLS + 2
    given = translation_grid(ref, block, cell_size=12.0, tie_cell=1.0).spec.cell_size
    assert abs(given - 12.0) <= ref.base_cell / 2
    with pytest.raises(InputError, match="cell_size 1 is too fine"):
        translation_grid(ref, block, cell_size=1.0, tie_cell=1.0)


def test_a_scale_range_given_narrows_the_search_to_it(suburb_world):
    """`scale_range` (reference units per model unit): a block at 50 is found inside
    (40, 62) as without it; told (5, 10), a range that excludes the truth, the answer is not
    confident; a range the wrong way round is refused, naming the parameter."""
    from tiereg.errors import InputError
    from tiereg.stages import searched_scales

    spec = SceneSpec(kind="suburban", seed=5, world_size_m=3000.0, lidar_size_m=2000.0,
                     block=ImageBlock(side_m=1200.0), survey=LidarSurvey(density_per_m2=0.5),
                     overlap=0.9, hidden=HiddenTransform(heading_deg=73.0, scale=0.02))
    scene = make_scene(spec, world=suburb_world)
    ref = prepare_reference(ArraySource(PointSet(scene.lidar.xyz)))
    local = scene.moving - scene.moving.mean(axis=0)
    cell = tie_cell_for(local)
    told = searched_scales(local, ref, cell, (40.0, 62.0))
    assert (told.lowest, told.highest) == (40.0, 62.0)
    assert searched_scales(local, ref, cell, (1e-6, 1e6)) == ScaleRange.of(local, ref, cell)
    inside = register(scene.moving, ref, fine="none", level="none", scale_range=(40.0, 62.0))
    assert inside.confident, inside.reasons
    assert inside.T_ref_mov.scale == pytest.approx(50.0, rel=0.02)
    outside = register(scene.moving, ref, fine="none", level="none", scale_range=(5.0, 10.0))
    assert not outside.confident
    with pytest.raises(InputError, match="`scale_range` must be two positive numbers"):
        register(scene.moving, ref, scale_range=(10.0, 5.0))
