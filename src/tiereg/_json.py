"""JSON as tiereg writes it (RESULT.json, overlap.json, CALIBRATION.json)."""

from __future__ import annotations

from typing import Any

import numpy as np


def dumps_json(data: dict[str, Any]) -> str:
    """Indented JSON with lists of numbers (matrix rows, vectors) kept on one line. JSON has no
    infinity or NaN: a number that is not finite (a ratio over nothing) is written as null."""
    import json
    import re

    text = json.dumps(_finite_or_null(data), indent=2, allow_nan=False, default=_json_default)
    number_list = re.compile(r"\[\s*(-?[\d.eE+-]+(?:,\s*-?[\d.eE+-]+)*)\s*\]")
    return number_list.sub(lambda m: "[" + ", ".join(v.strip() for v in m.group(1).split(","))
                           + "]", text)


def _finite_or_null(o: object) -> object:
    if isinstance(o, dict):
        return {k: _finite_or_null(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite_or_null(v) for v in o]
    if isinstance(o, (float, np.floating)):
        return float(o) if np.isfinite(o) else None
    return o


def _json_default(o: object) -> object:
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    raise TypeError(f"not JSON serializable: {type(o).__name__}")
