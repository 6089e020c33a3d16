"""Levelling: the vertical of a moving model in any orientation, before the level problem.

A structure-from-motion model without georeferencing (COLMAP, Bundler) comes in any orientation.
The coarse stage solves the *level* problem (heading, scale, shift, height offset, small tilts),
so the model is first turned so that its vertical points up:

- from the cameras, when the model has them: aerial images look down, so the mean optical axis
  is the model's down direction; the cameras lie above the points, which fixes its sign;
- otherwise from the points: the normal of their dominant plane (robust PCA: the smallest
  principal axis after trimming the points farthest from the plane). Its sign is unknown: both
  are tried, and the model as it is (steep ground tilts its own dominant plane), and the one the
  reference confirms wins. A block about as thick as it is wide has no dominant plane: the
  vertical is then ambiguous and the result says so.

From the cameras, a model is turned whenever its up is more than :data:`MIN_CAMERA_TILT_DEG`
off +z, upside down included. From the points alone, both senses of the dominant plane's
normal are tried whatever its tilt (a model may be upside down and still level to a few
degrees), and up to :data:`MAX_GROUND_TILT_DEG` the points as they are too (level data, tie
points of an aerial triangulation, on sloping ground); the reference decides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .transform import Transform

# points-only: the points as they are, with a dominant plane tilted less than this, are compared
# as level data (no plane fitted to their heights: terrain slopes are a few degrees)
MIN_TILT_DEG = 15.0
# cameras: a model whose up is less than this off +z is used as it is (the fine stage's tilts
# take up the rest)
MIN_CAMERA_TILT_DEG = 0.5
# points-only: a dominant plane tilted more than this is not the ground's own slope (high
# mountains tilt it by 15-20 deg), so the model as it is cannot be level and is not tried
MAX_GROUND_TILT_DEG = 40.0
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
    still lean (levelled by a plane of their own, not by cameras), and a name for the result."""

    T: Transform
    free_tilt: bool
    name: str  # "as is", "up" (levelled by the vertical found), "down" (by its opposite)


def starting_poses(vertical: Vertical, centre: np.ndarray) -> list[StartingPose]:
    """The orientations to try for a model whose vertical is ``vertical`` (turned about
    ``centre``), most likely first.

    From cameras: the one their viewing direction gives. From points: both senses of the
    dominant plane's normal, and the points as they are where that plane is no steeper than any
    ground (:data:`MAX_GROUND_TILT_DEG`); nearly level points (:data:`MIN_TILT_DEG`) are not
    levelled by their plane in the same sense (terrain slopes would tilt them), only turned over.
    """
    up = np.asarray(vertical.up, dtype=np.float64)
    if vertical.source == "cameras":
        return [StartingPose(levelling(up, centre), False, "up")]
    poses = []
    if vertical.tilt_deg <= MAX_GROUND_TILT_DEG:
        poses.append(StartingPose(Transform.identity(), vertical.tilt_deg > MIN_TILT_DEG, "as is"))
    if vertical.tilt_deg > MIN_TILT_DEG:
        poses.append(StartingPose(levelling(up, centre), True, "up"))
    poses.append(StartingPose(levelling(-up, centre), True, "down"))
    return poses


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
