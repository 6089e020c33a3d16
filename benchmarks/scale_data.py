"""The synthetic archive and blocks of the scale benchmark (benchmarks/scale.py), made once.

A suburban world (:func:`tiereg.simulate.make_world`, 10 km, 2 m raster) is sampled as airborne
lidar tile by tile: 16 x 16 tiles of 600 m (256 LAZ files, about 1.65 points per square metre,
about 152 million points in all; first returns on the visible surface, second returns on the
ground under canopy, 0.05 % noise points classed 7 far above, written with laspy + lazrs).
Twenty blocks of 3,000 tie points (190 m squares, random places, headings and scales in
0.25-4, tilts of a few tenths of a degree, 2 % blunders) are written as text files with their
truth. Everything goes to ``benchmarks/work/scale`` (not committed); a second run finds it there.

    python benchmarks/scale_data.py [--work DIR] [--tiles-per-side 16]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from tiereg.simulate import HiddenTransform, make_world

WORLD_M, WORLD_CELL_M, TILE_M, DENSITY = 10_000.0, 2.0, 600.0, 1.65
E0, N0 = 500_000.0, 5_000_000.0  # projected coordinates of the world's centre
N_BLOCKS, BLOCK_M, TIE_POINTS = 20, 190.0, 3000
NOISE_SHARE, CANOPY_SECOND = 0.0005, 0.4


def _sample(raster: np.ndarray, world, x: np.ndarray, y: np.ndarray, order: int = 1):
    r = (world.y0 - y) / world.cell - 0.5
    c = (x - world.x0) / world.cell - 0.5
    return ndimage.map_coordinates(raster, np.vstack([r, c]), order=order, mode="nearest")


def write_tile(path: Path, world, x0: float, y0: float, rng: np.random.Generator) -> int:
    import laspy

    n = rng.poisson(DENSITY * TILE_M * TILE_M)
    x, y = x0 + rng.uniform(0, TILE_M, n), y0 + rng.uniform(0, TILE_M, n)
    canopy = _sample(world.canopy.astype(np.float32), world, x, y, 0) > 0.5
    building = _sample(world.buildings.astype(np.float32), world, x, y, 0) > 0.5
    z = _sample(world.dsm, world, x, y)
    second = canopy & (rng.random(n) < CANOPY_SECOND)
    zg = _sample(world.dtm, world, x[second], y[second])
    noise = rng.random(n) < NOISE_SHARE
    xs, ys = np.concatenate([x, x[second]]), np.concatenate([y, y[second]])
    zs = np.concatenate([np.where(noise, z + rng.uniform(100, 400, n), z), zg])
    m = len(xs)
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = np.array([0.01, 0.01, 0.01])
    header.offsets = np.array([E0, N0, 0.0])
    las = laspy.LasData(header)
    las.x = xs + E0 + rng.normal(0, 0.1, m)
    las.y = ys + N0 + rng.normal(0, 0.1, m)
    las.z = zs + rng.normal(0, 0.05, m)
    las.return_number = np.concatenate([np.ones(n), np.full(second.sum(), 2)]).astype(np.uint8)
    las.number_of_returns = np.concatenate([np.where(second, 2, 1),
                                            np.full(second.sum(), 2)]).astype(np.uint8)
    cls = np.where(noise, 7, np.where(canopy, 5, np.where(building, 6, 2)))
    las.classification = np.concatenate([cls, np.full(second.sum(), 2)]).astype(np.uint8)
    las.write(str(path), do_compress=True, laz_backend=laspy.LazBackend.LazrsParallel)
    return m


def write_block(folder: Path, k: int, world, extent: float, rng: np.random.Generator) -> dict:
    half = extent / 2 - BLOCK_M
    cx, cy = rng.uniform(-half, half, 2)
    heading = rng.uniform(0, 360)
    a = np.radians(heading)
    u = rng.uniform(-BLOCK_M / 2, BLOCK_M / 2, (TIE_POINTS, 2))
    xy = np.column_stack([cx + u[:, 0] * np.cos(a) - u[:, 1] * np.sin(a),
                          cy + u[:, 0] * np.sin(a) + u[:, 1] * np.cos(a)])
    z = _sample(world.dsm, world, xy[:, 0], xy[:, 1])
    ref = np.column_stack([xy[:, 0] + E0, xy[:, 1] + N0, z])
    ref += rng.normal(0, [0.15, 0.15, 0.3], ref.shape)
    blunder = rng.random(TIE_POINTS) < 0.02
    ref[blunder, 2] += rng.choice([-1, 1], blunder.sum()) * rng.uniform(3, 60, blunder.sum())
    hidden = HiddenTransform.random(rng)
    T_mov_ref = hidden.T_mov_ref(np.array([cx + E0, cy + N0, float(np.median(z))]))
    mov = T_mov_ref.apply(ref)
    name = f"block{k:02d}"
    np.savetxt(folder / f"{name}.xyz", mov, fmt="%.4f")
    truth = {"block": name, "half": "dev" if k < N_BLOCKS // 2 else "held-out",
             "T_ref_mov": T_mov_ref.inverse.matrix.tolist(), "scale_model_per_m": hidden.scale,
             "heading_deg": heading, "centre": [cx + E0, cy + N0]}
    (folder / f"{name}.truth.json").write_text(json.dumps(truth, indent=1))
    return truth


def make_data(work: Path, tiles_per_side: int = 16) -> Path:
    out = work / "scale"
    done = out / "done.json"
    if done.is_file():
        return out
    (out / "tiles").mkdir(parents=True, exist_ok=True)
    (out / "blocks").mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    world = make_world("suburban", size_m=WORLD_M, cell=WORLD_CELL_M, seed=11)
    t_world = time.perf_counter() - t0
    extent = tiles_per_side * TILE_M
    rng = np.random.default_rng(5)
    points = 0
    for i in range(tiles_per_side):
        for j in range(tiles_per_side):
            x0, y0 = -extent / 2 + j * TILE_M, -extent / 2 + i * TILE_M
            path = out / "tiles" / f"tile_{i:02d}_{j:02d}.laz"
            points += write_tile(path, world, x0, y0, np.random.default_rng([5, i, j]))
        print(f"row {i + 1}/{tiles_per_side}: {points:,} points, "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
    truths = [write_block(out / "blocks", k, world, extent, rng) for k in range(N_BLOCKS)]
    done.write_text(json.dumps({"points": points, "tiles": tiles_per_side ** 2,
                                "extent_m": extent, "world_seconds": t_world,
                                "seconds": time.perf_counter() - t0, "blocks": len(truths)}))
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default=str(Path(__file__).parent / "work"))
    ap.add_argument("--tiles-per-side", type=int, default=16)
    a = ap.parse_args()
    print(make_data(Path(a.work), a.tiles_per_side))
