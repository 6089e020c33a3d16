"""Making grids comparable: clipping keeps every value within its bound and leaves the rest."""

from __future__ import annotations

import numpy as np
import pytest

from tiereg.coarse.preprocess import prepare
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
