"""Quality of a registration: height differences of the moving points against the reference."""

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

    @classmethod
    def from_dz(cls, dz: np.ndarray, n_moving: int) -> HeightStats:
        dz = np.asarray(dz, dtype=np.float64)
        dz = dz[np.isfinite(dz)]
        n = len(dz)
        if n == 0:
            return cls(n_moving, 0, None, None, None, None, None, None, 0.0)
        p05, p95 = np.percentile(dz, [5, 95])
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
        )

    def to_dict(self) -> dict[str, Any]:
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in asdict(self).items()}
