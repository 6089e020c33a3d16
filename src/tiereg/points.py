"""Point sets: the (N, 3) float64 coordinates tiereg works on, and where they came from."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import InputError


@dataclass(frozen=True, eq=False)
class PointSet:
    """Coordinates ``xyz`` (N, 3) float64 in the file's own units and CRS.

    ``source`` names the origin (a path or ``"<array>"``) so that errors can point at it;
    ``crs_wkt`` is the coordinate reference system when the file carried one.
    """

    xyz: np.ndarray = field(repr=False)
    source: str = "<array>"
    crs_wkt: str | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        try:
            xyz = np.asarray(self.xyz, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(
                f"{self.source}: points must be an (N, 3) array of numbers x, y, z, got "
                f"{_describe(self.xyz)}") from None
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise InputError(
                f"{self.source}: points must be an (N, 3) array of x, y, z, got shape {xyz.shape}"
            )
        if not xyz.flags.c_contiguous or xyz is self.xyz:
            xyz = np.ascontiguousarray(xyz).copy()
        xyz.setflags(write=False)
        object.__setattr__(self, "xyz", xyz)

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(min xyz, max xyz)``."""
        return self.xyz.min(axis=0), self.xyz.max(axis=0)


def _describe(obj: object) -> str:
    """A few words on what a caller gave in place of points."""
    if isinstance(obj, np.ndarray):
        return f"an array of {obj.dtype} with shape {obj.shape}"
    return f"a {type(obj).__name__}"


def check_finite(points: PointSet) -> None:
    """Refuse points with a NaN or infinite coordinate, naming how many and the first row."""
    finite = np.isfinite(points.xyz).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise InputError(
            f"{points.source}: {len(bad)} of {len(finite)} points have NaN or infinite "
            f"coordinates (the first in row {bad[0]}, from 0); remove them or fix the export"
        )


GROSS_FENCE = 3.0  # spans of the 1st-99th percentiles beyond either end: far outside the block
MAX_GROSS_SHARE = 0.01  # more points than this out there are not strays but part of the data


def gross_outliers(xyz: np.ndarray) -> np.ndarray:
    """Which points lie far outside the block: beyond :data:`GROSS_FENCE` times the span of the
    1st to 99th percentiles past either end, on any axis (a nodata height such as -9999, a point
    left at the origin). None when more than :data:`MAX_GROSS_SHARE` of the points would be.
    The height span counts as at least a hundredth of the horizontal one (a level block's is
    nearly nothing)."""
    lo, hi = np.percentile(xyz, [1.0, 99.0], axis=0)
    span = hi - lo
    span = np.maximum(span, 0.01 * max(span[0], span[1]))
    far = np.any((xyz < lo - GROSS_FENCE * span) | (xyz > hi + GROSS_FENCE * span), axis=1)
    return far if far.sum() <= MAX_GROSS_SHARE * len(xyz) else np.zeros(len(xyz), bool)


def validate_points(points: PointSet, *, min_count: int, role: str) -> None:
    """Reject point sets that no registration can use, naming the file and the fix.

    Checks: enough points, all coordinates finite, and a horizontal spread that is neither a
    single position nor a line (a registration needs an areal footprint).
    """
    n = len(points)
    src = points.source
    if n == 0:
        raise InputError(f"{src}: the {role} point set is empty; give a file with points in it")
    if n < min_count:
        raise InputError(
            f"{src}: the {role} side has {n} points, a registration needs at least {min_count}; "
            "give more points (a denser or larger tie-point set)"
        )
    check_finite(points)
    xy = points.xyz[:, :2] - points.xyz[:, :2].mean(axis=0)
    sv = np.linalg.svd(xy, compute_uv=False) / np.sqrt(n)
    # a spread within the rounding of the coordinates themselves is none (the mean of 200
    # copies of 500000.123 is not exactly 500000.123)
    if sv[0] <= 1e-12 * max(1.0, float(np.abs(points.xyz[:, :2]).max())):
        raise InputError(
            f"{src}: all {role} points share one horizontal position; "
            "a registration needs points spread over an area"
        )
    if sv[1] <= 1e-6 * sv[0]:
        raise InputError(
            f"{src}: the {role} points lie on a line in plan view; "
            "a registration needs points spread over an area, not a profile"
        )
