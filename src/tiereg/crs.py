"""Coordinate reference systems, for labels and units in results (never for computation)."""

from __future__ import annotations


def _parse(wkt: str | None):
    if not wkt:
        return None
    try:
        import pyproj

        return pyproj.CRS.from_wkt(wkt)
    except Exception:  # an unparsable CRS record must not stop a registration
        return None


def crs_label(wkt: str | None) -> str | None:
    """``"NAME (EPSG:code)"``, the name alone, or None without a (parsable) CRS."""
    crs = _parse(wkt)
    if crs is None:
        return None
    epsg = crs.to_epsg()
    return f"{crs.name} (EPSG:{epsg})" if epsg else crs.name


def crs_units(wkt: str | None) -> str:
    """The horizontal unit name (``"metre"``, ``"foot"``, ``"US survey foot"``) or ``"unknown"``."""
    crs = _parse(wkt)
    if crs is None or not crs.axis_info:
        return "unknown"
    return crs.axis_info[0].unit_name
