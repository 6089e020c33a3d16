"""A synthetic airborne-lidar LAZ for the benchmarks, generated chunk by chunk and cached.

LAS 1.4, point format 6, 1 cm scales, UTM 32N coordinates (offsets 500000, 5000000, 0), 2 points
per m^2 over a 1.6:1 area (4 km x 2.5 km for 20 million points). Points come in acquisition
order: east-west flight strips flown alternately both ways with sidelap, zig-zag scan lines
across the track, increasing GPS time. Heights: a smooth random terrain, flat-roofed buildings,
forest with multiple returns, 3 cm noise and a few outliers (class 7).
"""

from __future__ import annotations

import json
import math
import os
import resource
import time
from pathlib import Path

import numpy as np

ORIGIN = (500_000.0, 5_000_000.0)  # lower-left corner of the area, UTM 32N metres
DENSITY = 2.0  # points per m^2
PULSE_HZ = 200_000.0
GEN_VERSION = 2  # bump when the generator changes so cached files are rebuilt


def _waves(rng, n, shortest, longest, rel_amp):
    """Random plane waves (kx, ky, phase, amplitude), log-uniform wavelengths."""
    lam = np.exp(rng.uniform(math.log(shortest), math.log(longest), n))
    theta, phase = rng.uniform(0, 2 * np.pi, (2, n))
    k = 2 * np.pi / lam
    return np.column_stack([k * np.cos(theta), k * np.sin(theta), phase, rel_amp * lam])


def _surface(waves, x, y):
    z = np.zeros(np.broadcast(x, y).shape)
    for kx, ky, phase, amp in waves:
        z += amp * np.cos(kx * x + ky * y + phase)
    return z


def _scene(rng, width, height):
    """Terrain waves, a 1 m map of absolute roof heights (NaN: none) and a 5 m forest mask."""
    terrain = _waves(rng, 24, 150.0, 4000.0, 0.008)
    roofs = np.full((int(height) + 1, int(width) + 1), np.nan, np.float32)
    for _ in range(int(width * height / 20_000)):  # about 50 buildings per km^2
        cx, cy = rng.uniform(0, width), rng.uniform(0, height)
        hx, hy = rng.uniform(4, 20, 2)
        top = 300.0 + _surface(terrain, cx, cy) + rng.uniform(4, 25)
        roofs[int(max(cy - hy, 0)):int(cy + hy), int(max(cx - hx, 0)):int(cx + hx)] = top
    gy, gx = np.mgrid[0:height + 5:5.0, 0:width + 5:5.0]
    field = _surface(_waves(rng, 12, 80.0, 1500.0, 1.0), gx, gy)
    return terrain, roofs, field > np.quantile(field, 0.7)  # about 30 % forest


def _acquisition(rng, width, height, n_points, chunk=1_000_000):
    """Yield blocks of scan lines in acquisition order: E-W strips flown alternately eastward
    and westward with 10 % sidelap on each side, zig-zag scan lines across the track."""
    n_strips = max(1, round(height / 500.0))
    swath = height / n_strips
    per_line = round(swath)  # about one point per metre across
    n_lines = math.ceil(n_points / (n_strips * per_line))
    spacing = width / n_lines
    step = max(1, chunk // per_line)
    for strip in range(n_strips):
        lo, hi = max(0.0, (strip - 0.1) * swath), min(height, (strip + 1.1) * swath)
        for j0 in range(0, n_lines, step):
            j = np.repeat(np.arange(j0, min(j0 + step, n_lines)), per_line)
            p = np.tile(np.arange(per_line), len(j) // per_line)  # order within a line
            frac = (np.where(j % 2 == 0, p, per_line - 1 - p) + 0.5) / per_line
            along = (j + 0.5 + rng.uniform(-0.3, 0.3, len(j))) * spacing
            x = along if strip % 2 == 0 else width - along
            y = np.clip(lo + frac * (hi - lo) + rng.normal(0, 0.2, len(j)), 0, height)
            t = 3.0e8 + strip * 300.0 + (j * per_line + p) / PULSE_HZ
            yield {"x": np.clip(x, 0, width), "y": y, "t": t, "strip": strip, "frac": frac,
                   "forward": j % 2 == 0, "edge": p == per_line - 1}


def _record(block, scene, header, rng):
    """One laspy point record for a block: heights, returns, classes, times."""
    import laspy

    terrain, roofs, forest_map = scene
    x, y = block["x"], block["y"]
    n = len(x)
    z = 300.0 + _surface(terrain, x, y)
    roof = roofs[y.astype(int), x.astype(int)]
    building = ~np.isnan(roof)
    forest = forest_map[(y / 5).astype(int), (x / 5).astype(int)] & ~building
    nret, ret = np.ones(n, np.uint8), np.ones(n, np.uint8)
    nret[forest] = rng.integers(2, 5, forest.sum())
    ret[forest] = rng.integers(1, nret[forest].astype(int) + 1)
    canopy = forest & (ret < nret)  # the last return of a pulse in forest is ground
    z[building] = roof[building]
    z[canopy] += rng.uniform(2, 25, canopy.sum())
    z += rng.normal(0, 0.03, n)
    cls = np.full(n, 2, np.uint8)
    cls[building], cls[canopy] = 6, 5
    noise = rng.random(n) < 5e-4
    z[noise] += rng.choice([-1.0, 1.0], noise.sum()) * rng.uniform(5, 60, noise.sum())
    cls[noise] = 7
    rec = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    rec.x, rec.y, rec.z = x + ORIGIN[0], y + ORIGIN[1], z
    rec.intensity = rng.integers(20, 2000, n)
    rec.return_number, rec.number_of_returns, rec.classification = ret, nret, cls
    rec.gps_time, rec.point_source_id = block["t"], np.full(n, block["strip"] + 1, np.uint16)
    rec.scan_angle = np.round((block["frac"] - 0.5) * 60.0 / 0.006).astype(np.int16)
    rec.scan_direction_flag, rec.edge_of_flight_line = block["forward"], block["edge"]
    return rec


def ensure_laz(work: Path, n_points: int, seed: int = 0) -> tuple[Path, dict]:
    """The cached synthetic LAZ of at least ``n_points`` points, generating it if needed."""
    import laspy
    import pyproj

    from tiereg.io.las import _backend

    work.mkdir(exist_ok=True)
    path = work / f"airborne_{n_points}_v{GEN_VERSION}.laz"
    meta_path = path.with_suffix(".json")
    if path.exists() and meta_path.exists():
        return path, json.loads(meta_path.read_text())
    print(f"generating {path} ...", flush=True)
    start = time.perf_counter()
    rng = np.random.default_rng(seed)
    height = math.sqrt(n_points / DENSITY / 1.6)  # a 1.6:1 area, e.g. 4 km x 2.5 km
    width = 1.6 * height
    scene = _scene(rng, width, height)
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales, header.offsets = np.full(3, 0.01), np.array([*ORIGIN, 0.0])
    header.add_crs(pyproj.CRS.from_epsg(32632))
    tmp = path.with_suffix(".tmp.laz")
    with laspy.open(tmp, mode="w", header=header, do_compress=True,
                    laz_backend=_backend()) as writer:
        for block in _acquisition(rng, width, height, n_points):
            writer.write_points(_record(block, scene, header, rng))
    seconds = time.perf_counter() - start
    os.replace(tmp, path)
    with laspy.open(path) as reader:
        count = int(reader.header.point_count)
    meta = {"points": count, "generation_s": round(seconds, 1),
            "generation_peak_rss_mb": round(
                resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6)}
    meta_path.write_text(json.dumps(meta))
    return path, meta
