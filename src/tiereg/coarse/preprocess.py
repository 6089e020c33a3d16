"""Making elevation grids comparable for correlation (algorithms note, section 2).

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
    """Subtract the least-squares plane ``z = a + b*row + c*col`` fitted to the valid cells."""
    rows, cols = np.nonzero(mask)
    out = np.zeros_like(values, dtype=np.float64)
    if len(rows) < 3:
        return out
    a = np.column_stack([np.ones(len(rows)), rows, cols]).astype(np.float64)
    z = values[rows, cols]
    coef, *_ = np.linalg.lstsq(a, z - z.mean(), rcond=None)
    rr, cc = np.indices(values.shape)
    plane = coef[0] + coef[1] * rr + coef[2] * cc + z.mean()
    out[mask] = (values - plane)[mask]
    return out


def prepare(
    values: np.ndarray,
    mask: np.ndarray,
    *,
    fill_sigma_cells: float = 1.0,
    bandpass_sigma_cells: float = 4.0,
    clip_nmad: float = 0.0,
) -> Prepared:
    """Detrend, fill (normalized convolution), band-pass (DoG) and zero outside the support.

    ``clip_nmad > 0`` clips the band-passed values at that many NMADs of the support's values
    (winsorizing): then every object counts by where it stands, not by how tall it is, and a
    few tall ones cannot outweigh the many that agree.
    """
    mask = np.asarray(mask, bool) & np.isfinite(values)
    flat = detrend_plane(np.where(mask, values, 0.0), mask)
    filled, support = fill_normalized(flat, mask, sigma_cells=fill_sigma_cells)
    if bandpass_sigma_cells > 0:
        low, _ = fill_normalized(filled, support, sigma_cells=bandpass_sigma_cells,
                                 min_support=0.0)
        image = filled - low
    else:
        image = filled
    image = np.where(support, image, 0.0)
    support = ndimage.binary_opening(support) if support.sum() > 50 else support
    image = np.where(support, image, 0.0)
    if clip_nmad > 0 and support.sum() > 10:
        bound = clip_nmad * nmad(image[support])
        image = np.where(support, np.clip(image, -bound, bound), 0.0)
    return Prepared(image, support)
