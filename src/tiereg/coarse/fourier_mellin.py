"""Rotation and scale from Fourier magnitudes: FMT, AFMT and QAFMT, classic and robust.

The magnitude of a grid's Fourier transform ignores translation. If the moving grid is the
reference turned by ``theta`` and scaled by ``a``, ``|F_m|(r, phi) = a^-2 |F_r|(r / a, phi -
theta)`` (Reddy & Chatterji 1996, IEEE TIP 5(8)), so in log-polar coordinates ``(ln r, phi)``
rotation and scale become a shift, found by correlating the two maps.

- ``fmt`` (classic): log-polar magnitude with the Reddy-Chatterji high-pass
  ``H = (1 - X)(2 - X), X = cos(pi xi) cos(pi eta)``, phase correlation (POMF) of the maps.
- ``afmt``: the analytical Fourier-Mellin transform (Ghorbel 1994; Derrode & Ghorbel 2001) of the
  magnitude, ``M(k, v) = int int f(r, phi) r^(sigma - iv) e^(-ik phi) dphi dr/r``. Its phase
  carries ``(v ln a + k theta)``, so its registration is the phase correlation of the log-polar
  map weighted by ``e^(sigma rho)``; ``sigma = 0.5``.
- ``qafmt``: AFMT on a quasi-log-polar grid, ``rho = asinh(r / r0)``: linear near the centre,
  logarithmic further out, which removes the oversampled centre pixels of the log-polar grid
  (reading (B) of the note; scale is a shift of ``ln a`` wherever ``r >> r0``). The
  pseudo-polar construction (reading (A)) is not implemented.

Each takes a ``robust`` flag: mask-aware fill, band-pass and a circular taper on both grids, and
per-radius whitening with plain (amplitude) correlation of the maps, the changes that make the
method work on sparse grids (note, section 3.8). Every peak is returned with its 180 deg twin;
the caller verifies them against the lidar.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import fft, ndimage

from .correlation import local_maxima
from .preprocess import Prepared

N_THETA = 360  # over [0, pi)
N_RHO = 128
AFMT_SIGMA = 0.5
QUASI_R0 = 3.0  # frequency bins


@dataclass(frozen=True)
class RotationScale:
    """A candidate map from moving to reference pixels: turn by ``theta`` (radians, in the
    (row, col) plane, which is the same angle in map coordinates), scale by ``scale``; with the
    correlation ``peak`` that proposed it."""

    theta: float
    scale: float
    peak: float


def taper(p: Prepared) -> np.ndarray:
    """Circular Hann window over the support, centred on it (no 0/90 deg edge streaks)."""
    rows, cols = np.nonzero(p.support)
    if len(rows) == 0:
        return p.image
    cr, cc = rows.mean(), cols.mean()
    radius = max(np.hypot(rows - cr, cols - cc).max(), 1.0)
    rr, cc_ = np.indices(p.image.shape)
    d = np.hypot(rr - cr, cc_ - cc) / radius
    window = np.where(d < 1, 0.5 * (1 + np.cos(np.pi * d)), 0.0)
    soft = ndimage.gaussian_filter(p.support.astype(float), 1.0)
    img = p.image - np.average(p.image, weights=np.maximum(soft * window, 1e-12))
    return img * window * soft


def _magnitude(image: np.ndarray, n: int, *, highpass: bool) -> np.ndarray:
    f = np.abs(fft.fftshift(fft.fft2(image, s=(n, n))))
    if highpass:  # Reddy & Chatterji (1996), eqs. 23-24
        xi = np.linspace(-0.5, 0.5, n)
        x = np.cos(np.pi * xi)[:, None] * np.cos(np.pi * xi)[None, :]
        f = f * (1.0 - x) * (2.0 - x)
    return f


def polar_map(mag: np.ndarray, *, radial: str) -> tuple[np.ndarray, float]:
    """Resample a centred magnitude on ``N_THETA x N_RHO``; returns the map and the rho step.

    ``radial="log"``: ``r = r_min * exp(j * step)``; ``"quasi"``: ``r = r0 * sinh(rho)``.
    """
    n = mag.shape[0]
    r_min, r_max = 3.0, n / 4
    if radial == "log":
        rho = np.linspace(math.log(r_min), math.log(r_max), N_RHO)
        r = np.exp(rho)
    else:
        rho = np.linspace(0.0, math.asinh(r_max / QUASI_R0), N_RHO)
        r = QUASI_R0 * np.sinh(rho)
    theta = np.arange(N_THETA) * math.pi / N_THETA
    rows = n / 2 + r[None, :] * np.sin(theta)[:, None]
    cols = n / 2 + r[None, :] * np.cos(theta)[:, None]
    out = ndimage.map_coordinates(mag, [rows, cols], order=1, mode="constant")
    return out, float(rho[1] - rho[0])


def _correlate_maps(a: np.ndarray, b: np.ndarray, *, phase: bool) -> np.ndarray:
    """Correlation of two (theta, rho) maps: periodic in theta, zero-padded in rho."""
    shape = (a.shape[0], 2 * a.shape[1])
    fa, fb = fft.fft2(a, s=shape), fft.fft2(b, s=shape)
    cross = fa * np.conj(fb)
    if phase:
        cross /= np.maximum(np.abs(cross), 1e-12)
    c = np.real(fft.ifft2(cross))
    return fft.fftshift(c, axes=1)


def rotation_scale_candidates(
    reference: Prepared,
    moving: Prepared,
    *,
    method: str,
    robust: bool,
    k: int = 6,
) -> list[RotationScale]:
    """Top-``k`` (theta, scale) peaks of ``method`` in {"fmt", "afmt", "qafmt"}, with twins."""
    n = 1 << int(math.ceil(math.log2(2 * max(*reference.image.shape, *moving.image.shape))))
    if robust:
        imgs = [taper(reference), taper(moving)]
    else:  # classic: the (filled) heights as they are, DC removed
        imgs = [np.where(p.support, p.image - p.image[p.support].mean(), 0.0)
                for p in (reference, moving)]
    mags = [_magnitude(img, n, highpass=not robust) for img in imgs]
    radial = "quasi" if method == "qafmt" else "log"
    maps = []
    for m in mags:
        lp, step = polar_map(m, radial=radial)
        if method in ("afmt", "qafmt"):  # analytical FMT weighting r^sigma = e^(sigma rho)
            rho = np.arange(lp.shape[1]) * step
            lp = lp * np.exp(AFMT_SIGMA * rho)[None, :]
        if robust:  # per-radius whitening: the angular modulation carries the heading
            lp = lp / np.maximum(lp.mean(axis=0, keepdims=True), 1e-12) - 1.0
        maps.append(lp)
    surface = _correlate_maps(maps[1], maps[0], phase=not robust)
    peaks = local_maxima(surface, k=k if robust else 1, exclusion=3)
    out: list[RotationScale] = []
    half = surface.shape[1] // 2
    for i, j in peaks:
        theta = (i if i <= N_THETA // 2 else i - N_THETA) * math.pi / N_THETA
        scale = math.exp((j - half) * step)
        for t in (theta, theta + math.pi):  # the magnitude cannot tell theta from theta + pi
            out.append(RotationScale(t, scale, float(surface[i, j])))
    return out
