"""Synthetic scenes with known answers: worlds, an airborne lidar, an image block's tie points.

>>> from tiereg.simulate import SceneSpec, make_scene   # doctest: +SKIP
>>> scene = make_scene(SceneSpec(kind="urban", seed=3, overlap=0.6))   # doctest: +SKIP
>>> scene.moving, scene.lidar.xyz, scene.T_ref_mov   # doctest: +SKIP
"""

from __future__ import annotations

from .scene import (
    GEOREF,
    HiddenTransform,
    OrientedModel,
    Scene,
    SceneSpec,
    make_scene,
    oriented_model,
    write_scene,
)
from .sensors import ImageBlock, LidarSurvey
from .world import KINDS, World, make_world

__all__ = ["GEOREF", "KINDS", "HiddenTransform", "ImageBlock", "LidarSurvey", "OrientedModel",
           "Scene", "SceneSpec", "World", "make_scene", "make_world", "oriented_model",
           "write_scene"]
