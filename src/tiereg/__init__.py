"""tiereg: automatic co-registration of photogrammetric tie points with airborne lidar."""

from __future__ import annotations

import logging

from .errors import FormatError, InputError, OutputError, TieregError
from .points import PointSet
from .transform import Helmert7, Transform

__version__ = "0.1.0"

__all__ = [
    "FormatError",
    "Helmert7",
    "InputError",
    "OutputError",
    "PointSet",
    "TieregError",
    "Transform",
    "__version__",
]

logging.getLogger(__name__).addHandler(logging.NullHandler())
