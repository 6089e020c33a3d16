"""The quick overlap check: where the data sets overlap, and saying so only when it is known."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tiereg.cli import main
from tiereg.demo import TRUTH, make_tie_points, sample_lidar
from tiereg.io import open_points
from tiereg.overlap import check_overlap


@pytest.fixture(scope="module")
def lidar_xyz():
    return open_points(sample_lidar()).read().xyz


def _inside(poly_rings, xy):
    from matplotlib.path import Path as MplPath

    return np.any([MplPath(np.asarray(rings[0])).contains_points(xy) for rings in poly_rings],
                  axis=0)


@pytest.mark.slow
def test_overlap_outline_covers_the_block(lidar_xyz):
    ties = make_tie_points(lidar_xyz)
    result = check_overlap(ties, sample_lidar())
    assert result.confident and result.fraction > 0.95
    true_xy = TRUTH.inverse.apply(ties)[:, :2]  # where the tie points really are
    inside = _inside(result.outline["coordinates"], true_xy)
    assert inside.mean() > 0.95
    # the outline hugs the block: its area is near that of the block's footprint (feet^2)
    lo, hi = true_xy.min(axis=0), true_xy.max(axis=0)
    assert 0.5 * np.prod(hi - lo) < result.area < 1.2 * np.prod(hi - lo)


@pytest.mark.slow
def test_tie_points_from_elsewhere_are_not_called_overlapping(lidar_xyz, tmp_path):
    # a block of another place: the lidar mirrored and shifted is a different surface
    rng = np.random.default_rng(3)
    other = lidar_xyz[rng.choice(len(lidar_xyz), 1500, replace=False)] * [1, -1, 1]
    other[:, 2] = rng.normal(400, 20, 1500)  # heights that match nothing there
    np.savetxt(tmp_path / "other.xyz", other)
    code = main(["overlap", str(tmp_path / "other.xyz"), str(sample_lidar()), "--out",
                 str(tmp_path / "ov"), "-q"])
    assert code == 3
    data = json.loads((tmp_path / "ov" / "overlap.json").read_text())
    assert data["confident"] is False and data["verdict"] == "no reliable overlap found"


@pytest.mark.slow
def test_overlap_command_writes_outline_and_picture(lidar_xyz, tmp_path, capsys):
    np.savetxt(tmp_path / "ties.xyz", make_tie_points(lidar_xyz))
    code = main(["overlap", str(tmp_path / "ties.xyz"), str(sample_lidar()), "--out",
                 str(tmp_path / "ov")])
    out = capsys.readouterr().out
    assert code == 0 and out.startswith("overlap: ")
    gj = json.loads((tmp_path / "ov" / "overlap.geojson").read_text())
    assert gj["features"][0]["geometry"]["type"] == "MultiPolygon"
    assert (tmp_path / "ov" / "overlap.png").read_bytes()[:4] == b"\x89PNG"
    # the time of the answer apart from that of reading the lidar (the acceptance's measure)
    data = json.loads((tmp_path / "ov" / "overlap.json").read_text())
    assert 0 < data["reference_seconds"] < data["seconds"]
    assert "s reading and gridding the reference" in out


def test_overlap_bad_input_is_one_line(tmp_path, capsys):
    code = main(["overlap", str(tmp_path / "none.xyz"), str(sample_lidar())])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
