"""Small synthetic scenes with known answers for the tests (terrain, buildings, lidar, ties)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tiereg import Transform


def surface(x: np.ndarray, y: np.ndarray, *, seed: int = 0, extent: float = 2000.0) -> np.ndarray:
    """Rolling terrain (random plane waves) with box buildings: z(x, y), metres."""
    rng = np.random.default_rng(seed)
    z = np.zeros_like(x, dtype=np.float64)
    for _ in range(40):
        wavelength = rng.uniform(60.0, 1500.0)
        angle = rng.uniform(0, np.pi)
        k = 2 * np.pi / wavelength
        amp = 8.0 * (wavelength / 1500.0) ** 1.2
        z += amp * np.sin(k * (np.cos(angle) * x + np.sin(angle) * y) + rng.uniform(0, 2 * np.pi))
    for _ in range(int(60 * (extent / 2000.0) ** 2)):
        cx, cy = rng.uniform(-extent / 2, extent / 2, 2)
        w, h = rng.uniform(15, 60, 2)
        inside = (np.abs(x - cx) < w / 2) & (np.abs(y - cy) < h / 2)
        z = np.where(inside, z + rng.uniform(5, 20), z)
    return z + 100.0


@dataclass(frozen=True)
class Scene:
    lidar: np.ndarray  # (N, 3) in the reference frame
    tie_mov: np.ndarray  # (M, 3) in the moving frame
    T_ref_mov: Transform  # truth
    origin: np.ndarray


def make_scene(
    *,
    seed: int = 0,
    extent: float = 2000.0,
    lidar_points: int = 400_000,
    tie_points: int = 2000,
    block: float = 1200.0,
    block_offset: tuple[float, float] = (150.0, -100.0),
    T_mov_ref: Transform | None = None,
    origin: tuple[float, float, float] = (500_000.0, 5_000_000.0, 0.0),
    noise_xy: float = 0.15,
    noise_z: float = 0.3,
) -> Scene:
    """Lidar over ``extent`` squared, tie points over a ``block`` inside it, moved by a transform.

    Coordinates sit near ``origin`` (projected coordinates in the millions).
    """
    rng = np.random.default_rng(seed + 1000)
    h = extent / 2
    lx, ly = rng.uniform(-h, h, lidar_points), rng.uniform(-h, h, lidar_points)
    lidar = np.column_stack([lx, ly, surface(lx, ly, seed=seed, extent=extent)])
    lidar[:, 2] += rng.normal(0, 0.05, lidar_points)
    b = block / 2
    tx = rng.uniform(-b, b, tie_points) + block_offset[0]
    ty = rng.uniform(-b, b, tie_points) + block_offset[1]
    tie = np.column_stack([tx, ty, surface(tx, ty, seed=seed, extent=extent)])
    tie += rng.normal(0, [noise_xy, noise_xy, noise_z], tie.shape)
    o = np.asarray(origin, dtype=np.float64)
    lidar += o
    tie += o
    T = T_mov_ref if T_mov_ref is not None else Transform.identity()
    return Scene(lidar, T.apply(tie), T.inverse, o)
