"""Grid spec conventions and chunked rasterization against slow, obvious references."""

from __future__ import annotations

import numpy as np
import pytest

from tiereg import InputError
from tiereg.grid import (
    GridAccumulator,
    GridSpec,
    cell_size_from_density,
    fill_normalized,
    rasterize,
)


def slow_stats(xyz, spec):
    """Per-cell statistics by a Python loop over cells: the obvious reference."""
    cells: dict[tuple[int, int], list[float]] = {}
    for x, y, z in xyz:
        col = int(np.floor((x - spec.x0) / spec.cell_size))
        row = int(np.floor((spec.y0 - y) / spec.cell_size))
        if 0 <= row < spec.shape[0] and 0 <= col < spec.shape[1]:
            cells.setdefault((row, col), []).append(z)
    return cells


def test_pixel_centre_convention():
    spec = GridSpec(x0=100.0, y0=200.0, cell_size=10.0, shape=(3, 4))
    x, y = spec.xy(np.array([0, 2]), np.array([0, 3]))
    assert np.allclose(x, [105.0, 135.0]) and np.allclose(y, [195.0, 175.0])
    r, c = spec.rowcol(x, y)
    assert np.allclose(r, [0, 2]) and np.allclose(c, [0, 3])
    assert spec.bounds == (100.0, 170.0, 140.0, 200.0)
    idx, inside = spec.cell_index(np.array([100.0, 139.99, 140.0]), np.array([199.9, 170.01, 180]))
    assert inside.tolist() == [True, True, False]
    assert idx[:2].tolist() == [0, 2 * 4 + 3]


def test_from_bounds_snaps_to_the_cell_lattice():
    spec = GridSpec.from_bounds(503.7, 1001.2, 611.0, 1100.0, 25.0)
    assert spec.x0 % 25.0 == 0 and spec.y0 % 25.0 == 0
    xmin, ymin, xmax, ymax = spec.bounds
    assert xmin <= 503.7 and ymin <= 1001.2 and xmax > 611.0 and ymax > 1100.0


def test_rasterize_matches_the_slow_reference(rng):
    xyz = np.column_stack([rng.uniform(0, 50, 3000), rng.uniform(0, 30, 3000),
                           rng.normal(100, 5, 3000)])
    spec = GridSpec.from_bounds(0, 0, 50, 30, 5.0)
    chunks = np.array_split(xyz, 7)  # chunked accumulation equals the whole
    grid = rasterize(iter(chunks), spec, stats=("min", "max", "mean", "median"),
                     median_sample=1000)
    ref = slow_stats(xyz, spec)
    assert int(grid.count.sum()) == sum(len(v) for v in ref.values())
    for (r, c), zs in ref.items():
        assert grid.count[r, c] == len(zs)
        assert grid["min"][r, c] == min(zs) and grid["max"][r, c] == max(zs)
        assert grid["mean"][r, c] == pytest.approx(np.mean(zs), abs=1e-9)
        assert grid["median"][r, c] == pytest.approx(np.median(zs), abs=1e-12)
    empty = grid.count == 0
    assert np.isnan(grid["mean"][empty]).all()


def test_median_sketch_is_exact_for_sparse_cells_and_close_for_full_ones(rng):
    # 400 points in one cell, 5 in another; sample of 15 per cell
    full = np.column_stack([rng.uniform(0, 1, 400), rng.uniform(0, 1, 400), rng.normal(0, 1, 400)])
    sparse = np.column_stack([rng.uniform(1, 2, 5), rng.uniform(0, 1, 5), rng.normal(0, 1, 5)])
    spec = GridSpec(0.0, 1.0, 1.0, (1, 2))
    grid = rasterize(np.vstack([full, sparse]), spec, stats=("median",), median_sample=15)
    assert grid["median"][0, 1] == np.median(sparse[:, 2])
    # the median of 15 of 400 N(0,1) values: standard error ~ 1.253/sqrt(15) = 0.32
    assert abs(grid["median"][0, 0] - np.median(full[:, 2])) < 1.3


