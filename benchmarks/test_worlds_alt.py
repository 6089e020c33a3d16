"""Checks of the second world generator and its sensors (worlds_alt.py, sensors_alt.py) and of the
verdict benchmark's case list; not part of the main suite, a few seconds in all.

    .venv/bin/python -m pytest -q benchmarks/test_worlds_alt.py
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))

from sensors_alt import (  # noqa: E402
    GEOREF,
    T_mov_ref,
    add_spikes,
    fly_lidar,
    in_block,
    sample_ties,
    write_laz,
)
from verdict_cases import (  # noqa: E402
    GENERATORS,
    MAX_LIDAR_POINTS,
    REAL,
    all_cases,
)
from worlds_alt import FAMILIES, make_alt_world  # noqa: E402
from worlds_alt_parts import diamond_square, foerstner_corners, value_noise  # noqa: E402

from tiereg.simulate import World  # noqa: E402

_WORLDS: dict[str, object] = {}


def alt(family: str):
    if family not in _WORLDS:
        _WORLDS[family] = make_alt_world(family, size_m=400.0, cell=1.0, seed=3)
    return _WORLDS[family]


def flat_world(size: int = 200, cell: float = 1.0) -> World:
    dtm = np.full((size, size), 100.0)
    dsm = dtm.copy()
    dsm[50:80, 50:90] += 8.0  # a building
    canopy = np.zeros((size, size), bool)
    canopy[120:160, 120:160] = True
    dsm[canopy] += 15.0
    buildings = dsm - dtm == 8.0
    ortho = np.zeros((size, size), np.float32)
    rc = np.argwhere(np.ones((size, size), bool))[::7]
    half = size * cell / 2
    return World("flat", cell, -half, half, dtm, dsm, ortho, canopy, buildings, rc,
                 np.ones(len(rc)))


def test_midpoint_displacement_is_unit_normalised_and_reproducible():
    a = diamond_square(6, 0.8, np.random.default_rng(1))
    b = diamond_square(6, 0.8, np.random.default_rng(1))
    assert a.shape == (65, 65)
    assert np.array_equal(a, b)
    assert a.mean() == pytest.approx(0, abs=1e-9) and a.std() == pytest.approx(1, rel=1e-9)
    # rougher (smaller Hurst exponent) fields change more from one cell to the next
    rough = diamond_square(6, 0.3, np.random.default_rng(1))
    assert np.abs(np.diff(rough)).mean() > np.abs(np.diff(a)).mean()


def test_value_noise_has_its_wavelength():
    v = value_noise(400, 1.0, 50.0, np.random.default_rng(0))
    assert v.shape == (400, 400) and v.std() == pytest.approx(1, rel=1e-3)
    # neighbours a tenth of a wavelength apart are strongly correlated, two wavelengths not
    near = np.corrcoef(v[:, :-5].ravel(), v[:, 5:].ravel())[0, 1]
    far = np.corrcoef(v[:, :-100].ravel(), v[:, 100:].ravel())[0, 1]
    assert near > 0.9 and abs(far) < 0.2


def test_foerstner_finds_the_corners_of_a_square():
    img = np.zeros((80, 80), np.float32)
    img[20:60, 25:55] = 1.0
    rc, w = foerstner_corners(img)
    truth = np.array([[20, 25], [20, 54], [59, 25], [59, 54]])
    assert len(rc) == 4 and np.all(w > 0)
    d = np.linalg.norm(rc[:, None, :] - truth[None], axis=2).min(axis=0)
    assert np.all(d <= 1.5)


@pytest.mark.parametrize("family", FAMILIES)
def test_world_rasters_are_consistent(family):
    a = alt(family)
    w = a.world
    assert w.kind == family and w.shape == (400, 400) and w.cell == 1.0
    assert w.x0 == -200 and w.y0 == 200
    assert np.all(np.isfinite(w.dsm)) and np.all(w.dsm >= w.dtm - 1e-9)
    assert w.ortho.dtype == np.float32 and 0 <= w.ortho.min() and w.ortho.max() <= 1
    assert np.all(w.dsm[w.buildings] - w.dtm[w.buildings] > 2.0)
    assert np.all(w.dsm[w.canopy] - w.dtm[w.canopy] > 1.0)
    assert not np.any(w.buildings & a.water) and not np.any(w.canopy & a.water)
    assert len(w.corner_rc) == len(w.corner_response) > 200  # > 1,250 per km^2
    labels, k = ndimage.label(a.water)
    for i in range(1, k + 1):  # every lake is flat
        assert np.ptp(w.dsm[labels == i]) < 1e-9


def test_families_differ_in_what_stands_on_the_ground():
    relief = {f: np.ptp(alt(f).world.dtm) for f in FAMILIES}
    assert relief["mountains"] > 5 * relief["farmland"]
    cover = {f: alt(f).world.canopy.mean() for f in FAMILIES}
    built = {f: alt(f).world.buildings.mean() for f in FAMILIES}
    assert cover["forest"] > 0.5 and cover["forest"] > max(cover[f] for f in FAMILIES
                                                           if f != "forest")
    assert built["urban"] > 0.08 and built["urban"] > 3 * built["forest"]


def test_ties_lie_on_the_surface_inside_the_block():
    w = flat_world()
    rng = np.random.default_rng(0)
    corners = (w.corner_rc, w.corner_response)
    ties = sample_ties(w, corners, centre=(10.0, -5.0), side_m=100, aspect=1.4, heading_deg=30,
                       n=500, noise_z_m=0.0, blunder_fraction=0.0, blunder_max_m=10, rng=rng)
    assert len(ties.xyz) == 500 and not ties.blunder.any()
    inside, _ = in_block(ties.xyz, (10.0, -5.0), 100, 1.4, 30)
    assert inside.all()
    r = ((w.y0 - ties.xyz[:, 1]) / w.cell).astype(int)
    c = ((ties.xyz[:, 0] - w.x0) / w.cell).astype(int)
    assert np.array_equal(ties.xyz[:, 2], w.dsm[r, c])  # the cell's height: roof or ground
    noisy = sample_ties(w, corners, centre=(0.0, 0.0), side_m=150, aspect=1.0, heading_deg=0,
                        n=2000, noise_z_m=0.3, blunder_fraction=0.05, blunder_max_m=20,
                        rng=np.random.default_rng(1))
    dz = noisy.xyz[:, 2] - noisy.true_xyz[:, 2]
    assert np.std(dz[~noisy.blunder]) == pytest.approx(0.3, rel=0.1)
    assert noisy.blunder.mean() == pytest.approx(0.05, abs=0.015)
    assert np.all(np.abs(dz[noisy.blunder]) > 1.0) and np.all(np.abs(dz) < 21)


def test_lidar_density_returns_and_classes():
    w = flat_world()
    lidar = fly_lidar(w, None, centre=(0.0, 0.0), side_m=180, density=4.0, heading_deg=20,
                      rng=np.random.default_rng(2))
    first = lidar.return_number == 1
    assert first.sum() / 180**2 == pytest.approx(4.0, rel=0.15)
    assert np.all(np.abs(lidar.xyz[:, :2]) < 90.5)
    on_roof = lidar.classification == 6
    x, y = lidar.xyz[:, 0], lidar.xyz[:, 1]
    inner = (x > -48) & (x < -12) & (y > 22) & (y < 48)  # the roof less 2 m at its walls
    assert on_roof[inner].all() and np.abs(lidar.xyz[inner, 2] - 108).max() < 0.3
    last = lidar.return_number == 2
    assert last.any() and np.all(lidar.classification[last] == 2)
    assert np.abs(lidar.xyz[last, 2] - 100).max() < 0.3  # under the canopy, on the ground
    spiked = add_spikes(lidar, 0.01, np.random.default_rng(3))
    new = slice(len(lidar), None)
    assert len(spiked) - len(lidar) == round(0.01 * len(lidar))
    assert np.all(spiked.classification[new] == 1)
    assert np.all(spiked.xyz[new, 2] > 100 + 19) and np.all(spiked.xyz[new, 2] < 100 + 1530)


def test_water_returns_few_points():
    w = flat_world()
    water = np.zeros(w.shape, bool)
    water[:, :40] = True  # x < -60 m: nothing stands there
    lidar = fly_lidar(w, water, centre=(0.0, 0.0), side_m=180, density=2.0, heading_deg=0,
                      rng=np.random.default_rng(4), water_returns=0.1)
    x = lidar.xyz[:, 0]
    west, east = x < -61, (x > -59) & (x < -29)  # two strips of 30 m x 180 m
    assert 0.05 < west.sum() / east.sum() < 0.15
    assert np.all(lidar.classification[west] == 9)


def test_laz_round_trip_keeps_crs_and_millimetres(tmp_path):
    import laspy

    w = flat_world(100)
    lidar = fly_lidar(w, None, centre=(0.0, 0.0), side_m=90, density=1.0, heading_deg=0,
                      rng=np.random.default_rng(5))
    lidar = replace(lidar, xyz=lidar.xyz + np.asarray(GEOREF))
    path = write_laz(tmp_path / "ref.laz", lidar)
    las = laspy.read(path)
    assert las.header.parse_crs().to_epsg() == 32632
    xyz = np.column_stack([las.x, las.y, las.z])
    assert np.abs(xyz - lidar.xyz).max() <= 0.0006
    assert np.array_equal(np.asarray(las.classification), lidar.classification)
    assert not (tmp_path / "ref.tmp.laz").exists()


def test_hidden_transform_is_a_similarity_about_the_centre():
    c = np.array([500_100.0, 5_000_200.0, 320.0])
    T = T_mov_ref(c, heading_deg=130, scale=3.2808, tilt_deg=(0.2, -0.1),
                  model_origin=(10.0, 20.0, 5.0))
    assert np.allclose(T.apply(c[None])[0], [10, 20, 5])
    p = T.parameters()
    assert p.scale == pytest.approx(3.2808) and np.degrees(p.kappa) == pytest.approx(130)
    pts = c + np.random.default_rng(0).normal(0, 100, (20, 3))
    assert np.allclose(T.inverse.apply(T.apply(pts)), pts, atol=1e-6)


def test_verdict_cases_are_fixed_split_and_within_the_ranges():
    cases = all_cases()
    assert cases == all_cases() and len(cases) >= 240
    assert len({c.case_id for c in cases}) == len(cases)
    dev = [c for c in cases if c.half == "dev"]
    held = [c for c in cases if c.half == "heldout"]
    assert len(dev) == len(held)
    assert max(c.seed for c in dev) < 500 <= 1000 <= min(c.seed for c in held)
    synthetic = [c for c in cases if c.family not in REAL]
    for g in GENERATORS:
        share = sum(c.generator == g for c in synthetic) / len(synthetic)
        assert share == pytest.approx(0.5, abs=0.05)
    assert 0.08 <= sum(bool(c.negative) for c in cases) / len(cases) <= 0.12
    assert any(c.spikes_fraction > 0 for c in dev) and any(c.spikes_fraction > 0 for c in held)
    for c in cases:
        assert c.lidar_density * c.lidar_m**2 <= MAX_LIDAR_POINTS * 1.0001
        assert c.block_m >= c.lidar_m / 4 - 1e-6
        assert 0.1 <= c.noise_z_m <= 0.5 and 0 <= c.blunder_fraction <= 0.05
        assert 0.25 <= c.scale <= 4 and 0.5 <= c.overlap <= 1
        if c.family not in REAL:
            assert 0.5 <= c.lidar_density <= 8 and 300 <= c.n_target <= 6000
            assert c.world_m >= c.lidar_m + c.block_m
    scales = {round(c.scale, 4) for c in cases}
    assert {3.2808, 0.25, 4.0} <= scales
