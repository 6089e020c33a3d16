"""Quality of a registration: height differences of the moving points against the reference.

``dz = Z_reference(x, y) - z`` at each moving point placed in the reference frame, with ``Z`` the
bilinear height of the reference grid (first returns); positive where the point lies below the
lidar surface. Statistics follow Hoehle & Hoehle (2009): median and NMAD next to RMSE, because
tie points on canopy, walls and blunders make the distribution heavy-tailed.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from .robust import nmad


@dataclass(frozen=True)
class HeightStats:
    """Statistics of ``dz = z_reference_surface - z_moving`` over the points on the reference."""

    n_moving: int
    n_used: int
    median_dz: float | None
    nmad_dz: float | None
    mean_dz: float | None
    rmse_z: float | None
    p05_dz: float | None
    p95_dz: float | None
    overlap_fraction: float
    p25_dz: float | None = None
    p75_dz: float | None = None
    max_abs_dz: float | None = None

    @classmethod
    def from_dz(cls, dz: np.ndarray, n_moving: int) -> HeightStats:
        dz = np.asarray(dz, dtype=np.float64)
        dz = dz[np.isfinite(dz)]
        n = len(dz)
        if n == 0:
            return cls(n_moving, 0, None, None, None, None, None, None, 0.0)
        p05, p25, p75, p95 = np.percentile(dz, [5, 25, 75, 95])
        return cls(
            n_moving=n_moving,
            n_used=n,
            median_dz=float(np.median(dz)),
            nmad_dz=nmad(dz),
            mean_dz=float(dz.mean()),
            rmse_z=float(np.sqrt(np.mean(dz**2))),
            p05_dz=float(p05),
            p95_dz=float(p95),
            overlap_fraction=n / max(n_moving, 1),
            p25_dz=float(p25),
            p75_dz=float(p75),
            max_abs_dz=float(np.abs(dz).max()),
        )

    def to_dict(self) -> dict[str, Any]:
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in asdict(self).items()}


BLUNDER_NMADS = 4.0  # without fine-stage weights: |dz - median| beyond this many NMADs


@dataclass(frozen=True, eq=False)
class PointResiduals:
    """Per-point height differences before and after the fine stage, with the fine weights.

    ``xyz``: the moving points in the reference frame after registration (file coordinates).
    ``dz_before``: at the pose before the fine stage (the coarse answer or the starting pose);
    ``dz_after``: at the final pose; NaN where a point is off the reference surface.
    ``weight``: the fine stage's final robust weight (NaN without a fine stage); ``blunder``:
    rejected by the fine stage (weight 0), or without weights beyond :data:`BLUNDER_NMADS`.
    """

    xyz: np.ndarray
    dz_before: np.ndarray
    dz_after: np.ndarray
    weight: np.ndarray
    blunder: np.ndarray

    @classmethod
    def from_dz(cls, xyz: np.ndarray, dz_before: np.ndarray, dz_after: np.ndarray,
                weight: np.ndarray | None = None) -> PointResiduals:
        n = len(xyz)
        w = np.full(n, np.nan) if weight is None else np.asarray(weight, dtype=np.float64)
        on = np.isfinite(dz_after)
        if np.isfinite(w).any():
            blunder = on & np.isfinite(w) & (w <= 0.0)
        else:
            med, spread = np.nanmedian(dz_after) if on.any() else 0.0, nmad(dz_after)
            blunder = on & (np.abs(dz_after - med) > BLUNDER_NMADS * max(spread, 1e-12))
        return cls(np.asarray(xyz, dtype=np.float64), np.asarray(dz_before, dtype=np.float64),
                   np.asarray(dz_after, dtype=np.float64), w, blunder)

    def stats(self, *, after: bool = True) -> HeightStats:
        return HeightStats.from_dz(self.dz_after if after else self.dz_before, len(self.xyz))

    def to_csv(self) -> str:
        """``x,y,z,dz_before,dz_after,weight,blunder`` per point (empty fields: no value)."""

        def f(v: float, fmt: str) -> str:
            return format(v, fmt) if np.isfinite(v) else ""

        lines = ["x,y,z,dz_before,dz_after,weight,blunder"]
        for (x, y, z), b, a, w, bl in zip(self.xyz, self.dz_before, self.dz_after, self.weight,
                                          self.blunder):
            lines.append(f"{x:.4f},{y:.4f},{z:.4f},{f(b, '.4f')},{f(a, '.4f')},{f(w, '.3f')},"
                         f"{int(bl)}")
        return "\n".join(lines) + "\n"
