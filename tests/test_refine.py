"""The surface sampler and the robust surface fit of the coarse stage."""

import math

import numpy as np
import pytest
from scipy import ndimage

from tiereg.coarse.refine import EDGE_MARGIN_CELLS, MIN_KEPT, fit_to_surface, fit_to_surface_many
from tiereg.grid import Grid, GridSpec
from tiereg.robust import nmad, tukey_loss
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


def test_roughness_is_half_the_range_of_the_nearest_cells_neighbourhood():
    rng = np.random.default_rng(3)
    sampler = SurfaceSampler.from_grid(_grid(rng, shape=(12, 15)))
    x, y = rng.uniform(95, 135, 400), rng.uniform(172, 205, 400)
    got = sampler.roughness(x, y)
    rows, cols = sampler.grid.spec.rowcol(x, y)
    v = sampler.values
    for k in range(len(x)):  # the slow, obvious reference: the 3 x 3 cells, clamped at edges
        r = min(max(int(round(rows[k])), 0), v.shape[0] - 1)
        c = min(max(int(round(cols[k])), 0), v.shape[1] - 1)
        block = v[max(r - 1, 0):r + 2, max(c - 1, 0):c + 2]
        assert got[k] == pytest.approx(0.5 * (block.max() - block.min()), abs=1e-12)


def _smooth_block(rng, shape=(400, 400), cell=2.0, n_points=3000):
    """A smooth surface (metres) and ``n_points`` points on it, scaled 1.1 and shifted by 400 m;
    the block reaches beyond the surface on all sides (partial overlap)."""
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]] * cell
    surface = 8 * np.sin(xx / 90.0) * np.cos(yy / 70.0) + 3 * np.sin((xx + yy) / 37.0)
    grid = Grid(GridSpec(0.0, shape[0] * cell, cell, shape), np.ones(shape, np.int64),
                {"mean": surface}, None)
    sampler = SurfaceSampler.from_grid(grid)
    p = rng.uniform(-450, 450, (n_points, 2))  # model units, centred
    q = 1.1 * p + 400.0
    rows, cols = grid.spec.rowcol(q[:, 0], q[:, 1])
    z = ndimage.map_coordinates(surface, np.vstack([rows, cols]), order=1, mode="nearest")
    z = z + rng.normal(0, 0.3, len(z))  # heights in model units too, with noise

    def place(params):  # (K, 3) -> (K, N, 3)
        s = np.exp(params[:, 0])[:, None, None]
        return np.concatenate([s * p + params[:, None, 1:3], s * z[:, None] / 1.1], axis=2)

    return sampler, place


def test_fit_recovers_a_known_scale_and_shift_from_either_side():
    # the fit must not favour shrinking the block
    sampler, place = _smooth_block(np.random.default_rng(1))
    for start in (1.04, 1.16):  # a few per cent small, a few per cent large
        fit = fit_to_surface(place, sampler, np.array([math.log(start), 405.0, 396.0]),
                             np.array([math.log(1.01), 1.0, 1.0]))
        assert fit.converged
        assert abs(math.exp(fit.params[0]) / 1.1 - 1) < 0.002
        assert np.hypot(*(fit.params[1:3] - 400.0)) < 0.5  # metres, a quarter cell


def _compass_one_call_at_a_time(place, sampler, p, steps, stop):
    """The slow, obvious compass search: one loss evaluation per call (the reference)."""
    inner = sampler.inner(EDGE_MARGIN_CELLS)

    def residuals(params):
        pts = place(params[None])[0]
        z, deep = sampler.sample(pts[:, 0], pts[:, 1], within=inner)
        return z - pts[:, 2], deep

    r0, use = residuals(p)
    n0, scale = use.sum(), nmad(r0[use])

    def loss(params):
        r, good = residuals(params)
        if good.sum() < max(10, MIN_KEPT * n0):
            return np.inf
        return tukey_loss(r[good] - np.median(r[good]), scale).mean()

    best = loss(p)
    while np.any(steps >= stop):
        moved = False
        for i in np.flatnonzero(steps >= stop):
            for sign in (1.0, -1.0):
                trial = p.copy()
                trial[i] += sign * steps[i]
                if (value := loss(trial)) < best:
                    p, best, moved = trial, value, True
                    break
        if not moved:
            steps = steps / 2
    return p


@pytest.mark.parametrize("n_points", [3000, 300])
def test_fits_in_lock_step_are_the_fits_one_at_a_time(n_points):
    sampler, place = _smooth_block(np.random.default_rng(2), n_points=n_points)
    steps = np.array([math.log(1.01), 1.0, 1.0])
    starts = [np.array([math.log(s), 400.0 + dx, 400.0 - dx])
              for s, dx in ((1.0, 6.0), (1.15, -3.0), (1.05, 0.0), (0.97, 9.0))]
    starts.append(np.array([0.0, 3000.0, 3000.0]))  # off the surface: no points, no fit
    fits = fit_to_surface_many(place, sampler, starts, steps, tol_fraction=1 / 64)
    for start, fit in zip(starts[:-1], fits):
        alone = _compass_one_call_at_a_time(place, sampler, start.copy(), steps.copy(),
                                            steps / 64)
        assert fit.converged and fit.iterations > 3
        assert np.allclose(fit.params, alone, rtol=0, atol=1e-9)
    # all found the truth, to about what that many points with 0.3 m of noise tell
    assert all(abs(math.exp(f.params[0]) / 1.1 - 1) < 0.05 / math.sqrt(n_points)
               for f in fits[:-1])
    assert fits[-1].n_used == 0 and not fits[-1].converged and np.isnan(fits[-1].sigma0)
