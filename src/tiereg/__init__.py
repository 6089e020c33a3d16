"""tiereg: automatic co-registration of photogrammetric tie points with airborne lidar."""

from __future__ import annotations

import logging

from ._version import __version__
from .calibrate import CalibrationResult, calibrate
from .errors import FormatError, InputError, OutputError, TieregError
from .evaluate import Quality, evaluate
from .io import open_points, read_points, write_points
from .pipeline import RegistrationResult, register
from .points import PointSet
from .reference import Reference, prepare_reference
from .transform import Helmert7, Transform

__all__ = [
    "CalibrationResult",
    "FormatError",
    "Helmert7",
    "InputError",
    "OutputError",
    "PointSet",
    "Quality",
    "Reference",
    "RegistrationResult",
    "TieregError",
    "Transform",
    "__version__",
    "calibrate",
    "evaluate",
    "open_points",
    "prepare_reference",
    "read_points",
    "register",
    "write_points",
]

logging.getLogger(__name__).addHandler(logging.NullHandler())