def test_row_medians_equal_numpy(rng):
    from tiereg.grid import _row_medians

    vals = rng.normal(size=(1000, 9))
    count = rng.integers(0, 15, 1000)  # counts above 9: the sample is full
    vals[np.arange(9)[None, :] >= np.minimum(count, 9)[:, None]] = np.nan
    expected = [np.median(r[: min(c, 9)]) if c else np.nan for r, c in zip(vals, count)]
    assert np.allclose(_row_medians(vals, count), expected, equal_nan=True)


def test_median_sample_size_follows_density():
    from tiereg.grid import median_sample_for

    assert median_sample_for(0.5) == 7 and median_sample_for(2.0) == 9
    assert median_sample_for(3000.0) == 31


def test_points_outside_or_not_finite_are_ignored():
    spec = GridSpec(0.0, 10.0, 1.0, (10, 10))
    acc = GridAccumulator(spec, stats=("mean",))
    acc.add(np.array([[0.5, 9.5, 1.0], [-5.0, 5.0, 2.0], [0.5, 9.5, np.nan], [50, 50, 3.0]]))
    grid = acc.result()
    assert grid.count.sum() == 1 and grid["mean"][0, 0] == 1.0


def test_cell_size_from_density():
    # 2,500 points on a 1000 x 1000 square: spacing 20, cell sqrt(0.64) * 20 = 16 -> nice 15
    g = np.stack(np.meshgrid(np.linspace(0, 1000, 50), np.linspace(0, 1000, 50)), -1)
    xy = g.reshape(-1, 2)
    assert cell_size_from_density(xy) == 15.0
    with pytest.raises(InputError, match="line"):
        cell_size_from_density(np.column_stack([np.arange(10.0), np.arange(10.0)]))


def test_fill_normalized_reproduces_planes_and_keeps_data_where_dense():
    rows, cols = np.indices((40, 40))
    plane = 3.0 + 0.5 * rows - 0.25 * cols
    mask = np.zeros_like(plane, bool)
    mask[::2, ::2] = True  # a quarter of the cells
    filled, support = fill_normalized(np.where(mask, plane, np.nan), mask, sigma_cells=1.0)
    interior = np.zeros_like(mask)
    interior[5:-5, 5:-5] = True
    # normalized convolution is exact for linear fields away from the border
    assert np.abs(filled - plane)[interior].max() < 1e-9
    assert support[interior].all()


def test_bad_cell_size():
    with pytest.raises(InputError, match="cell size"):
        GridSpec.from_bounds(0, 0, 10, 10, 0.0)
    with pytest.raises(InputError, match="larger `cell_size`"):
        GridSpec.from_bounds(0, 0, 1e6, 1e6, 0.01)
    with pytest.raises(InputError, match="not finite"):  # was a bare ValueError of math.floor
        GridSpec.from_bounds(float("nan"), 0, 10, 10, 1.0)


def test_mask_bounds_are_the_box_of_the_true_cells_ends_exclusive():
    from tiereg.grid import mask_bounds

    mask = np.zeros((6, 8), bool)
    mask[2, 3] = mask[4, 6] = True
    assert mask_bounds(mask) == (2, 5, 3, 7)
    assert mask_bounds(np.zeros((3, 3), bool)) is None


def test_cell_points_are_the_filled_cells_centres_and_means():
    rng = np.random.default_rng(7)
    xyz = np.column_stack([rng.uniform(0, 50, 400), rng.uniform(0, 30, 400),
                           rng.normal(10, 2, 400)])
    spec = GridSpec(x0=0.0, y0=30.0, cell_size=5.0, shape=(6, 10))
    xyz = xyz[(xyz[:, 0] < 20) | (xyz[:, 1] > 15)]  # leave a quarter of the grid empty
    grid = rasterize(xyz, spec)
    expected = {(round(k[1] * 5 + 2.5, 6), round(30 - k[0] * 5 - 2.5, 6)): float(np.mean(v))
                for k, v in slow_stats(xyz, spec).items()}
    pts = grid.cell_points()
    assert len(pts) == len(expected) < spec.shape[0] * spec.shape[1]
    for x, y, z in pts:
        assert z == pytest.approx(expected[(round(x, 6), round(y, 6))], abs=1e-9)
    thinned = grid.cell_points(max_cells=10)  # every k-th of them, k = N // 10
    np.testing.assert_array_equal(thinned, pts[::len(pts) // 10])
