"""The embedded demo: a real structure-from-motion model registered to real lidar.

``data/autzen_colmap`` is what pycolmap made of twelve images rendered over the shipped lidar
sample (``data/autzen_trim.laz``, Autzen 2010, international feet): a COLMAP model in COLMAP's own
gauge (about 73 feet per model unit, upside down), with the true model -> lidar similarity in
``truth.json``. The demo registers the model with no initial guess and compares with the truth.

:func:`make_tie_points` makes simpler tie points, lidar samples under a known shift, for tests.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from .io import open_points
from .io.base import write_text_atomic
from .pipeline import RegistrationResult, register
from .progress import ProgressFactory
from .report import Report, write_report
from .transform import Transform

N_TIE_POINTS = 1500
BLUNDER_FRACTION = 0.02
NOISE_XY = 0.15  # file units (feet): horizontal tie-point noise
NOISE_Z = 0.3  # vertical noise
TRUTH = Transform.from_translation((-1520.25, 830.75, -37.5))  # T_mov_ref: into the model frame


def sample_lidar() -> Path:
    """Path of the packaged lidar sample (Autzen, 110,000 points, LAZ)."""
    return Path(str(resources.files("tiereg") / "data" / "autzen_trim.laz"))


def sample_model() -> Path:
    """Path of the packaged COLMAP model of the lidar sample (``cameras.bin``, ...)."""
    return Path(str(resources.files("tiereg") / "data" / "autzen_colmap"))


def sample_model_truth() -> tuple[Transform, float]:
    """The sample model's true ``T_ref_mov`` and its ground sampling distance (feet)."""
    d = json.loads((sample_model() / "truth.json").read_text())
    return Transform(np.asarray(d["T_ref_mov"], dtype=np.float64)), float(d["gsd"])


@dataclass(frozen=True)
class DemoOutcome:
    result: RegistrationResult
    T_ref_mov_true: Transform
    error: np.ndarray  # recovered - true position of the model's centroid (file units, feet)
    error_cells: float  # horizontal error in grid cells
    block_centre_true: np.ndarray  # the model's centroid mapped by the truth
    block_centre_est: np.ndarray  # ... and by the result
    rotation_error_deg: float  # angle of R_est R_true^T
    rms_gsd: float  # RMS of |T_est p - T_true p| over the model's points, in GSD
    gsd: float  # the images' ground sampling distance (feet)
    n_points: int
    report: Report


def make_tie_points(lidar_xyz: np.ndarray, *, seed: int = 0) -> np.ndarray:
    """Tie points in the model frame: lidar samples in a sub-block, noisy, with blunders."""
    rng = np.random.default_rng(seed)
    lo, hi = lidar_xyz[:, :2].min(axis=0), lidar_xyz[:, :2].max(axis=0)
    ext = hi - lo
    inside = np.all((lidar_xyz[:, :2] > lo + [0.20, 0.05] * ext)
                    & (lidar_xyz[:, :2] < hi - [0.05, 0.20] * ext), axis=1)
    pick = rng.choice(np.flatnonzero(inside), N_TIE_POINTS, replace=False)
    tie = lidar_xyz[pick] + rng.normal(0.0, [NOISE_XY, NOISE_XY, NOISE_Z], (N_TIE_POINTS, 3))
    blunders = rng.random(N_TIE_POINTS) < BLUNDER_FRACTION
    tie[blunders, 2] += rng.normal(0.0, 30.0, int(blunders.sum()))
    return TRUTH.apply(tie)


def run_demo(out_dir: str | Path, *, progress: ProgressFactory | None = None) -> DemoOutcome:
    """Register the sample COLMAP model to the sample lidar, write ``RESULT.json``,
    ``truth.json`` and the report to ``out_dir``, and compare with the truth."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    model, lidar = sample_model(), sample_lidar()
    truth, gsd = sample_model_truth()
    write_text_atomic(out / "truth.json", json.dumps(truth.to_dict(), indent=2) + "\n")
    result = register(model, lidar, progress=progress)
    write_text_atomic(out / "RESULT.json", result.to_json() + "\n")
    report = write_report(result, out / "report")
    xyz = open_points(model).read().xyz
    centre = xyz.mean(axis=0, keepdims=True)
    c_true, c_est = truth.apply(centre)[0], result.T_ref_mov.apply(centre)[0]
    error = c_est - c_true
    R = result.T_ref_mov.rotation @ truth.rotation.T
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
    err = np.linalg.norm(result.T_ref_mov.apply(xyz) - truth.apply(xyz), axis=1)
    return DemoOutcome(result, truth, error, float(np.hypot(error[0], error[1]) / result.cell_size),
                       c_true, c_est, angle, float(np.sqrt(np.mean(err**2)) / gsd), gsd,
                       len(xyz), report)
