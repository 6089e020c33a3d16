"""Making elevation grids comparable for correlation.

Sparse tie-point grids are mostly empty; empty cells must never enter an FFT as data. Each grid is
detrended on its valid cells, filled by normalized convolution, band-passed by a difference of
Gaussians and tapered at the edge of its support.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..grid import fill_normalized
from ..robust import nmad


@dataclass(frozen=True, eq=False)
class Prepared:
    """A grid ready for correlation: ``image`` (0 outside ``support``) and its ``support``."""

    image: np.ndarray
    support: np.ndarray


def detrend_plane(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Subtract the least-squares plane ``z = a + b*row + c*col`` fitted to the valid cells.

    ``values`` and ``mask`` are ``(..., rows, cols)``: each image of a stack gets its own plane.
    Images with fewer than 3 valid cells come back as zeros.
    """
    mask = np.asarray(mask, bool)
    values = np.where(mask, values, 0.0).astype(np.float64)
    rows, cols = values.shape[-2:]
    # row and column about the image centre keep the normal equations well conditioned
    r = (np.arange(rows, dtype=np.float64) - 0.5 * (rows - 1))[:, None]
    c = (np.arange(cols, dtype=np.float64) - 0.5 * (cols - 1))[None, :]
    m = mask.astype(np.float64)
    # the normal equations from row and column sums: sums of m, m r, m c, m r^2, m r c, m c^2
    # and of z, z r, z c over the valid cells
    m_rows, m_cols, z_rows = m.sum(axis=-1), m.sum(axis=-2), values.sum(axis=-1)
    r1, c1 = r[:, 0], c[0, :]
    s0, sr, sc = m_rows.sum(axis=-1), m_rows @ r1, m_cols @ c1
    srr, scc, src = m_rows @ r1**2, m_cols @ c1**2, (m @ c1) @ r1
    AtA = np.stack([np.stack([s0, sr, sc], -1), np.stack([sr, srr, src], -1),
                    np.stack([sc, src, scc], -1)], -2)
    Atz = np.stack([z_rows.sum(axis=-1), z_rows @ r1, values.sum(axis=-2) @ c1], -1)
    # the pseudo-inverse gives lstsq's minimum-norm plane when the valid cells are collinear
    coef = np.einsum("...ij,...j->...i", np.linalg.pinv(AtA), Atz)
    plane = (coef[..., 0, None, None] + coef[..., 1, None, None] * r
             + coef[..., 2, None, None] * c)
    enough = (s0 >= 3)[..., None, None]
    return np.where(mask & enough, values - plane, 0.0)


def prepare(
    values: np.ndarray,
    mask: np.ndarray,
    *,
    fill_sigma_cells: float = 1.0,
    bandpass_sigma_cells: float = 4.0,
    clip_nmad: float = 0.0,
    within: np.ndarray | None = None,
) -> Prepared:
    """Detrend, fill (normalized convolution), band-pass (DoG) and zero outside the support.

    ``clip_nmad > 0`` clips the band-passed values at that many NMADs of the support's values
    (winsorizing): then every object counts by where it stands, not by how tall it is, and a
    few tall ones cannot outweigh the many that agree. ``within``: the cells the support may
    cover (the filling does not reach past them), as if the grid ended there. ``values`` and
    ``mask`` may be stacks ``(..., rows, cols)``; each image is prepared on its own, as if alone.
    """
    mask = np.asarray(mask, bool) & np.isfinite(values)
    flat = detrend_plane(values, mask)
    filled, support = fill_normalized(flat, mask, sigma_cells=fill_sigma_cells)
    if within is not None:
        support &= np.asarray(within, bool)
        filled = np.where(support, filled, 0.0)
    if bandpass_sigma_cells > 0:
        low, _ = fill_normalized(filled, support, sigma_cells=bandpass_sigma_cells,
                                 min_support=0.0)
        image = filled - low
    else:
        image = filled
    n_support = support.sum(axis=(-2, -1), keepdims=True)
    cross = ndimage.generate_binary_structure(2, 1).reshape((1,) * (support.ndim - 2) + (3, 3))
    support = np.where(n_support > 50, ndimage.binary_opening(support, cross), support)
    image = np.where(support, image, 0.0)
    if clip_nmad > 0:
        images, supports = image.reshape(-1, *image.shape[-2:]), support.reshape(
            -1, *support.shape[-2:])
        bound = np.array([clip_nmad * nmad(one[sup]) if sup.sum() > 10 else np.inf
                          for one, sup in zip(images, supports)])
        bound = bound.reshape(image.shape[:-2] + (1, 1))
        image = np.clip(image, -bound, bound)
    return Prepared(image, support)
