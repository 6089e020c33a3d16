"""Cross-aided camera calibration: the lidar calibrates the cameras of a registered model.

>>> import tiereg   # doctest: +SKIP
>>> result = tiereg.calibrate("sparse/0", "lidar.laz")   # doctest: +SKIP
>>> result.camera().after, result.camera().held, result.check_after   # doctest: +SKIP

See :func:`~tiereg.calibrate.run.calibrate` and docs/calibration.md.
"""

from __future__ import annotations

from .degenerate import TOLERANCE, Tolerance
from .result import CalibrationResult, CameraCalibration
from .run import REFINE_KINDS, calibrate

__all__ = ["REFINE_KINDS", "TOLERANCE", "CalibrationResult", "CameraCalibration", "Tolerance",
           "calibrate"]
