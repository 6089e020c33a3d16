"""The command line: outputs, exit codes, and one-line errors for bad input (exit code 2)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest
import rasterio
from affine import Affine
from scenes import make_scene

from tiereg import Transform
from tiereg.cli import main
from tiereg.io import open_points, read_points, write_points
from tiereg.io.text import write_xyz

SHIFT = Transform.from_translation((-2000.0, 1500.0, -20.0))


@pytest.fixture(scope="module")
def scene_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("scene")
    scene = make_scene(seed=11, T_mov_ref=SHIFT, lidar_points=150_000)
    write_points(d / "lidar.laz", scene.lidar)
    write_xyz(d / "ties.xyz", scene.tie_mov)
    return d, scene


def run(args, capsys):
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.slow
def test_register_writes_result_and_points(scene_files, tmp_path, capsys):
    d, scene = scene_files
    out = tmp_path / "RESULT.json"
    code, stdout, _ = run(["register", d / "ties.xyz", d / "lidar.laz", "-o", out,
                           "--output-points", tmp_path / "moved.laz"], capsys)
    assert code == 0
    data = json.loads(out.read_text())
    assert data["confident"] is True
    umask = os.umask(0)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o666 & ~umask  # like any file the user creates
    assert "confident:   yes" in stdout
    moved = read_points(tmp_path / "moved.laz").xyz
    expected = scene.T_ref_mov.apply(scene.tie_mov)
    # within a tenth of the 20 m cell horizontally (the demo criterion), 0.1 m in height
    assert np.median(np.hypot(*(moved - expected)[:, :2].T)) < 2.0
    assert abs(np.median((moved - expected)[:, 2])) < 0.1


def test_not_confident_exits_3_and_still_writes_result(scene_files, tmp_path, capsys):
    d, scene = scene_files
    # a rotation the translation-only method cannot recover and must not answer confidently
    rotated = Transform.from_parameters(kappa=np.radians(25)).apply(scene.tie_mov)
    write_xyz(tmp_path / "rot.xyz", rotated)
    out = tmp_path / "RESULT.json"
    code, stdout, _ = run(["register", tmp_path / "rot.xyz", d / "lidar.laz", "-o", out,
                           "--coarse", "pomf"], capsys)
    assert code == 3
    assert json.loads(out.read_text())["confident"] is False
    assert "confident:   NO" in stdout


def test_apply_grid_info_round(scene_files, tmp_path, capsys):
    d, scene = scene_files
    result = tmp_path / "R.json"
    result.write_text(json.dumps({"T_ref_mov": scene.T_ref_mov.matrix.tolist()}))
    code, _, _ = run(["apply", result, d / "ties.xyz", tmp_path / "ties_ref.ply"], capsys)
    assert code == 0
    assert np.allclose(read_points(tmp_path / "ties_ref.ply").xyz,
                       scene.T_ref_mov.apply(scene.tie_mov), atol=1e-6)
    # the inverse, from a CloudCompare matrix file, on LAS (streamed, attributes kept)
    (tmp_path / "m.txt").write_text(scene.T_ref_mov.to_cloudcompare())
    code, _, _ = run(["apply", "--inverse", tmp_path / "m.txt", d / "lidar.laz",
                      tmp_path / "lidar_mov.laz"], capsys)
    assert code == 0
    back = read_points(tmp_path / "lidar_mov.laz").xyz
    assert np.abs(back - scene.T_ref_mov.inverse.apply(scene.lidar)).max() < 0.001
    code, stdout, _ = run(["grid", d / "lidar.laz", tmp_path / "dsm.tif", "--cell-size", "10",
                           "--stat", "max"], capsys)
    assert code == 0 and "cell 10" in stdout
    with rasterio.open(tmp_path / "dsm.tif") as ds:
        assert ds.res == (10.0, 10.0) and ds.shape == (200, 200)  # 2 km of lidar, 10 m cells
    code, stdout, _ = run(["info", d / "lidar.laz", "--json"], capsys)
    assert code == 0 and json.loads(stdout)["points"] == len(scene.lidar)


def test_apply_to_a_dsm_moves_it(tmp_path, capsys):
    values = np.arange(100, dtype=np.float64).reshape(10, 10)
    with rasterio.open(tmp_path / "dsm.tif", "w", driver="GTiff", height=10, width=10, count=1,
                       dtype="float64", nodata=-9999.0,
                       transform=Affine(2.0, 0.0, 1000.0, 0.0, -2.0, 2000.0)) as ds:
        ds.write(values, 1)
    (tmp_path / "t.json").write_text(json.dumps(
        {"matrix": Transform.from_translation((10.0, -4.0, 5.0)).matrix.tolist()}))
    code, _, _ = run(["apply", tmp_path / "t.json", tmp_path / "dsm.tif", tmp_path / "out.tif"],
                     capsys)
    assert code == 0
    with rasterio.open(tmp_path / "out.tif") as ds:
        assert ds.transform.c == 1010.0 and ds.transform.f == 1996.0
        assert np.allclose(ds.read(1), values + 5.0)


@pytest.mark.slow
def test_demo(tmp_path, capsys):
    code, stdout, stderr = run(["demo", "--out", tmp_path], capsys)
    assert code == 0, stderr
    assert "truth" in stdout and "recovered" in stdout and "cell of" in stdout
    assert (tmp_path / "RESULT.json").exists() and (tmp_path / "truth.json").exists()
    assert (tmp_path / "report" / "report.html").exists()


def test_help_has_examples(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["register", "--help"])
    assert exc.value.code == 0
    assert "examples:" in capsys.readouterr().out


# ----------------------------------------------------------------------------------- bad input
def _cases(tmp: Path, good_lidar: Path, good_ties: Path):
    """(name, argv, text the one-line message must contain) for every kind of bad input."""
    (tmp / "unknown.dat").write_bytes(b"\x00\x01\x02 binary junk \xff" * 20)
    good = good_lidar.read_bytes()
    (tmp / "cut.laz").write_bytes(good[: len(good) // 3])
    (tmp / "junk.las").write_bytes(b"not a las file at all" * 10)
    write_xyz(tmp / "empty.xyz", np.zeros((0, 3)))
    write_xyz(tmp / "few.xyz", np.random.default_rng(0).uniform(0, 100, (5, 3)))
    nan = np.random.default_rng(0).uniform(0, 100, (100, 3))
    nan[3, 1] = np.nan
    (tmp / "nan.xyz").write_text("\n".join(" ".join(map(str, r)) for r in nan) + "\n")
    write_xyz(tmp / "same.xyz", np.ones((100, 3)))
    line = np.column_stack([np.arange(100.0), 2 * np.arange(100.0), np.zeros(100)])
    write_xyz(tmp / "line.xyz", line)
    with rasterio.open(tmp / "void.tif", "w", driver="GTiff", height=5, width=5, count=1,
                       dtype="float32", nodata=-9999.0,
                       transform=Affine(1.0, 0.0, 0.0, 0.0, -1.0, 5.0)) as ds:
        ds.write(np.full((5, 5), -9999.0, np.float32), 1)
    (tmp / "nothing").mkdir()
    (tmp / "nothing" / "notes.txt").write_text("no points here")
    # semicolon columns with decimal commas: named a text file, read as one, and told why not
    (tmp / "decomma.csv").write_text("".join(f"{i},5;{2 * i},25;100,0\n" for i in range(50)))
    (tmp / "mixed").mkdir()
    unit = np.column_stack([np.random.default_rng(1).uniform(0, 1, (500, 2)), np.zeros(500)])
    _las_in(tmp / "mixed" / "a.las", unit * [1000, 1000, 1] + [500000, 5000000, 0], 32632)
    _las_in(tmp / "mixed" / "b.las", unit * [0.01, 0.01, 1] + [9.0, 45.0, 0], 4326)
    _las_in(tmp / "lonlat.las", unit * [0.01, 0.01, 1] + [9.0, 45.0, 0], 4326)
    out = tmp / "R.json"
    reg = ["register"]
    return [
        ("no command", [], "command is needed"),
        ("missing file", reg + [tmp / "nope.xyz", good_lidar, "-o", out], "nope.xyz"),
        ("unknown format", reg + [tmp / "unknown.dat", good_lidar, "-o", out], "unknown.dat"),
        ("truncated laz", reg + [good_ties, tmp / "cut.laz", "-o", out], "cut.laz"),
        ("corrupt las", reg + [good_ties, tmp / "junk.las", "-o", out], "junk.las"),
        ("empty", reg + [tmp / "empty.xyz", good_lidar, "-o", out], "empty"),
        ("too few", reg + [tmp / "few.xyz", good_lidar, "-o", out], "at least"),
        ("nan", reg + [tmp / "nan.xyz", good_lidar, "-o", out], "nan.xyz"),
        ("identical", reg + [tmp / "same.xyz", good_lidar, "-o", out], "one horizontal"),
        ("collinear", reg + [tmp / "line.xyz", good_lidar, "-o", out], "line"),
        ("no valid cells", reg + [good_ties, tmp / "void.tif", "-o", out], "no valid cells"),
        ("empty directory", reg + [good_ties, tmp / "nothing", "-o", out], "nothing"),
        ("unwritable output", reg + [good_ties, good_lidar, "-o", tmp / "no" / "dir" / "R.json"],
         "does not exist"),
        ("bad cell size", reg + [good_ties, good_lidar, "-o", out, "--cell-size", "-3"],
         "cell"),
        ("bad option", reg + [good_ties, good_lidar, "-o", out, "--coarse", "magic"], "magic"),
        ("scale range the wrong way round", reg + [good_ties, good_lidar, "-o", out,
                                                   "--scale-range", "10", "5"],
         "--scale-range must be"),
        ("result onto the lidar", reg + [good_ties, good_lidar, "-o", good_lidar], "overwrite"),
        ("points onto the tie points", reg + [good_ties, good_lidar, "-o", out,
                                             "--output-points", good_ties], "overwrite"),
        ("decimal commas", reg + [tmp / "decomma.csv", good_lidar, "-o", out],
         "decimal point"),
        ("tiles in two CRSs", reg + [good_ties, tmp / "mixed", "-o", out], "one crs"),
        ("longitude and latitude", reg + [good_ties, tmp / "lonlat.las", "-o", out],
         "projected crs"),
        ("apply unknown transform", ["apply", tmp / "nope.json", good_ties, tmp / "x.xyz"],
         "nope.json"),
        ("apply onto itself", ["apply", tmp / "m.txt", good_ties, good_ties], "overwrite"),
    ]


def _las_in(path: Path, xyz: np.ndarray, epsg: int) -> None:
    """A small LAS file whose header names the CRS ``epsg``."""
    import pyproj

    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = np.array([1e-7, 1e-7, 0.01]) if epsg == 4326 else np.array([0.01] * 3)
    header.offsets = np.floor(xyz.min(axis=0))
    header.add_crs(pyproj.CRS.from_epsg(epsg))
    data = laspy.LasData(header)
    data.x, data.y, data.z = xyz.T
    data.write(str(path))


def test_bad_input_one_line_exit_2_no_output(scene_files, tmp_path):
    """Each bad input: exit code 2, one line on stderr naming the problem, no traceback,
    no output file, inputs untouched. Run through the installed console script."""
    d, _ = scene_files
    lidar, ties = tmp_path / "lidar.laz", tmp_path / "ties.xyz"
    shutil.copy(d / "lidar.laz", lidar)
    shutil.copy(d / "ties.xyz", ties)
    (tmp_path / "m.txt").write_text(Transform.identity().to_cloudcompare())
    before = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in (lidar, ties)}
    exe = Path(sys.executable).with_name("tiereg")
    for name, argv, fragment in _cases(tmp_path, lidar, ties):
        proc = subprocess.run([str(exe), *map(str, argv)], capture_output=True, text=True,
                              env={**os.environ, "COLUMNS": "200"}, timeout=120)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2, (name, proc.stderr)
        assert len(lines) == 1, (name, proc.stderr)
        assert fragment.lower() in lines[0].lower(), (name, lines[0])
        assert "Traceback" not in proc.stderr
        assert not (tmp_path / "R.json").exists(), name
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith(".") and "tmp" in p.name]
    assert leftovers == []
    assert {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in (lidar, ties)} == before


def test_read_only_input_is_enough(scene_files, tmp_path, capsys):
    d, _ = scene_files
    ties = tmp_path / "ties.xyz"
    shutil.copy(d / "ties.xyz", ties)
    ties.chmod(0o444)
    # reading is what is tested: no search, no fine stage (exit 3 says only "not confident")
    code, _, _ = run(["register", ties, d / "lidar.laz", "-o", tmp_path / "R.json", "-q",
                      "--coarse", "none", "--fine", "none"], capsys)
    assert code in (0, 3) and (tmp_path / "R.json").is_file()
    assert json.loads((tmp_path / "R.json").read_text())["quality"]["n_moving"] == len(
        np.loadtxt(ties))


def test_las_writes_keep_the_source_header(scene_files, tmp_path, capsys):
    d, _ = scene_files
    code, _, _ = run(["apply", "--inverse", tmp_path / "missing.json", d / "lidar.laz",
                      tmp_path / "o.laz"], capsys)
    assert code == 2
    src = laspy.open(d / "lidar.laz")
    (tmp_path / "t.txt").write_text(Transform.from_translation((1.0, 2.0, 3.0)).to_pdal())
    code, _, _ = run(["apply", tmp_path / "t.txt", d / "lidar.laz", tmp_path / "o.laz"], capsys)
    assert code == 0
    out = laspy.open(tmp_path / "o.laz")
    assert out.header.point_format.id == src.header.point_format.id
    assert np.allclose(out.header.scales, src.header.scales)


def test_apply_keeps_the_crs_forward_and_drops_it_into_the_model_frame(tmp_path, capsys):
    """Forward, the points stay in their CRS; the inverse carries them into a model's frame,
    which no CRS describes: the output must not claim the input's."""
    unit = np.column_stack([np.random.default_rng(2).uniform(0, 1, (300, 2)), np.zeros(300)])
    _las_in(tmp_path / "utm.las", unit * [1000, 1000, 1] + [500000, 5000000, 0], 32632)
    (tmp_path / "t.txt").write_text(Transform.from_parameters(
        scale=0.5, translation=(-250000.0, -2500000.0, 0.0)).to_pdal())
    for inverse, crs in ((False, "EPSG:32632"), (True, None)):
        out = tmp_path / f"out-{inverse}.las"
        code, _, _ = run(["apply", *(["--inverse"] if inverse else []), tmp_path / "t.txt",
                          tmp_path / "utm.las", out], capsys)
        parsed = laspy.read(out).header.parse_crs()
        assert code == 0
        assert (parsed is None) if crs is None else parsed.equals(crs)


@pytest.mark.slow
def test_apply_with_a_result_writes_the_reference_crs(tmp_path, capsys):
    """Tie points without a CRS, registered to lidar with one: applied with the RESULT.json they
    come out in the lidar's frame and say so; the lidar carried into the model's frame says
    nothing."""
    from tiereg.demo import make_tie_points, sample_lidar

    lidar = sample_lidar()
    np.savetxt(tmp_path / "ties.xyz", make_tie_points(open_points(lidar).read().xyz))
    code, _, _ = run(["register", tmp_path / "ties.xyz", lidar, "-o", tmp_path / "R.json",
                      "--fine", "none", "-q"], capsys)
    assert code == 0
    lidar_crs = laspy.read(lidar).header.parse_crs()
    assert lidar_crs is not None
    code, _, _ = run(["apply", tmp_path / "R.json", tmp_path / "ties.xyz", tmp_path / "t.las"],
                     capsys)
    assert code == 0 and laspy.read(tmp_path / "t.las").header.parse_crs().equals(lidar_crs)
    code, _, _ = run(["apply", "--inverse", tmp_path / "R.json", lidar, tmp_path / "l.laz"],
                     capsys)
    assert code == 0 and laspy.read(tmp_path / "l.laz").header.parse_crs() is None
