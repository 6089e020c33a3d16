"""Heading from the second moments of the grids' spectra: a quick initialiser (``moments``).

The principal axes of a grid's own footprint or heights say where its mass is, which depends on
what part of the ground each data set covers; those of its power spectrum do not: the spectrum
ignores translation, and a street grid, field pattern or ridge direction puts its energy along
fixed directions wherever the block lies. Per-radius whitening (each ring of frequencies divided
by its mean power, as in the robust Fourier-Mellin methods) makes every scale count alike, and the
orientation tensor of the whitened spectrum,

    T = sum_k w(k) k^ k^T / sum_k w(k),   k^ = k / |k|,

has its major axis at ``phi = atan2(2 T_xy, T_xx - T_yy) / 2`` (map coordinates, modulo 180 deg;
Bigun & Granlund 1987 for the orientation tensor, here of the spectrum). Turning the tie points
by ``kappa`` turns their spectrum by ``kappa``, so ``kappa = phi_ref - phi_mov`` up to 180 deg.
The spectrum's second moments carry no usable scale (terrain spectra are close to power laws), so
scale is a one-dimensional scan. About 130 hypotheses (both senses, up to 15 deg around each, as
the orientations are good to about 10 deg; scales a third of an octave apart) are scored by
masked NCC and the best refined, against about a thousand in the full sweep. Where neither
spectrum has a dominant direction (``anisotropy`` near 0: hills, forest) the heading is a guess,
and the answer's confidence says so: like the frequency-domain methods, ``moments`` is confident
only when its pose explains the heights.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import fft

from ..grid import GridSpec, rasterize
from ..reference import Reference
from .fourier_mellin import taper
from .preprocess import Prepared, prepare
from .result import Moments
from .scoring import ScaleRange, Scorer
from .search import HeightCheck, SearchResult, verify_candidates

REFERENCE_CELLS = 256  # per side of the reference grid whose spectrum is taken
KAPPA_OFFSETS_DEG = (-15.0, -7.5, 0.0, 7.5, 15.0)  # the orientations are good to about 10 deg
SCALE_RATIO = 2 ** (1 / 3)


@dataclass(frozen=True)
class Orientation:
    """The major axis of a spectrum's orientation tensor (map coordinates)."""

    phi: float  # radians, modulo pi
    anisotropy: float  # (l1 - l2) / (l1 + l2) of the tensor: 0 isotropic, 1 one direction


def spectral_orientation(p: Prepared, *, excess: float = 1.0) -> Orientation:
    """The orientation of a prepared grid's whitened power spectrum (module docstring).

    Each frequency weighs by how far its power exceeds ``excess`` times its ring's mean. A higher
    ``excess`` finds clean stripes to a fraction of a degree (5: 0.5 deg, against 4 deg at 1 with
    noise), but on sparse tie-point grids it follows the lattice's own peaks: on four simulated
    blocks it found no heading at 5 and two at 1.
    """
    img = taper(p)
    n = 1 << math.ceil(math.log2(2 * max(img.shape)))
    power = np.abs(fft.fftshift(fft.fft2(img, s=(n, n)))) ** 2
    f = np.arange(n) - n // 2
    kx = np.broadcast_to(f[None, :], (n, n)).astype(np.float64)
    ky = -np.broadcast_to(f[:, None], (n, n)).astype(np.float64)  # rows run southwards
    r = np.hypot(kx, ky)
    ring = np.rint(r).astype(int)
    band = (r >= 3.0) & (r <= n / 4)
    mean = np.bincount(ring[band], weights=power[band], minlength=ring.max() + 1)
    count = np.bincount(ring[band], minlength=ring.max() + 1)
    ring_mean = mean / np.maximum(count, 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(band, np.maximum(power / ring_mean[ring] - excess, 0.0), 0.0)
    w = np.nan_to_num(w)
    ux, uy = kx / np.maximum(r, 1e-12), ky / np.maximum(r, 1e-12)
    txx, tyy, txy = (np.sum(w * ux * ux), np.sum(w * uy * uy), np.sum(w * ux * uy))
    total = max(txx + tyy, 1e-300)
    phi = 0.5 * math.atan2(2 * txy, txx - tyy)
    return Orientation(phi, float(math.hypot(txx - tyy, 2 * txy) / total))


def moments_search(
    moving: np.ndarray,
    ref: Reference,
    *,
    tie_cell: float,
    scales: ScaleRange | None = None,
    heights: HeightCheck | None = None,
) -> tuple[SearchResult, Moments]:
    """Candidates from the spectra's orientations and a scale scan, verified and refined;
    ``moving`` is local (centred) model coordinates; ``heights`` as in
    :func:`~tiereg.coarse.search.verify_candidates`. Returns the result and what the
    orientations were (evidence of the coarse stage)."""
    lo, hi = moving[:, :2].min(axis=0), moving[:, :2].max(axis=0)
    mgrid = rasterize(moving, GridSpec.from_bounds(lo[0], lo[1], hi[0], hi[1], tie_cell),
                      stats=("median",))
    mov = prepare(mgrid["median"], mgrid.mask, bandpass_sigma_cells=6.0)
    (x0, y0, x1, y1) = ref.base.spec.bounds
    grid = ref.grid(max(ref.base_cell, max(x1 - x0, y1 - y0) / REFERENCE_CELLS))
    o_mov = spectral_orientation(mov)
    o_ref = spectral_orientation(prepare(grid["mean"], grid.mask, bandpass_sigma_cells=6.0))
    kappa0 = o_ref.phi - o_mov.phi
    kappas = [kappa0 + turn + math.radians(d) for turn in (0.0, math.pi)
              for d in KAPPA_OFFSETS_DEG]
    scales = scales or ScaleRange.of(moving, ref, tie_cell)
    sigmas = scales.lattice(SCALE_RATIO, level=2)
    scorer = Scorer(moving, ref, tie_cell, 2)
    hyps = [h for k in kappas for s in sigmas if (h := scorer.score(k, float(s))) is not None]
    found = verify_candidates(moving, ref, hyps, tie_cell=tie_cell, keep=4,
                              log_sigma=math.log(SCALE_RATIO),
                              n_tried=len(kappas) * len(sigmas), scales=scales,
                              heights=heights)
    return found, Moments(math.degrees(kappa0) % 180.0, o_mov.anisotropy, o_ref.anisotropy)
