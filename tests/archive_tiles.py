"""Small lidar archives for the archive, distributed and batch tests: LAZ tiles of a known
surface (:func:`scenes.surface`) with second returns, noise points (class 7) and withheld
points, written tile by tile."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scenes import surface

ORIGIN = (500_000.0, 5_000_000.0)


def write_tiles(folder: Path, *, tiles: tuple[int, int] = (3, 2), tile_m: float = 500.0,
                density: float = 0.12, seed: int = 0, extent: float = 2000.0,
                returns: bool = True) -> list[Path]:
    """``tiles`` (columns, rows) of ``tile_m`` squares from the lower-left corner
    ``(-cols * tile_m / 2, -rows * tile_m / 2)`` (local metres, plus :data:`ORIGIN`)."""
    import laspy

    folder.mkdir(parents=True, exist_ok=True)
    cols, rows = tiles
    paths = []
    for i in range(rows):
        for j in range(cols):
            rng = np.random.default_rng([seed, i, j])
            n = rng.poisson(density * tile_m * tile_m)
            x = -cols * tile_m / 2 + j * tile_m + rng.uniform(0, tile_m, n)
            y = -rows * tile_m / 2 + i * tile_m + rng.uniform(0, tile_m, n)
            z = surface(x, y, seed=seed, extent=extent) + rng.normal(0, 0.05, n)
            second = rng.random(n) < 0.1  # a last return 3 m below
            noise = rng.random(n) < 0.01  # birds, 300 m up
            withheld = rng.random(n) < 0.005
            header = laspy.LasHeader(version="1.4", point_format=6)
            header.scales = np.array([0.01, 0.01, 0.01])
            header.offsets = np.array([ORIGIN[0], ORIGIN[1], 0.0])
            las = laspy.LasData(header)
            las.x = np.concatenate([x, x[second]]) + ORIGIN[0]
            las.y = np.concatenate([y, y[second]]) + ORIGIN[1]
            las.z = np.concatenate([np.where(noise, z + 300, z), z[second] - 3])
            if returns:
                las.return_number = np.r_[np.ones(n), np.full(second.sum(), 2)].astype(np.uint8)
                las.number_of_returns = np.r_[np.where(second, 2, 1),
                                              np.full(second.sum(), 2)].astype(np.uint8)
            las.classification = np.r_[np.where(noise, 7, 2),
                                       np.full(second.sum(), 2)].astype(np.uint8)
            las.withheld = np.r_[withheld, np.zeros(second.sum(), bool)]
            path = folder / f"tile_{i}_{j}.laz"
            las.write(str(path), do_compress=True)
            paths.append(path)
    return paths
