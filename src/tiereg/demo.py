"""The embedded demo: real lidar, tie points made from it with a known transform, registered back.

Real tie points are sparser than these (about 350 per km^2); the shipped lidar sample covers only
about 0.06 km^2, so the demo's block is denser to keep enough cells for correlation.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from .io import open_points
from .io.base import write_text_atomic
from .io.text import write_xyz
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


@dataclass(frozen=True)
class DemoOutcome:
    result: RegistrationResult
    T_ref_mov_true: Transform
    error: np.ndarray  # recovered - true position of the tie-point centroid (file units)
    error_cells: float  # horizontal error in grid cells
    block_centre_true: np.ndarray  # the tie-point centroid mapped by the truth
    block_centre_est: np.ndarray  # ... and by the result
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


def run_demo(out_dir: str | Path, *, seed: int = 0,
             progress: ProgressFactory | None = None) -> DemoOutcome:
    """Make the tie points, register them to the sample lidar, write the outputs to ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    lidar_path = sample_lidar()
    lidar = open_points(lidar_path)
    tie = make_tie_points(lidar.read().xyz, seed=seed)
    tie_path = out / "tiepoints.xyz"
    write_xyz(tie_path, tie)
    truth = TRUTH.inverse
    write_text_atomic(out / "truth.json", json.dumps(truth.to_dict(), indent=2) + "\n")
    result = register(tie_path, lidar, progress=progress)
    write_text_atomic(out / "RESULT.json", result.to_json() + "\n")
    report = write_report(result, out / "report")
    centre = tie.mean(axis=0, keepdims=True)
    c_true, c_est = truth.apply(centre)[0], result.T_ref_mov.apply(centre)[0]
    error = c_est - c_true
    return DemoOutcome(result, truth, error, float(np.hypot(error[0], error[1]) / result.cell_size),
                       c_true, c_est, report)
