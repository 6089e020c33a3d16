"""Fourier-Mellin candidates on dense images with a known rotation and scale."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from tiereg.coarse.fourier_mellin import polar_map, rotation_scale_candidates
from tiereg.coarse.preprocess import Prepared


def _pair(theta_deg: float, a: float, rng) -> tuple[Prepared, Prepared]:
    """``ref`` and ``mov``: the moving image is the reference turned by ``theta``, scaled by
    ``a`` about the centres (row, col coordinates)."""
    ref = ndimage.gaussian_filter(rng.normal(size=(160, 160)), 3)
    th = math.radians(theta_deg)
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    rr, cc = np.indices((120, 120)).astype(float)
    p = np.stack([rr - 59.5, cc - 59.5])
    q = np.tensordot(np.linalg.inv(a * R), p, axes=1)
    mov = ndimage.map_coordinates(ref, [q[0] + 79.5, q[1] + 79.5], order=1)

    def prep(im):
        return Prepared(im - im.mean(), np.ones_like(im, bool))

    return prep(ref), prep(mov)


@pytest.mark.parametrize("method", ["fmt", "afmt", "qafmt"])
@pytest.mark.parametrize("theta_deg, a", [(30.0, 1.0), (0.0, 1.3), (40.0, 0.8)])
def test_robust_variants_find_rotation_and_scale(method, theta_deg, a):
    ref, mov = _pair(theta_deg, a, np.random.default_rng(0))
    cands = rotation_scale_candidates(ref, mov, method=method, robust=True)
    # the candidate maps moving to reference: the inverse turn and scale, or its 180 deg twin
    def off_deg(c):  # angular distance of the candidate from -theta, modulo 180 deg
        d = (math.degrees(c.theta) + theta_deg) % 180.0
        return min(d, 180.0 - d)

    found = [c for c in cands[:2] if off_deg(c) < 1.0]
    assert found, [(math.degrees(c.theta), c.scale) for c in cands[:2]]
    # bins: 0.5 deg in angle; log-polar scale bins of ~3.3 %
    assert found[0].scale == pytest.approx(1 / a, rel=0.05)


def test_every_peak_comes_with_its_180_degree_twin():
    ref, mov = _pair(25.0, 1.0, np.random.default_rng(1))
    cands = rotation_scale_candidates(ref, mov, method="qafmt", robust=True, k=3)
    assert len(cands) == 6
    for a, b in zip(cands[::2], cands[1::2]):
        assert b.theta - a.theta == pytest.approx(math.pi) and a.scale == b.scale


def test_quasi_log_map_is_linear_near_the_centre_and_log_far_out():
    mag = np.ones((256, 256))
    lp, step = polar_map(mag, radial="quasi")
    assert lp.shape == (360, 128) and step > 0
    rho = np.arange(128) * step
    r = 3.0 * np.sinh(rho)
    assert r[0] == 0.0  # starts at the centre
    assert np.log(r[-1]) - np.log(r[-2]) == pytest.approx(step, rel=0.02)  # log spacing far out
