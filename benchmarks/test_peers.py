"""Checks of the peer adapters (benchmarks/peers.py) on synthetic data; not part of the main suite.

    .venv/bin/python -m pytest benchmarks/test_peers.py
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from peers import (
    _SWAP,
    PEERS_IMAGE,
    _imreg_dft_matrix,
    run_open3d_fpfh_ransac,
    similarity_matrix,
    similarity_params,
)

ndimage = pytest.importorskip("scipy.ndimage")
transform = pytest.importorskip("skimage.transform")
# imreg_dft 2.0.0 imports the scipy.ndimage.interpolation namespace (deprecated, gone in SciPy 2)
pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def textured(n: int = 256, seed: int = 0) -> np.ndarray:
    """A dense image: smoothed random fields of two wavelengths plus raised rectangles."""
    rng = np.random.default_rng(seed)
    img = 200 * ndimage.gaussian_filter(rng.standard_normal((n, n)), 16)
    img += 40 * ndimage.gaussian_filter(rng.standard_normal((n, n)), 4)
    for _ in range(12):
        (r, c), (h, w) = rng.integers(0, n - 40, 2), rng.integers(8, 40, 2)
        img[r:r + h, c:c + w] += rng.uniform(2, 6)
    return img


def moving_from(ref: np.ndarray, H_ref_mov: np.ndarray, shape) -> np.ndarray:
    """Moving image whose pixel p shows ``ref`` at ``H_ref_mov @ p`` (NaN outside ``ref``)."""
    tform = transform.ProjectiveTransform(_SWAP @ H_ref_mov @ _SWAP)  # skimage uses (x, y)
    return transform.warp(ref, tform, output_shape=shape, order=1, cval=np.nan)


def errors(H: np.ndarray, H_true: np.ndarray, point) -> tuple[float, float, float]:
    """(angle error in degrees, relative scale error, pixel error at the moving ``point``)."""
    (a, s), (a0, s0) = similarity_params(H), similarity_params(H_true)
    p = np.array([*point, 1.0])
    return (abs((a - a0 + 180) % 360 - 180), abs(s / s0 - 1),
            float(np.hypot(*(H @ p - H_true @ p)[:2])))


def test_convention_of_the_synthetic_warp():
    """A blob at moving pixel p lands at reference pixel H @ p: the convention of every test."""
    ref = np.zeros((128, 128))
    ref[80, 40] = 1.0
    ref = ndimage.gaussian_filter(ref, 2)
    H = similarity_matrix(30, 1.2, (7, -12), centre=(63.5, 63.5))
    mov = np.nan_to_num(moving_from(ref, H, ref.shape))
    p = np.array([*ndimage.center_of_mass(mov), 1.0])
    assert np.allclose((H @ p)[:2], (80, 40), atol=0.2)
    angle, scale = similarity_params(H)
    assert math.isclose(angle, 30) and math.isclose(scale, 1.2)


@pytest.mark.parametrize("n", [64, 100, 256])
def test_imreg_dft_matrix_is_its_transform_img(n):
    """H from imreg_dft's (scale, angle, tvec) maps exactly as imreg_dft.transform_img does."""
    imreg_dft = pytest.importorskip("imreg_dft")
    rows, cols = np.mgrid[0:n, 0:n].astype(float)
    rng = np.random.default_rng(n)
    for _ in range(5):
        scale, angle, tvec = rng.uniform(0.55, 1.9), rng.uniform(-180, 180), rng.uniform(-9, 9, 2)
        H = _imreg_dft_matrix((n, n), scale, angle, tvec)
        r, c, inside = (imreg_dft.transform_img(img, scale, angle, tvec, bgval=0.0, order=1)
                        for img in (rows, cols, np.ones((n, n))))
        ok = inside > 1 - 1e-9  # output pixels interpolated from the image only
        assert ok.sum() > n  # output pixel p shows moving (r, c) there
        mapped = H @ np.stack([r[ok], c[ok], np.ones(ok.sum())])
        assert np.allclose(mapped[0], rows[ok], atol=1e-6)
        assert np.allclose(mapped[1], cols[ok], atol=1e-6)


