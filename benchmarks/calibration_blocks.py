"""The calibration benchmark's blocks and its memory probe, shared by ``calibration.py`` and
``calibration_solvers.py`` (neither imports the other's functions)."""

from __future__ import annotations

import numpy as np

from tiereg.simulate import ImageBlock, LidarSurvey, SceneSpec, make_scene, make_world
from tiereg.simulate.cameras import CameraModel, FlightPlan, flat_world, make_camera_block


def truth_camera(seed: int) -> CameraModel:
    return CameraModel.random(np.random.default_rng([seed, 3]), width_px=3000, height_px=2000)


def block_side_m(plan: FlightPlan, camera: CameraModel) -> float:
    """The side of the square of ground the flight plan covers."""
    h = plan.flying_height_m
    along = h * camera.height_px / camera.focal_px * (1 + (plan.images_per_strip - 1)
                                                       * (1 - plan.forward_overlap))
    across = h * camera.width_px / camera.focal_px * (1 + (plan.strips - 1)
                                                      * (1 - plan.side_overlap))
    return max(along, across) * 1.05


def make_block(world_kind: str, flat: bool, plan: FlightPlan, camera: CameraModel, seed: int,
               *, max_points: int = 5000, heading: float | None = None):
    """``(scene, block)``: the world, its lidar and the image block over it."""
    rng = np.random.default_rng([seed, 5])
    side = block_side_m(plan, camera)
    lidar = 1.3 * side + 150
    spec = SceneSpec(kind=world_kind, seed=seed, world_size_m=lidar + 300, lidar_size_m=lidar,
                     survey=LidarSurvey(density_per_m2=1.0, gap_probability=0.0),
                     block=ImageBlock(side_m=side, tie_points_per_km2=20000,
                                      blunder_fraction=0.02),
                     block_heading_deg=float(rng.uniform(0, 180)) if heading is None else heading,
                     overlap=1.0)
    world = make_world(world_kind, size_m=spec.world_size_m, cell=spec.world_cell_m, seed=seed)
    scene = make_scene(spec, world=flat_world(world) if flat else world)
    return scene, make_camera_block(scene, plan, camera, max_points=max_points, seed=seed)



def _rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 1e6


class PeakMemory:
    """The peak resident memory of this process while in the block (psutil, sampled)."""

    def __enter__(self):
        import threading

        self.start = self.peak = _rss_mb()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()
        return self

    def _watch(self):
        while not self._stop.wait(0.05):
            self.peak = max(self.peak, _rss_mb())

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, _rss_mb())
