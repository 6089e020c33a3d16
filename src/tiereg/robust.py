"""Robust statistics and weights: one home for the M-estimators used across tiereg.

References: Tukey's biweight (Beaton & Tukey 1974); the normalized median absolute
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


def tukey_loss(residuals: np.ndarray, scale: float, *, c: float = 4.685) -> np.ndarray:
    """Tukey's biweight loss ``(c^2/6)(1 - (1 - (r/(c*scale))^2)^3)``, bounded at ``c^2/6``:
    a blunder costs a constant."""
    a = np.clip(np.abs(residuals) / (c * np.maximum(scale, 1e-12)), 0.0, 1.0)
    return (c**2 / 6.0) * (1.0 - (1.0 - a**2) ** 3)
