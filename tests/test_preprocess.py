"""Making grids comparable: clipping keeps every value within its bound and leaves the rest."""

from __future__ import annotations

import numpy as np
import pytest

from tiereg.coarse.preprocess import detrend_plane, prepare
from tiereg.robust import nmad


def test_clipping_bounds_the_values_at_nmads_and_leaves_the_others(rng):
    z = rng.normal(size=(80, 80))
    z[30:33, 40:43] += 40.0  # one tall object
    mask = rng.random(z.shape) < 0.7
    plain = prepare(z, mask, bandpass_sigma_cells=4.0)
    clipped = prepare(z, mask, bandpass_sigma_cells=4.0, clip_nmad=1.5)
    bound = 1.5 * nmad(plain.image[plain.support])
    assert np.array_equal(clipped.support, plain.support)
    assert np.abs(clipped.image).max() == pytest.approx(bound)
    within = np.abs(plain.image) <= bound
    assert np.array_equal(clipped.image[within], plain.image[within])
    assert plain.image[31, 41] > 10 * bound  # the object stood out before, now by the bound only
    assert clipped.image[31, 41] == pytest.approx(bound)
    assert not clipped.image[~clipped.support].any()


def test_detrend_removes_the_least_squares_plane_of_the_valid_cells(rng):
    rows, cols = np.indices((30, 40))
    z = 5.0 + 0.3 * rows - 0.7 * cols + rng.normal(size=rows.shape)
    mask = rng.random(z.shape) < 0.4
    out = detrend_plane(z, mask)
    a = np.column_stack([np.ones(mask.sum()), rows[mask], cols[mask]])
    coef, *_ = np.linalg.lstsq(a, z[mask], rcond=None)  # the slow, obvious fit
    assert np.allclose(out[mask], z[mask] - a @ coef, atol=1e-9)
    assert not out[~mask].any()
    line = np.zeros(z.shape, bool)
    line[5, :] = True  # collinear cells: the plane along them is still the least-squares line
    flat = detrend_plane(z, line)
    fit = np.polyfit(cols[5], z[5], 1)
    assert np.allclose(flat[5], z[5] - np.polyval(fit, cols[5]), atol=1e-9)


def test_a_stack_is_prepared_image_by_image(rng):
    z = rng.normal(size=(3, 50, 60)).cumsum(axis=2)
    z[1, 20:23, 30:33] += 40.0  # an object in one image must not spill into the others
    mask = rng.random(z.shape) < 0.5
    mask[2, :45] = False  # an image with few cells (no opening of its support)
    both = prepare(z, mask, bandpass_sigma_cells=4.0, clip_nmad=1.0)
    for k in range(3):
        one = prepare(z[k], mask[k], bandpass_sigma_cells=4.0, clip_nmad=1.0)
        assert np.array_equal(both.support[k], one.support)
        assert np.allclose(both.image[k], one.image, atol=1e-9)
