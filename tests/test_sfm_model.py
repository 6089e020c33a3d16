"""A real structure-from-motion model registered to the shipped lidar.

``tiereg/data/autzen_colmap`` is what pycolmap made of twelve images rendered over
``tiereg/data/autzen_trim.laz`` (``benchmarks/data/make_autzen_colmap.py``), in COLMAP's own
gauge: about 73 feet per model unit and upside down. ``truth.json`` holds the similarity
from the model frame to the LAZ's (international feet) and the ground sampling distance (GSD,
0.35 ft). The registration must find it without help, from the model folder (with its cameras)
and from the bare points.

Tolerances, as in ``benchmarks/sfm.py``: heading and tilt within 2 deg, scale within 2 %, the
model's centroid within one coarse cell (the result's ``cell_size``) horizontally, and, when the
fine stage ran, the RMS over the model's points of ``|T_est p - T_true p|`` within 1.5 GSD.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

import tiereg
from tiereg.io import open_points
from tiereg.transform import Transform

DATA = Path(str(resources.files("tiereg") / "data"))
MODEL = DATA / "autzen_colmap"
LAZ = DATA / "autzen_trim.laz"
ANGLE_TOL_DEG = 2.0
SCALE_TOL = 0.02
RMS_TOL_GSD = 1.5


def _truth() -> tuple[Transform, float]:
    d = json.loads((MODEL / "truth.json").read_text())
    return Transform(np.asarray(d["T_ref_mov"])), float(d["gsd"])


def _model_points() -> np.ndarray:
    return open_points(MODEL).read().xyz


def test_the_shipped_model_is_in_colmap_gauge():
    """The data are what the acceptance test below needs: a model far outside scale 1 and
    upside down, whose truth fits its points to within a GSD."""
    T_true, gsd = _truth()
    d = json.loads((MODEL / "truth.json").read_text())
    assert {"cameras.bin", "images.bin", "points3D.bin"} <= {p.name for p in MODEL.iterdir()}
    assert T_true.scale > 10.0  # feet per model unit
    up = T_true.rotation.T @ [0.0, 0.0, 1.0]  # the lidar's up in the model frame
    assert up[2] < -0.9
    assert d["fit_points"]["median"] < gsd
    assert len(_model_points()) > 1000


@pytest.mark.slow
@pytest.mark.parametrize("moving", ["bare points"])  # the model folder: test_pipeline's demo test
def test_colmap_model_registers_to_lidar(moving):
    T_true, gsd = _truth()
    xyz = _model_points()
    result = tiereg.register(MODEL if moving == "model folder" else xyz, LAZ)
    T = result.T_ref_mov
    dR = T.rotation @ T_true.rotation.T
    heading_deg = np.degrees(np.arctan2(dR[1, 0] - dR[0, 1], dR[0, 0] + dR[1, 1]))
    tilt_deg = np.degrees(np.arccos(np.clip(dR[2, 2], -1.0, 1.0)))
    scale_err = T.scale / T_true.scale - 1.0
    centre = xyz.mean(axis=0, keepdims=True)
    shift = np.hypot(*(T.apply(centre) - T_true.apply(centre))[0, :2])
    err = np.linalg.norm(T.apply(xyz) - T_true.apply(xyz), axis=1)
    rms_gsd = float(np.sqrt(np.mean(err**2)) / gsd)
    found = (f"heading {heading_deg:.2f} deg, tilt {tilt_deg:.2f} deg, scale {scale_err:+.2%}, "
             f"centroid {shift:.2f} ft (cell {result.cell_size:.3g}), RMS {rms_gsd:.2f} GSD, "
             f"confident {result.confident}, reasons {list(result.reasons)}")
    assert abs(heading_deg) <= ANGLE_TOL_DEG and tilt_deg <= ANGLE_TOL_DEG, found
    assert abs(scale_err) <= SCALE_TOL, found
    assert shift <= result.cell_size, found
    if result.fine is not None:
        assert rms_gsd <= RMS_TOL_GSD, found
    assert result.confident, found
