"""Coordinate reference systems, for labels, units and checks of the inputs (never for
computation)."""

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


def is_geographic(wkt: str | None) -> bool:
    """Whether the CRS is geographic (longitude and latitude in degrees)."""
    crs = _parse(wkt)
    return crs is not None and crs.is_geographic


def refuse_geographic(wkt: str | None, *, where: str, role: str = "") -> None:
    """:class:`~tiereg.errors.InputError` when ``wkt`` is geographic: cells, shifts and scales
    in degrees mean nothing. ``where`` names the data, ``role`` its part (moving, reference)."""
    if is_geographic(wkt):
        from .errors import InputError

        raise InputError(f"{where}: the {role + ' ' if role else ''}coordinates are longitude "
                         f"and latitude ({crs_label(wkt)}); reproject to a projected CRS (metres "
                         "or feet, e.g. UTM) first")


def same_crs(a: str | None, b: str | None) -> bool:
    """Whether two CRS records name the same CRS (both missing counts as the same; one missing
    or unparsable does not contradict the other)."""
    ca, cb = _parse(a), _parse(b)
    return ca is None or cb is None or ca.equals(cb, ignore_axis_order=True)
