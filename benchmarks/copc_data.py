"""COPC copies of the scale benchmark's LAZ tiles, for benchmarks/copc.py (made once).

Each tile's points are written, unchanged (the same point records, scales and offsets), into a
COPC octree with copc-lib: a cube around the tile's points, 128 voxels a side at the root
(the customary root spacing), each level halving the voxel; a level takes one point of each
voxel not yet taken by a coarser one (in a random order, seeded), and the level at which no
voxel holds two points takes what is left. So the levels down to any spacing are an even
sample of the tile at about that spacing, as COPC writers make them.

    python benchmarks/copc_data.py [--tiles N]   # the first N tiles of benchmarks/work/scale
"""

from __future__ import annotations

import argparse
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
SCALE = HERE / "work" / "scale"
OUT = SCALE / "copc"
ROOT_VOXELS = 128  # voxels a side of the root node's cube
MAX_LEVEL = 12


def octree_levels(xyz: np.ndarray, centre: np.ndarray, halfsize: float,
                  seed: int = 0) -> list[tuple[int, np.ndarray]]:
    """``(level, indices)`` of the points each level of the octree holds (every point once)."""
    rng = np.random.default_rng(seed)
    left = rng.permutation(len(xyz))
    corner = centre - halfsize
    out = []
    for level in range(MAX_LEVEL + 1):
        if not len(left):
            break
        voxel = 2.0 * halfsize / ROOT_VOXELS / 2**level
        _, first = np.unique(_flat(np.floor((xyz[left] - corner) / voxel)), return_index=True)
        if len(first) == len(left) or level == MAX_LEVEL:
            out.append((level, left))
            break
        out.append((level, left[first]))
        rest = np.ones(len(left), bool)
        rest[first] = False
        left = left[rest]
    return out


def _flat(q: np.ndarray) -> np.ndarray:
    """Integer voxel coordinates ``(n, 3)`` (below 2**20 each) as one int64 key per row."""
    q = q.astype(np.int64)
    return (q[:, 0] << 40) | (q[:, 1] << 20) | q[:, 2]


def write_copc(src: Path, dst: Path) -> int:
    """``src`` (LAS/LAZ, point format 6-8) as the COPC file ``dst``; returns its points."""
    import copclib as copc
    import laspy

    las = laspy.read(src)
    if las.header.point_format.id not in (6, 7, 8):
        raise ValueError(f"{src}: COPC takes point formats 6-8, not {las.header.point_format.id}")
    xyz = np.column_stack([las.x, las.y, las.z])
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    centre = (lo + hi) / 2.0
    halfsize = float((hi - lo).max()) / 2.0 + 1e-3
    config = copc.CopcConfigWriter(las.header.point_format.id,
                                   copc.Vector3(las.header.scales.tolist()),
                                   copc.Vector3(las.header.offsets.tolist()))
    tmp = dst.with_suffix(".part")
    writer = copc.FileWriter(str(tmp), config)
    header, info = writer.copc_config.las_header, writer.copc_config.copc_info
    header.min, header.max = copc.Vector3(lo.tolist()), copc.Vector3(hi.tolist())
    info.center_x, info.center_y, info.center_z = map(float, centre)
    info.halfsize, info.spacing = halfsize, 2.0 * halfsize / ROOT_VOXELS
    records = las.points.array
    for level, idx in octree_levels(xyz, centre, halfsize):
        node = np.floor((xyz[idx] - (centre - halfsize)) / (2.0 * halfsize / 2**level))
        flat = _flat(node)
        order = np.argsort(flat, kind="stable")
        _, starts = np.unique(flat[order], return_index=True)
        for start, end in zip(starts, [*starts[1:], len(order)]):
            sel = idx[order[start:end]]
            raw = np.ascontiguousarray(records[sel]).view(np.int8).ravel()
            key = node[order[start]].astype(np.int64)
            writer.AddNode(copc.VoxelKey(level, *map(int, key)), copc.VectorChar(raw))
    writer.Close()
    tmp.replace(dst)
    return len(xyz)


def _one(src: Path) -> int:
    dst = OUT / src.name.replace(".laz", ".copc.laz")
    if dst.is_file():
        import laspy

        with laspy.open(dst) as r:
            return int(r.header.point_count)
    return write_copc(src, dst)


def make_copc(n_tiles: int, processes: int = 2) -> list[Path]:
    OUT.mkdir(parents=True, exist_ok=True)
    tiles = sorted((SCALE / "tiles").glob("*.laz"))[:n_tiles]
    if len(tiles) < n_tiles:
        raise SystemExit("make the scale benchmark's tiles first: python benchmarks/scale_data.py")
    t0 = time.perf_counter()
    with Pool(processes) as pool:
        points = pool.map(_one, tiles)
    print(f"{len(tiles)} COPC tiles, {sum(points):,} points, {time.perf_counter() - t0:.0f} s")
    return [OUT / t.name.replace(".laz", ".copc.laz") for t in tiles]


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tiles", type=int, default=64)
    ap.add_argument("--processes", type=int, default=2)
    a = ap.parse_args()
    make_copc(a.tiles, a.processes)