CASES = {  # name: (angle, scale, shift, moving shape, seed)
    "square": (30.0, 1.2, (7.0, -12.0), (256, 256), 0),
    "flipped_nonsquare": (-150.0, 0.9, (5.0, -3.0), (180, 230), 0),
}
# The example's log-polar map has 360 / N degrees per row (1.4 at N = 256) and nearest-neighbour
# sampling: it is not held to 1 degree / 2 % off the specified case (see the benchmark report).
TOLERANCE = {"imreg_dft": (1.0, 0.02, 1.5), "skimage_fmt": (2.0, 0.03, 1.5)}


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("peer", PEERS_IMAGE)
def test_dense_image_is_recovered(peer, case):
    if peer == "imreg_dft":
        pytest.importorskip("imreg_dft")
    angle, scale, shift, shape, seed = CASES[case]
    ref = textured(256, seed)
    centre = np.array([(shape[0] - 1) / 2, (shape[1] - 1) / 2])
    H_true = similarity_matrix(angle, scale, centre=centre)  # about the moving centre ...
    H_true[:2, 2] += 127.5 - centre + np.asarray(shift)  # ... onto the reference centre + shift
    est = PEERS_IMAGE[peer](ref, moving_from(ref, H_true, shape))
    assert est.note == "" or "error" in est.note, est.note
    assert est.H_ref_mov.shape == (3, 3) and est.score is not None and est.seconds > 0
    d_angle, d_scale, d_px = errors(est.H_ref_mov, H_true, centre)
    tol = (1.0, 0.02, 1.5) if case == "square" else TOLERANCE[peer]
    assert d_angle <= tol[0] and d_scale <= tol[1] and d_px <= tol[2], (d_angle, d_scale, d_px)


@pytest.mark.parametrize("peer", PEERS_IMAGE)
def test_failure_is_reported_not_raised(peer):
    est = PEERS_IMAGE[peer](textured(64), np.full((32, 32), np.nan))
    assert np.array_equal(est.H_ref_mov, np.eye(3)) and est.score is None
    assert est.note


# --- Open3D -------------------------------------------------------------------------------------

OFFSET = np.array([500_000.0, 5_000_000.0, 300.0])  # UTM-like coordinates


def terrain_points(n: int, rng, size: float = 200.0, seed: int = 0) -> np.ndarray:
    """n points uniformly over a size x size m terrain with hills and flat-roofed blocks."""
    field_rng = np.random.default_rng(seed)
    field = 60 * ndimage.gaussian_filter(field_rng.standard_normal((64, 64)), 4)
    for _ in range(15):
        (r, c), (h, w) = field_rng.integers(0, 58, 2), field_rng.integers(2, 6, 2)
        field[r:r + h, c:c + w] += field_rng.uniform(5, 12)
    xy = rng.uniform(0, size, (n, 2))
    z = ndimage.map_coordinates(field, (xy / size * 63).T, order=1)
    return np.column_stack([xy, z]) + OFFSET


def similarity_3d(angle_deg: float, scale: float, shift) -> np.ndarray:
    a = math.radians(angle_deg)
    T = np.eye(4)
    T[:3, :3] = scale * np.array([[math.cos(a), -math.sin(a), 0],
                                  [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    T[:3, 3] = shift
    return T


def moving_cloud(n_ref: int, n_mov: int, T_ref_mov: np.ndarray, seed: int):
    rng = np.random.default_rng(seed)
    ref = terrain_points(n_ref, rng)
    mov_in_ref = terrain_points(n_mov, rng)
    keep = (mov_in_ref[:, 0] > OFFSET[0] + 30) & (mov_in_ref[:, 1] < OFFSET[1] + 170)
    mov_in_ref = mov_in_ref[keep]  # partial overlap
    inv = np.linalg.inv(T_ref_mov)
    return mov_in_ref @ inv[:3, :3].T + inv[:3, 3], ref


T_TRUE = similarity_3d(40.0, 1.0, OFFSET + (123.4, -56.7, 20.0)) @ similarity_3d(0, 1, -OFFSET)


def test_open3d_easy_case_same_density():
    pytest.importorskip("open3d")
    mov, ref = moving_cloud(20_000, 20_000, T_TRUE, seed=3)  # 1 point per 2 m^2 on both sides
    est = run_open3d_fpfh_ransac(mov, ref, voxel=2.0, seed=1)
    assert est.T_ref_mov.shape == (4, 4) and est.score is not None and est.score > 0.5, est.note
    R = est.T_ref_mov[:3, :3]
    assert abs(math.degrees(math.atan2(R[1, 0], R[0, 0])) - 40.0) < 2.0
    assert abs(np.cbrt(np.linalg.det(R)) - 1.0) < 0.03
    centre = mov.mean(axis=0)
    mapped = est.T_ref_mov[:3, :3] @ centre + est.T_ref_mov[:3, 3]
    assert np.linalg.norm(mapped - (T_TRUE[:3, :3] @ centre + T_TRUE[:3, 3])) < 3.0


def test_open3d_runs_at_a_1_to_1000_density_ratio():
    pytest.importorskip("open3d")
    mov, ref = moving_cloud(300_000, 300, T_TRUE, seed=4)
    est = run_open3d_fpfh_ransac(mov, ref, voxel=2.0, seed=1)
    assert est.T_ref_mov.shape == (4, 4) and np.isfinite(est.T_ref_mov).all(), est.note
    assert est.seconds > 0


def test_open3d_missing_gives_a_note(monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)  # makes `import open3d` raise ImportError
    est = run_open3d_fpfh_ransac(np.zeros((5, 3)), np.zeros((5, 3)), voxel=1.0)
    assert np.array_equal(est.T_ref_mov, np.eye(4)) and est.score is None
    assert "Open3D unavailable" in est.note
