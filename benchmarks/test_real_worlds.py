"""Checks of the real-surface worlds (benchmarks/real_worlds.py); not part of the main suite.

    .venv/bin/python -m pytest -q benchmarks/test_real_worlds.py
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from real_worlds import (  # noqa: E402
    DATA,
    LOOKALIKE_KIND,
    REAL_WORLDS,
    load_real_world,
    real_scene_spec,
)

from tiereg.simulate.scene import make_scene  # noqa: E402
from tiereg.simulate.world import World  # noqa: E402

_WORLDS: dict[str, World] = {}


def world(name: str) -> World:
    if name not in _WORLDS:
        _WORLDS[name] = load_real_world(name)
    return _WORLDS[name]


def test_data_folder_is_small():
    total = sum(p.stat().st_size for p in DATA.iterdir() if p.is_file())
    assert total < 3e6


@pytest.mark.parametrize("name", REAL_WORLDS)
def test_world_is_local_metres_centred(name):
    w = world(name)
    rows, cols = w.shape
    assert w.x0 == pytest.approx(-cols * w.cell / 2) and w.y0 == pytest.approx(rows * w.cell / 2)
    assert np.isfinite(w.dsm).all() and w.dtm is w.dsm
    assert not w.canopy.any() and not w.buildings.any()
    assert w.ortho.dtype == np.float32 and 0.0 <= w.ortho.min() and w.ortho.max() <= 1.0
    assert len(w.corner_rc) == len(w.corner_response) > 1000
    spec = real_scene_spec(name, 0)
    assert spec.world_cell_m == pytest.approx(w.cell)
    assert spec.world_size_m == pytest.approx(min(rows, cols) * w.cell, rel=0.01)
    assert spec.lidar_size_m < spec.world_size_m


@pytest.mark.parametrize("overlap, min_ties", [(1.0, 400), (0.5, 350)])
@pytest.mark.parametrize("name", REAL_WORLDS)
def test_scene_ties_lie_on_the_surface(name, overlap, min_ties):
    w = world(name)
    scene = make_scene(real_scene_spec(name, 0, overlap=overlap), world=w)
    n = len(scene.moving)
    assert min_ties <= n <= 1500
    assert 50_000 < len(scene.lidar.xyz) < 3_000_000
    # the lidar square is barely wider than the block: overlap 1 is out of reach near 45 deg
    assert min(overlap, 0.75) - 0.05 <= scene.overlap <= overlap + 0.05

    back = scene.T_ref_mov.apply(scene.moving) - np.asarray(scene.spec.georef)
    good = ~scene.tie_points.blunder
    dz = back[good, 2] - w.sample("dsm", back[good, 0], back[good, 1])
    assert np.median(np.abs(dz)) < 0.5

    xmin, ymin, xmax, ymax = w.bounds
    assert ((back[:, 0] > xmin) & (back[:, 0] < xmax) & (back[:, 1] > ymin)
            & (back[:, 1] < ymax)).mean() > 0.95
    lidar = scene.lidar.xyz - np.asarray(scene.spec.georef)
    half = scene.spec.lidar_size_m / 2
    assert np.abs(lidar[:, :2]).max() < half + 1.0
    lz = w.sample("dsm", lidar[:, 0], lidar[:, 1])
    assert np.median(np.abs(lidar[:, 2] - lz)) < 0.5


@pytest.mark.parametrize("name", REAL_WORLDS)
def test_negative_scene_with_lookalike_tie_world(name):
    spec = replace(real_scene_spec(name, 0), kind=LOOKALIKE_KIND[name], tie_world_seed=1000)
    scene = make_scene(spec, world=world(name))
    assert scene.overlap == 0.0 and len(scene.moving) > 100


def test_unknown_name():
    with pytest.raises(ValueError):
        load_real_world("atlantis")
    with pytest.raises(ValueError):
        real_scene_spec("atlantis", 0)
