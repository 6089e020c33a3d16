"""Packages that only some features need, imported when those features run.

The report's figures need matplotlib (the ``report`` extra) and the simulator's corner detector
scikit-image (the ``simulate`` extra); registration needs neither. A missing one raises
:class:`~tiereg.errors.MissingDependencyError` naming the extra that installs it.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from .errors import MissingDependencyError


def require(module: str, *, extra: str, feature: str) -> ModuleType:
    """``module`` imported, or a :class:`MissingDependencyError` that says which ``extra``
    installs it (``feature``: what needs it, for the message)."""
    try:
        return importlib.import_module(module)
    except ImportError:
        package = module.split(".")[0]
        raise MissingDependencyError(
            f"{feature} needs {package}, which is not installed; install tiereg with its "
            f"'{extra}' extra: pip install 'tiereg[{extra}]' (or pip install {package})"
        ) from None


def pyplot(feature: str = "the report") -> ModuleType:
    """matplotlib's pyplot on the off-screen Agg backend (no display is needed)."""
    matplotlib = require("matplotlib", extra="report", feature=feature)
    matplotlib.use("Agg", force=True)
    return require("matplotlib.pyplot", extra="report", feature=feature)
