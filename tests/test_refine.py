"""The surface sampler and the robust surface fit of the coarse stage."""

import math

import numpy as np
from scipy import ndimage

from tiereg.coarse.refine import fit_to_surface
from tiereg.grid import Grid, GridSpec
from tiereg.surface import SurfaceSampler


def _grid(rng, shape=(50, 60), cell=2.0, holes=0.1):
    count = (rng.random(shape) > holes).astype(np.int64)
    values = np.where(count > 0, rng.normal(size=shape), np.nan)
    return Grid(GridSpec(100.0, 200.0, cell, shape), count, {"mean": values}, None)


def test_sampler_matches_scipy_bilinear_and_nearest_validity():
    rng = np.random.default_rng(0)
    grid = _grid(rng)
    sampler = SurfaceSampler.from_grid(grid)
    x, y = rng.uniform(95, 230, 5000), rng.uniform(95, 205, 5000)
    z, ok = sampler.sample(x, y)
    rows, cols = grid.spec.rowcol(x, y)
    coords = np.vstack([rows, cols])
    z_ref = ndimage.map_coordinates(sampler.values, coords, order=1, mode="nearest")
    inside = (rows >= 0) & (rows <= 49) & (cols >= 0) & (cols <= 59)
    ok_ref = inside & (ndimage.map_coordinates(sampler.valid.astype(float), coords, order=0,
                                               mode="constant") > 0.5)
    assert np.abs(z - z_ref)[inside].max() < 1e-12
    assert np.array_equal(ok, ok_ref)
    assert 0.5 < ok.mean() < 0.9  # the test covers both answers


def test_fit_recovers_a_known_scale_and_shift_from_either_side():
    # a smooth surface (metres) and points on it; the fit must not favour shrinking the block
    shape, cell = (400, 400), 2.0
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]] * cell
    surface = 8 * np.sin(xx / 90.0) * np.cos(yy / 70.0) + 3 * np.sin((xx + yy) / 37.0)
    grid = Grid(GridSpec(0.0, shape[0] * cell, cell, shape), np.ones(shape, np.int64),
                {"mean": surface}, None)
    sampler = SurfaceSampler.from_grid(grid)
    rng = np.random.default_rng(1)
    # the block reaches beyond the surface on all sides (partial overlap)
    p = rng.uniform(-450, 450, (3000, 2))  # model units, centred; truth: scale 1.1, shift 400
    centre = np.array([400.0, 400.0])
    q = 1.1 * p + centre
    rows, cols = grid.spec.rowcol(q[:, 0], q[:, 1])
    z = ndimage.map_coordinates(surface, np.vstack([rows, cols]), order=1, mode="nearest")
    xyz = np.column_stack([p, z / 1.1])  # heights in model units too

    def place(params):
        s = math.exp(params[0])
        return np.column_stack([s * p + params[1:3], s * xyz[:, 2]])

    for start in (1.04, 1.16):  # a few per cent small, a few per cent large
        fit = fit_to_surface(place, sampler, np.array([math.log(start), 405.0, 396.0]),
                             np.array([math.log(1.01), 1.0, 1.0]))
        assert fit.converged
        assert abs(math.exp(fit.params[0]) / 1.1 - 1) < 0.002
        assert np.hypot(*(fit.params[1:3] - centre)) < 0.5  # metres, a quarter cell
