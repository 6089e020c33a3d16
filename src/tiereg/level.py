"""Levelling: the vertical of a moving model in any orientation, before the level problem.

A structure-from-motion model without georeferencing (COLMAP, Bundler) comes in any orientation.
The coarse stage solves the *level* problem (heading, scale, shift, height offset, small tilts),
so the model is first turned so that its vertical points up:

- from the cameras, when the model has them: aerial images look down, so the mean optical axis
  is the model's down direction; the cameras lie above the points, which fixes its sign;
- otherwise from the points: the normal of their dominant plane (robust PCA: the smallest
  principal axis after trimming the points farthest from the plane). Its sign is unknown: both
  are tried, and the model as it is (rugged ground tilts its own dominant plane, by any
  angle), in turn until the reference confirms one. A block about as thick as it is wide has no
  dominant plane: the vertical is then ambiguous and the result says so.

From the cameras, a model is turned whenever its up is more than :data:`MIN_CAMERA_TILT_DEG`
off +z, upside down included. From the points alone, both senses of the dominant plane's
normal are tried whatever its tilt (a model may be upside down and still level to a few
degrees), and the points as they are too, whatever the tilt (level data, tie points of an
aerial triangulation: a mountain block's dominant plane leans by 16-78 degrees on the verdict
benchmark's scenes), last where it leans more than :data:`MAX_GROUND_TILT_DEG` and only
when neither sense registers confidently; the reference decides. Where the points' plane says
nothing of their vertical (they have no dominant plane, or the reference's ground is steep:
its own dominant plane leans more than :data:`MIN_TILT_DEG`, or it has none, and level data
of it lean as much) the points as they are come first, and the same turned over and the
levelled orientations only when they do not register confidently. Whatever the order, the
first orientation registered confidently ends the search: a mirrored ground is rejected by the
verdict as any wrong pose is (:data:`~tiereg.verdict.MAX_SPREAD_SCATTER`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .transform import Transform

# points-only: points whose dominant plane is tilted less than this are not levelled by it in the
# same sense, only turned over (terrain slopes tilt it by a few degrees)
MIN_TILT_DEG = 15.0
# points-only: a dominant plane leaning more than this makes the points as they are the least
# likely orientation (a model in any orientation leans it by any angle), tried last and only
# when no levelled one registers confidently (tried always, they doubled the median time of
# the orientation benchmark's points-only models); mountain blocks lean it by 46-78 deg on the
# verdict benchmark's sample, where none of the 7 registered levelled by the plane, and all 7
# find their pose as they are
MAX_GROUND_TILT_DEG = 40.0
# cameras: a model whose up is less than this off +z is used as it is (the fine stage's tilts
# take up the rest)
MIN_CAMERA_TILT_DEG = 0.5
MAX_FLATNESS = 0.5  # smallest / middle principal spread above this: no dominant plane
TRIM = 0.8  # the robust PCA keeps this share of the points nearest to the plane


@dataclass(frozen=True)
class Vertical:
    """The up direction of a moving model (its own frame, unit vector) and where it came from."""

    up: tuple[float, float, float]
    source: str  # "cameras" or "points"
    sign_known: bool  # False: up and -up are both possible (points only)
    flatness: float  # smallest over middle principal spread of the points (0: a plane)

    @property
    def tilt_deg(self) -> float:
        """Angle between the model's up (either sense) and its z axis: 0 to 90 degrees."""
        return math.degrees(math.acos(float(np.clip(abs(self.up[2]), 0.0, 1.0))))

    @property
    def off_up_deg(self) -> float:
        """Angle between the model's up, in its sense, and its +z axis: 0 to 180 degrees (180:
        upside down)."""
        return math.degrees(math.acos(float(np.clip(self.up[2], -1.0, 1.0))))

    @property
    def ambiguous(self) -> bool:
        """Points only: no dominant plane, so no vertical (cameras say it whatever the relief)."""
        return self.source == "points" and self.flatness > MAX_FLATNESS


