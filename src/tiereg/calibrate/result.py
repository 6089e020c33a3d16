"""What a calibration found: frozen results with ``to_dict()`` for CALIBRATION.json."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._version import __version__
from ..quality import HeightStats
from ..transform import Transform

PARAM_NAMES = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}


@dataclass(frozen=True)
class CameraCalibration:
    """One camera's intrinsics before and after, with their precision.

    ``sigma``: one standard deviation per parameter (``None`` where held); ``held``: the
    parameters kept at their input value, each with the reason; ``correlations``: the pairs of
    refined intrinsics correlated by more than 0.5, and each one's largest correlation with
    the poses.
    """

    camera_id: int
    model: str
    width_px: int
    height_px: int
    names: tuple[str, ...]
    before: tuple[float, ...]
    after: tuple[float, ...]
    sigma: tuple[float | None, ...]
    held: tuple[tuple[str, str], ...] = ()
    correlations: tuple[tuple[str, str, float], ...] = ()
    n_images: int = 0
    reprojection_rms_before_px: float = float("nan")
    reprojection_rms_after_px: float = float("nan")

    def value(self, name: str, *, after: bool = True) -> float:
        return (self.after if after else self.before)[self.names.index(name)]

    def is_held(self, name: str) -> bool:
        return any(n == name for n, _ in self.held)

    def to_dict(self) -> dict[str, Any]:
        return {
            "camera_id": self.camera_id,
            "model": self.model,
            "width": self.width_px,
            "height": self.height_px,
            "n_images": self.n_images,
            "intrinsics": {
                n: {"before": b, "after": a, "sigma": s, "change": a - b,
                    "held": self.is_held(n)}
                for n, b, a, s in zip(self.names, self.before, self.after, self.sigma)},
            "held": [{"parameter": n, "reason": r} for n, r in self.held],
            "correlations": [{"a": a, "b": b, "r": round(r, 4)} for a, b, r in self.correlations],
            "reprojection_rms_px": {"before": self.reprojection_rms_before_px,
                                    "after": self.reprojection_rms_after_px},
        }


@dataclass(frozen=True)
class CalibrationResult:
    """Everything a calibration found; ``to_dict()`` is CALIBRATION.json.

    ``check_before``/``check_after``: height residuals against the lidar surface at the held-out
    check points (tie points on strictly planar patches, never used as control; the
    ``n_check_outliers`` of them off the lidar, such as vehicles, are left out), after the
    registration alone and after the calibration. ``model``: the calibrated
    ``pycolmap.Reconstruction`` in the reference frame (``None`` when the calibration did not run).
    """

    confident: bool
    reasons: tuple[str, ...]
    cameras: tuple[CameraCalibration, ...]
    T_ref_mov: Transform
    registration_confident: bool
    reprojection_rms_before_px: float
    reprojection_rms_after_px: float
    pixel_sigma_px: float
    check_before: HeightStats | None
    check_after: HeightStats | None
    control_before: HeightStats | None
    control_after: HeightStats | None
    n_control: int
    n_check: int
    rounds: int
    seconds: float
    refined: tuple[str, ...]
    n_check_outliers: int = 0  # check points left out of the statistics (off the lidar)
    warnings: tuple[str, ...] = ()
    solver: dict[str, Any] = field(default_factory=dict)
    inputs: dict[str, Any] = field(default_factory=dict)
    model: object = field(default=None, repr=False, compare=False)
    # per tie point in the reference frame, for the report: positions and height residuals at
    # the check and control points before and after (NaN elsewhere)
    residuals: dict[str, np.ndarray] = field(default_factory=dict, repr=False, compare=False)

    def camera(self, camera_id: int | None = None) -> CameraCalibration:
        if camera_id is None:
            return self.cameras[0]
        return next(c for c in self.cameras if c.camera_id == camera_id)

    def to_dict(self) -> dict[str, Any]:
        def stats(s: HeightStats | None) -> dict[str, Any] | None:
            return None if s is None else s.to_dict()

        return {
            "tiereg_version": __version__,
            "confident": self.confident,
            "reasons": list(self.reasons),
            "warnings": list(self.warnings),
            "refined": list(self.refined),
            "cameras": [c.to_dict() for c in self.cameras],
            "reprojection_rms_px": {"before": self.reprojection_rms_before_px,
                                    "after": self.reprojection_rms_after_px},
            "pixel_sigma_px": self.pixel_sigma_px,
            "lidar_check_points": {"count": self.n_check, "outliers": self.n_check_outliers,
                                   "before": stats(self.check_before),
                                   "after": stats(self.check_after)},
            "lidar_control_points": {"count": self.n_control,
                                     "before": stats(self.control_before),
                                     "after": stats(self.control_after)},
            "iterations": self.rounds,
            "seconds": round(self.seconds, 3),
            "T_ref_mov": self.T_ref_mov.matrix.tolist(),
            "registration_confident": self.registration_confident,
            "solver": self.solver,
            "inputs": self.inputs,
        }

    def to_json(self) -> str:
        from ..pipeline import dumps_json

        return dumps_json(self.to_dict())
