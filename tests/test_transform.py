"""Transform: algebra, parameters, precision near projected coordinates, exchange formats."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tiereg import InputError, Transform
from tiereg.transform import rotation_matrices, rotation_matrix

angles = st.floats(-np.pi + 1e-3, np.pi - 1e-3)
small = st.floats(-1.4, 1.4)  # phi kept away from +-90 deg, where omega and kappa mix
scales = st.floats(0.2, 5.0)
shifts = st.tuples(*(st.floats(-1e6, 1e6) for _ in range(3)))


def make(scale, omega, phi, kappa, t):
    return Transform.from_parameters(scale=scale, omega=omega, phi=phi, kappa=kappa,
                                     translation=t)


@settings(max_examples=200, deadline=None)
@given(scales, angles, small, angles, shifts)
def test_parameters_round_trip(scale, omega, phi, kappa, t):
    T = make(scale, omega, phi, kappa, t)
    p = T.parameters()
    assert p.scale == pytest.approx(scale, rel=1e-12)
    assert p.omega == pytest.approx(omega, abs=1e-9)
    assert p.phi == pytest.approx(phi, abs=1e-9)
    assert p.kappa == pytest.approx(kappa, abs=1e-9)
    assert np.allclose(p.translation, t, rtol=0, atol=1e-9 * max(1.0, np.abs(t).max()))
    assert Transform.from_helmert(p).isclose(T, atol_m=1e-6)


@settings(max_examples=200, deadline=None)
@given(scales, angles, small, angles, shifts)
def test_inverse_and_det(scale, omega, phi, kappa, t):
    T = make(scale, omega, phi, kappa, t)
    assert np.linalg.det(T.matrix[:3, :3]) > 0
    ident = (T @ T.inverse).matrix
    assert np.allclose(ident[:3, :3], np.eye(3), atol=1e-12)
    # the translation part of T T^-1 is a difference of numbers up to 1e6 * 5
    assert np.allclose(ident[:3, 3], 0.0, atol=1e-8)


@settings(max_examples=100, deadline=None)
@given(scales, angles, small, angles, shifts, scales, angles, shifts)
def test_composition_follows_frames(s1, o1, p1, k1, t1, s2, k2, t2):
    T_a_b = make(s1, o1, p1, k1, t1)
    T_b_c = make(s2, 0.0, 0.0, k2, t2)
    pts = np.random.default_rng(0).uniform(-1000, 1000, (20, 3))
    via = T_a_b.apply(T_b_c.apply(pts))
    direct = (T_a_b @ T_b_c).apply(pts)
    assert np.allclose(via, direct, rtol=0, atol=1e-6 * max(1.0, np.abs(via).max() * 1e-6))


def test_rotation_convention_matches_contract():
    # RESULT.json: T[:3,:3] = scale * Rz(kappa) @ Ry(phi) @ Rx(omega)
    T = Transform.from_parameters(kappa=np.radians(90))
    assert np.allclose(T.apply([[1.0, 0.0, 0.0]]), [[0.0, 1.0, 0.0]], atol=1e-15)
    T = Transform.from_parameters(omega=np.radians(90))  # about x: y -> z
    assert np.allclose(T.apply([[0.0, 1.0, 0.0]]), [[0.0, 0.0, 1.0]], atol=1e-15)
    T = Transform.from_parameters(phi=np.radians(90))  # about y: z -> x
    assert np.allclose(T.apply([[0.0, 0.0, 1.0]]), [[1.0, 0.0, 0.0]], atol=1e-15)


def test_apply_keeps_millimetres_at_projected_coordinates():
    # points near 500,000 / 5,000,000 with sub-millimetre digits, a rotation about the block
    rng = np.random.default_rng(1)
    pts = np.column_stack([500_000 + rng.uniform(0, 3000, 1000),
                           5_000_000 + rng.uniform(0, 3000, 1000), rng.uniform(100, 400, 1000)])
    pts = np.round(pts, 4)
    centre = pts.mean(axis=0)
    T = Transform.about(centre, Transform.from_parameters(kappa=0.3, scale=1.0001))
    back = T.inverse.apply(T.apply(pts))
    assert np.abs(back - pts).max() < 1e-6  # 1 micrometre
    # the same map computed in local coordinates, exactly
    local = pts - centre
    expected = 1.0001 * local @ rotation_matrix(0, 0, 0.3).T + centre
    assert np.abs(T.apply(pts) - expected).max() < 1e-6


def test_json_round_trip_is_exact():
    T = Transform.from_parameters(scale=0.3048, kappa=1.234, omega=0.01, phi=-0.02,
                                  translation=(512345.6789, 5012345.6789, 123.4567))
    back = Transform.from_dict(json.loads(T.to_json()))
    assert np.array_equal(back.matrix, T.matrix)


def test_pdal_and_cloudcompare_strings():
    T = Transform.from_parameters(kappa=0.5, translation=(500000.125, 5000000.25, 10.5))
    pdal = T.to_pdal()
    assert len(pdal.split()) == 16
    assert np.array_equal(Transform.from_text(pdal).matrix, T.matrix)
    cc = T.to_cloudcompare()
    assert len(cc.strip().splitlines()) == 4
    assert np.array_equal(Transform.from_text(cc).matrix, T.matrix)
    commented = f"# exported 2026-12-03\n// the model to the lidar\n{cc}\n# end\n"
    assert np.array_equal(Transform.from_text(commented).matrix, T.matrix)


@pytest.mark.parametrize(
    "matrix, fragment",
    [
        (np.eye(3), "4x4"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "det <= 0"),
        (np.diag([1.0, 2.0, 1.0, 1.0]), "not a scaled rotation"),
        (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [1, 0, 0, 1.0]]), "last row"),
        (np.full((4, 4), np.nan), "finite"),
    ],
)
def test_invalid_matrices_are_rejected(matrix, fragment):
    with pytest.raises(InputError, match=fragment):
        Transform(matrix)


def test_immutable():
    T = Transform.identity()
    with pytest.raises(ValueError):
        T.matrix[0, 3] = 5.0


def test_rotation_matrices_are_rotation_matrix_of_each_triple():
    rng = np.random.default_rng(5)
    angles = rng.uniform(-np.pi, np.pi, (50, 3))
    got = rotation_matrices(angles[:, 0], angles[:, 1], angles[:, 2])
    assert got.shape == (50, 3, 3)
    for (omega, phi, kappa), R in zip(angles, got):
        assert np.allclose(R, rotation_matrix(omega, phi, kappa), rtol=0, atol=1e-15)