def _principal(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = points - points.mean(axis=0)
    evals, evecs = np.linalg.eigh(d.T @ d / max(len(points), 1))
    return evals, evecs


def vertical_from_points(points: np.ndarray) -> Vertical:
    """The dominant plane's normal (robust PCA; the sign is unknown)."""
    p = np.asarray(points, dtype=np.float64)
    evals, evecs = _principal(p)
    for _ in range(3):  # trim the points farthest from the plane (trees, walls, blunders)
        n = evecs[:, 0]
        dist = np.abs((p - p.mean(axis=0)) @ n)
        keep = dist <= np.quantile(dist, TRIM)
        evals, evecs = _principal(p[keep])
    n = evecs[:, 0]
    n = n if n[2] >= 0 else -n
    spread = np.sqrt(np.maximum(_principal(p)[0], 0.0))
    return Vertical(tuple(float(v) for v in n), "points", False,
                    float(spread[0] / max(spread[1], 1e-300)))


def vertical_from_cameras(centres: np.ndarray, directions: np.ndarray,
                          points: np.ndarray) -> Vertical | None:
    """Up from the cameras' mean optical axis (``None`` if they do not look one way)."""
    d = np.asarray(directions, dtype=np.float64)
    if len(d) < 2:
        return None
    mean = d.mean(axis=0)
    if np.linalg.norm(mean) < 0.5:  # oblique views all around: no common down direction
        return None
    up = -mean / np.linalg.norm(mean)
    above = (np.asarray(centres, dtype=np.float64) - np.asarray(points).mean(axis=0)) @ up
    if np.median(above) < 0:  # the cameras must be above the ground they see
        return None
    spread = np.sqrt(np.maximum(_principal(np.asarray(points, dtype=np.float64))[0], 0.0))
    return Vertical(tuple(float(v) for v in up), "cameras", True,
                    float(spread[0] / max(spread[1], 1e-300)))


@dataclass(frozen=True)
class StartingPose:
    """A way to turn a model before the level problem: the rotation, whether its points may
    still lean (levelled by a plane of their own, not by cameras), a name for the result, and
    whether it is a last resort (put after the others; as every pose, tried only when none
    before it registers confidently)."""

    T: Transform
    free_tilt: bool
    name: str  # "as is", "as is, turned over", "up" (levelled by the vertical found), "down"
    last_resort: bool = False


def starting_poses(vertical: Vertical, centre: np.ndarray, *,
                   as_is_first: bool = False) -> list[StartingPose]:
    """The orientations to try for a model whose vertical is ``vertical`` (turned about
    ``centre``), most likely first.

    From cameras: the one their viewing direction gives. From points: the points as they are,
    and both senses of the dominant plane's normal, whatever its tilt (no tilt of the plane
    rules out level data: rugged ground leans it by any angle), compared as level data (no
    plane fitted to their heights). Where the plane leans more than
    :data:`MAX_GROUND_TILT_DEG`, the points as they are come last, as a last resort. Nearly
    level points (:data:`MIN_TILT_DEG`) are not levelled by their plane in the same sense
    (terrain slopes would tilt them), only turned over. With ``as_is_first`` (the plane says
    nothing of the vertical: :attr:`Vertical.ambiguous`, or :func:`is_steep_ground` of the
    reference) the points as they are come first; the same turned over (level data upside
    down, as a model whose first camera looked down gives them) and the levelled orientations
    are last resorts.
    """
    up = np.asarray(vertical.up, dtype=np.float64)
    if vertical.source == "cameras":
        return [StartingPose(levelling(up, centre), False, "up")]
    tilt = vertical.tilt_deg
    poses = [StartingPose(levelling(up, centre), True, "up", last_resort=as_is_first)
             ] if tilt > MIN_TILT_DEG else []
    poses.append(StartingPose(levelling(-up, centre), True, "down", last_resort=as_is_first))
    # as they are, the points are taken for level data: no plane is fitted to their heights,
    # which on steep ground would take away the slope that places them
    as_is = StartingPose(Transform.identity(), False, "as is",
                         last_resort=tilt > MAX_GROUND_TILT_DEG and not as_is_first)
    if as_is_first:
        over = StartingPose(turned_over(centre), False, "as is, turned over", last_resort=True)
        return [as_is, over, *poses]
    return poses + [as_is] if as_is.last_resort else [as_is, *poses]


def turned_over(centre: np.ndarray) -> Transform:
    """Half a turn about the x axis through ``centre``: level data upside down, right way up."""
    c = np.asarray(centre, dtype=np.float64)
    M = np.diag([1.0, -1.0, -1.0, 1.0])
    M[:3, 3] = c - M[:3, :3] @ c
    return Transform(M)


def is_steep_ground(xyz: np.ndarray) -> bool:
    """Whether the ground sampled by ``xyz`` (the reference) is steep: its dominant plane leans
    more than :data:`MIN_TILT_DEG`, or it has none (:data:`MAX_FLATNESS`). Level data of such
    ground lean their own plane as much, so the plane does not give their vertical."""
    if len(xyz) < 3:
        return False
    ground = vertical_from_points(xyz)
    return ground.tilt_deg > MIN_TILT_DEG or ground.ambiguous


def levelling(up: tuple[float, float, float] | np.ndarray, centre: np.ndarray) -> Transform:
    """The rotation about ``centre`` that turns ``up`` onto +z (Rodrigues' formula; the smallest
    such rotation, so heading is left for the coarse stage)."""
    u = np.asarray(up, dtype=np.float64)
    u = u / np.linalg.norm(u)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(u, z)
    s, c = float(np.linalg.norm(axis)), float(u @ z)
    if s < 1e-12:
        R = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        k = axis / s
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        R = np.eye(3) + s * K + (1 - c) * (K @ K)
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = centre - R @ centre
    return Transform(M)
