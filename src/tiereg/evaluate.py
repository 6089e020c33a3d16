"""How well a pose puts the tie points on the lidar: their heights against the reference.

``dz = Z_reference(x, y) - z`` at each tie point placed by ``T_ref_mov``, with ``Z`` the plane
through the lidar's own points around it (:class:`~tiereg.surface.LocalSurface`; a grid cell's
mean is metres off beside walls and in canopy gaps), or the reference grid where the lidar has
too few points there. :func:`evaluate` is the public entry; the registration, its report and the
quality maps all measure heights with :func:`height_differences`.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .io import PointSource, as_point_source
from .points import PointSet
from .quality import HeightStats
from .reference import Reference, prepare_reference
from .surface import LocalSurface, SurfaceSampler
from .transform import Transform

# heights against local planes of the lidar within this many point spacings of a tie point; half
# a spacing inside the corridor the fine stage reads (2.5 spacings at least), so that the fine
# stage's move cannot take a neighbour out of it
SURFACE_RADIUS_SPACINGS = 2.0
MIN_LIDAR_POINTS = 50  # fewer lidar points near the tie points: the grid serves


def height_differences(xyz_ref: np.ndarray, surface: SurfaceSampler | LocalSurface
                       ) -> np.ndarray:
    """``Z(x, y) - z`` of points (the surface's local frame) on the surface; NaN off it."""
    if isinstance(surface, LocalSurface):
        return surface.heights(xyz_ref[:, 0], xyz_ref[:, 1]) - xyz_ref[:, 2]
    z, ok = surface.sample(xyz_ref[:, 0], xyz_ref[:, 1])
    return np.where(ok, z - xyz_ref[:, 2], np.nan)


def lidar_surface(reference: Reference, xy_local: np.ndarray) -> LocalSurface | None:
    """The local planes of the lidar's own points around ``xy_local`` (the reference's local
    frame), or ``None`` where there are fewer than :data:`MIN_LIDAR_POINTS` of them."""
    radius = SURFACE_RADIUS_SPACINGS * reference.spacing
    lidar = reference.points_near(xy_local, radius)
    return LocalSurface(lidar, radius=radius) if len(lidar) >= MIN_LIDAR_POINTS else None


@dataclass(frozen=True, eq=False)
class Quality:
    """The tie points' heights against the reference at one pose."""

    T_ref_mov: Transform
    xyz: np.ndarray = field(repr=False)  # the tie points in the reference frame (file coords)
    dz: np.ndarray = field(repr=False)  # Z_reference - z per point; NaN off the reference
    stats: HeightStats
    surface: str  # "lidar points" or "grid": what Z was taken from

    @property
    def overlap_fraction(self) -> float:
        """The share of the tie points that lie on the reference."""
        return self.stats.overlap_fraction


def evaluate(
    reference: str | os.PathLike[str] | Sequence[str | os.PathLike[str]] | PointSource
    | Reference,
    moving: str | os.PathLike[str] | PointSource | PointSet | np.ndarray,
    T_ref_mov: Transform | np.ndarray,
    *,
    moving_format: str | None = None,
    reference_format: str | None = None,
) -> Quality:
    """The heights of the ``moving`` tie points placed by ``T_ref_mov`` against the
    ``reference`` (lidar; a :class:`~tiereg.reference.Reference` prepared once serves many
    calls): per point and their statistics, median and NMAD beside RMSE (Hoehle & Hoehle 2009).

    >>> q = evaluate("lidar.laz", "points3D.txt", result.T_ref_mov)  # doctest: +SKIP
    >>> q.stats.nmad_dz, q.overlap_fraction  # doctest: +SKIP
    """
    if not isinstance(T_ref_mov, Transform):
        T_ref_mov = Transform(np.asarray(T_ref_mov, dtype=np.float64))
    if not isinstance(reference, Reference):
        reference = prepare_reference(as_point_source(reference, role="reference",
                                                      format=reference_format))
    xyz = as_point_source(moving, role="moving", format=moving_format).read().xyz
    placed = T_ref_mov.apply(xyz)
    local = placed - reference.origin
    surface = lidar_surface(reference, local[:, :2])
    dz = height_differences(local, surface if surface is not None else reference.surface())
    return Quality(T_ref_mov, placed, dz, HeightStats.from_dz(dz, len(dz)),
                   "lidar points" if surface is not None else "grid")
