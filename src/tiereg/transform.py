"""A 3-D similarity transform (7-parameter Helmert) as a frozen value type.

Frames are explicit in names: ``T_ref_mov`` maps a point of the *moving* frame into the
*reference* frame, ``p_ref = T_ref_mov.apply(p_mov)``; composition follows the names,
``T_a_c = T_a_b @ T_b_c``.

The rotation convention is the photogrammetric one used in RESULT.json:
``T[:3, :3] = scale * Rz(kappa) @ Ry(phi) @ Rx(omega)``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import InputError

_ORTHO_TOL = 1e-6


def rotation_matrix(omega: float, phi: float, kappa: float) -> np.ndarray:
    """``Rz(kappa) @ Ry(phi) @ Rx(omega)`` for angles in radians."""
    co, so = np.cos(omega), np.sin(omega)
    cp, sp = np.cos(phi), np.sin(phi)
    ck, sk = np.cos(kappa), np.sin(kappa)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, co, -so], [0.0, so, co]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rz = np.array([[ck, -sk, 0.0], [sk, ck, 0.0], [0.0, 0.0, 1.0]])
    return rz @ ry @ rx


def rotation_matrices(omega: np.ndarray, phi: np.ndarray, kappa: np.ndarray) -> np.ndarray:
    """:func:`rotation_matrix` of each of ``K`` angle triples at once: ``(K, 3, 3)``."""
    omega, phi, kappa = (np.asarray(a, dtype=np.float64) for a in (omega, phi, kappa))
    co, so = np.cos(omega), np.sin(omega)
    cp, sp = np.cos(phi), np.sin(phi)
    ck, sk = np.cos(kappa), np.sin(kappa)
    one, zero = np.ones_like(co), np.zeros_like(co)
    rx = np.stack([one, zero, zero, zero, co, -so, zero, so, co], axis=-1).reshape(-1, 3, 3)
    ry = np.stack([cp, zero, sp, zero, one, zero, -sp, zero, cp], axis=-1).reshape(-1, 3, 3)
    rz = np.stack([ck, -sk, zero, sk, ck, zero, zero, zero, one], axis=-1).reshape(-1, 3, 3)
    return rz @ ry @ rx


@dataclass(frozen=True)
class Helmert7:
    """The seven parameters of a similarity: scale, rotations (radians) and translation."""

    scale: float
    omega: float
    phi: float
    kappa: float
    translation: tuple[float, float, float]

    def to_dict(self) -> dict[str, Any]:
        """The RESULT.json form: angles in degrees."""
        return {
            "scale": self.scale,
            "omega_deg": float(np.degrees(self.omega)),
            "phi_deg": float(np.degrees(self.phi)),
            "kappa_deg": float(np.degrees(self.kappa)),
            "translation": list(self.translation),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Helmert7:
        """Inverse of :meth:`to_dict`."""
        return cls(
            scale=float(d["scale"]),
            omega=float(np.radians(d["omega_deg"])),
            phi=float(np.radians(d["phi_deg"])),
            kappa=float(np.radians(d["kappa_deg"])),
            translation=tuple(float(v) for v in d["translation"]),  # type: ignore[arg-type]
        )


@dataclass(frozen=True, eq=False)
class Transform:
    """A 3-D similarity ``p' = s R p + t`` held as a 4x4 float64 matrix.

    The matrix is validated on construction: finite, last row ``[0, 0, 0, 1]``, upper-left block a
    positive scale times a proper rotation (``det > 0``). Instances are immutable; combine them with
    ``@`` and invert them with :attr:`inverse`.
    """

    matrix: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        m = np.array(self.matrix, dtype=np.float64, copy=True)
        if m.shape != (4, 4):
            raise InputError(f"a transform must be a 4x4 matrix, got shape {m.shape}")
        if not np.all(np.isfinite(m)):
            raise InputError("a transform matrix must hold finite numbers only")
        if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-12):
            raise InputError("the last row of a transform matrix must be [0, 0, 0, 1]")
        a = m[:3, :3]
        det = np.linalg.det(a)
        if det <= 0:
            raise InputError(
                "the transform's 3x3 block has det <= 0 (a reflection or collapse); "
                "tiereg handles similarities with positive scale only"
            )
        s = det ** (1.0 / 3.0)
        if not np.allclose(a.T @ a / s**2, np.eye(3), atol=_ORTHO_TOL):
            raise InputError(
                "the transform's 3x3 block is not a scaled rotation; "
                "give a similarity (scale, rotation, translation), not a general affine"
            )
        m[3] = (0.0, 0.0, 0.0, 1.0)
        m.setflags(write=False)
        object.__setattr__(self, "matrix", m)

    # -- construction ---------------------------------------------------------------------
    @classmethod
    def identity(cls) -> Transform:
        return cls(np.eye(4))

    @classmethod
    def from_translation(cls, translation: np.ndarray | tuple[float, float, float]) -> Transform:
        m = np.eye(4)
        m[:3, 3] = np.asarray(translation, dtype=np.float64).reshape(3)
        return cls(m)

    @classmethod
    def from_similarity(
        cls, scale: float, rotation: np.ndarray, translation: np.ndarray | tuple[float, ...]
    ) -> Transform:
        m = np.eye(4)
        m[:3, :3] = float(scale) * np.asarray(rotation, dtype=np.float64)
        m[:3, 3] = np.asarray(translation, dtype=np.float64).reshape(3)
        return cls(m)

    @classmethod
    def from_parameters(
        cls,
        *,
        scale: float = 1.0,
        omega: float = 0.0,
        phi: float = 0.0,
        kappa: float = 0.0,
        translation: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> Transform:
        """Build from the seven parameters; angles in radians."""
        return cls.from_similarity(scale, rotation_matrix(omega, phi, kappa), translation)

    @classmethod
    def from_helmert(cls, p: Helmert7) -> Transform:
        return cls.from_parameters(
            scale=p.scale, omega=p.omega, phi=p.phi, kappa=p.kappa, translation=p.translation
        )

    @classmethod
    def about(cls, centre: np.ndarray, T_local: Transform) -> Transform:
        """``T_local`` applied in coordinates centred on ``centre``: ``x -> T(x - c) + c``."""
        c = np.asarray(centre, dtype=np.float64).reshape(3)
        return cls.from_translation(c) @ T_local @ cls.from_translation(-c)

    # -- views ----------------------------------------------------------------------------
    @property
    def scale(self) -> float:
        return float(np.linalg.det(self.matrix[:3, :3]) ** (1.0 / 3.0))

    @property
    def rotation(self) -> np.ndarray:
        """The proper rotation matrix (3x3), scale removed."""
        return self.matrix[:3, :3] / self.scale

    @property
    def translation(self) -> np.ndarray:
        return self.matrix[:3, 3].copy()

    def parameters(self) -> Helmert7:
        """The seven parameters, with ``R = Rz(kappa) Ry(phi) Rx(omega)``.

        Angles come back in ``omega, kappa in (-pi, pi]`` and ``phi in [-pi/2, pi/2]``.
        """
        r = self.rotation
        phi = float(np.arctan2(-r[2, 0], np.hypot(r[0, 0], r[1, 0])))
        omega = float(np.arctan2(r[2, 1], r[2, 2]))
        kappa = float(np.arctan2(r[1, 0], r[0, 0]))
        t = self.matrix[:3, 3]
        omega, phi, kappa = (a + 0.0 for a in (omega, phi, kappa))  # no negative zeros
        return Helmert7(self.scale, omega, phi, kappa, (float(t[0]), float(t[1]), float(t[2])))

    # -- algebra --------------------------------------------------------------------------
    def __matmul__(self, other: Transform) -> Transform:
        if not isinstance(other, Transform):
            return NotImplemented
        return Transform(self.matrix @ other.matrix)

    @property
    def inverse(self) -> Transform:
        s = self.scale
        r_t = self.rotation.T
        m = np.eye(4)
        m[:3, :3] = r_t / s
        m[:3, 3] = -(r_t @ self.matrix[:3, 3]) / s
        return Transform(m)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map ``(N, 3)`` points; returns a new float64 array.

        The points are reduced to a local origin first, so coordinates in the millions keep their
        sub-millimetre digits: ``A p + t = A (p - o) + (A o + t)``.
        """
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise InputError(f"points must have shape (N, 3), got {p.shape}")
        if len(p) == 0:
            return p.copy()
        origin = np.round(p[0])
        a = self.matrix[:3, :3]
        shifted = (p - origin) @ a.T
        shifted += a @ origin + self.matrix[:3, 3]
        return shifted

    def isclose(self, other: Transform, *, atol_m: float = 1e-9, rtol: float = 1e-12) -> bool:
        return bool(np.allclose(self.matrix, other.matrix, atol=atol_m, rtol=rtol))

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        return np.array(self.matrix, dtype=dtype)

    def __repr__(self) -> str:
        p = self.parameters()
        return (
            f"Transform(scale={p.scale:.9g}, omega_deg={np.degrees(p.omega):.6g}, "
            f"phi_deg={np.degrees(p.phi):.6g}, kappa_deg={np.degrees(p.kappa):.6g}, "
            f"translation=({p.translation[0]:.6f}, {p.translation[1]:.6f}, "
            f"{p.translation[2]:.6f}))"
        )

    # -- exchange formats -------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the matrix (row-major lists) and the seven parameters."""
        return {"T_ref_mov": self.matrix.tolist(), "parameters": self.parameters().to_dict()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Transform:
        """Read the dict of :meth:`to_dict`, a RESULT.json, or ``{"matrix": ...}``."""
        for key in ("T_ref_mov", "matrix", "transform"):
            if key in d:
                return cls(np.asarray(d[key], dtype=np.float64))
        if "parameters" in d:
            return cls.from_helmert(Helmert7.from_dict(d["parameters"]))
        raise InputError(
            "no transform found: expected a 'T_ref_mov' (RESULT.json), 'matrix' or "
            "'parameters' entry"
        )

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    def to_pdal(self) -> str:
        """The 16 numbers of PDAL's ``filters.transformation`` ``matrix`` option (row-major)."""
        return " ".join(_fmt(v) for v in self.matrix.ravel())

    def to_cloudcompare(self) -> str:
        """A CloudCompare matrix file (``-APPLY_TRANS``): four lines of four numbers."""
        return "\n".join(" ".join(_fmt(v) for v in row) for row in self.matrix) + "\n"

    @classmethod
    def from_text(cls, text: str) -> Transform:
        """Parse 16 whitespace-separated numbers (PDAL or CloudCompare form); lines that start
        with ``#`` or ``//`` are comments."""
        lines = (ln for ln in text.splitlines() if not ln.lstrip().startswith(("#", "//")))
        try:
            values = [float(v) for v in " ".join(lines).replace(",", " ").split()]
        except ValueError as exc:
            raise InputError(f"a matrix text must hold 16 numbers: {exc}") from None
        if len(values) != 16:
            raise InputError(f"a matrix text must hold 16 numbers, found {len(values)}")
        return cls(np.asarray(values).reshape(4, 4))


def _fmt(v: float) -> str:
    return repr(float(v))
