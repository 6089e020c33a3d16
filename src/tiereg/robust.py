"""Robust statistics and weights: one home for the M-estimators used across tiereg.

References: Huber (1964); Tukey's biweight (Beaton & Tukey 1974); the normalized median absolute
deviation ``NMAD = 1.4826 * median(|r - median(r)|)`` (Hoehle & Hoehle 2009).
"""

from __future__ import annotations

import numpy as np

NMAD_FACTOR = 1.4826


def nmad(values: np.ndarray) -> float:
    """Normalized median absolute deviation; a robust standard deviation."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return float("nan")
    return float(NMAD_FACTOR * np.median(np.abs(v - np.median(v))))


def huber_weights(residuals: np.ndarray, scale: float, *, k: float = 1.345) -> np.ndarray:
    """Huber weights ``min(1, k*scale/|r|)``."""
    a = np.abs(residuals) / max(scale, 1e-12)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))


def tukey_weights(residuals: np.ndarray, scale: float, *, c: float = 4.685) -> np.ndarray:
    """Tukey biweight ``(1 - (r/(c*scale))^2)^2`` inside ``c*scale``, 0 outside."""
    a = np.abs(residuals) / max(scale, 1e-12) / c
    return np.where(a < 1.0, (1.0 - a**2) ** 2, 0.0)
