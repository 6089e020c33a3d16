"""Many blocks against one archive: each block found, a RESULT.json per block, summary.csv and
overview.png, resumable, the same answers on a cluster as in one process; and a block found in
a lidar several search grids wide."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from archive_tiles import ORIGIN, write_tiles
from scenes import surface

from tiereg import Transform
from tiereg.batch import run_batch
from tiereg.cli import main
from tiereg.distributed import cluster

pytest.importorskip("distributed")

TRUTHS = {  # T_mov_ref of each block: heading (deg), scale (model units per metre), centre
    "north": (35.0, 1.0, (-150.0, 150.0)),
    "south": (250.0, 2.0, (150.0, -100.0)),
}


def _block(folder: Path, name: str, heading: float, scale: float, centre) -> Path:
    rng = np.random.default_rng(len(name))
    xy = np.asarray(centre) + rng.uniform(-600, 600, (1000, 2))
    xyz = np.column_stack([xy, surface(xy[:, 0], xy[:, 1], seed=0)])
    xyz[:, :2] += ORIGIN
    xyz += rng.normal(0, [0.15, 0.15, 0.3], xyz.shape)
    T = Transform.from_parameters(scale=scale, kappa=np.radians(heading),
                                  translation=(1000.0, -3000.0, 50.0))
    moved = (T @ Transform.from_translation((-ORIGIN[0], -ORIGIN[1], 0.0))).apply(xyz)
    path = folder / f"{name}.xyz"
    np.savetxt(path, moved, fmt="%.4f")
    return path


def _error_m(result_json: Path, block: Path, name: str) -> float:
    heading, scale, _ = TRUTHS[name]
    T = Transform.from_parameters(scale=scale, kappa=np.radians(heading),
                                  translation=(1000.0, -3000.0, 50.0))
    T_true = (T @ Transform.from_translation((-ORIGIN[0], -ORIGIN[1], 0.0))).inverse
    found = Transform(np.array(json.loads(result_json.read_text())["T_ref_mov"]))
    centre = np.loadtxt(block).mean(axis=0)[None]
    return float(np.linalg.norm(found.apply(centre) - T_true.apply(centre)))


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    root = tmp_path_factory.mktemp("batch")
    write_tiles(root / "tiles", tiles=(4, 4), density=0.05)  # 2 km square
    blocks = [_block(root, n, *t) for n, t in TRUTHS.items()]
    return root, blocks


@pytest.fixture(scope="module")
def one_process(archive):
    """The batch of both blocks run once in this process (shared by the tests below)."""
    root, blocks = archive
    return run_batch(blocks, root / "tiles", root / "one"), root / "one"


@pytest.mark.slow
def test_batch_on_a_cluster_finds_every_block_as_one_process_does(archive, one_process,
                                                                   tmp_path):
    root, blocks = archive
    with cluster(workers=2, processes=False) as client:
        many = run_batch(blocks, root / "tiles", tmp_path / "many", client=client)
    one, one_dir = one_process
    for a, b, block in zip(many.outcomes, one.outcomes, blocks):
        assert a.confident and b.confident
        e_many = _error_m(tmp_path / "many" / a.name / "RESULT.json", block, a.name)
        e_one = _error_m(one_dir / b.name / "RESULT.json", block, b.name)
        assert e_many < 1.0 and e_one < 1.0  # metres at the block centre (lidar 0.05 pt/m2)
        np.testing.assert_allclose(a.T_ref_mov, b.T_ref_mov, atol=1e-6)
    rows = list(csv.DictReader((tmp_path / "many" / "summary.csv").open()))
    assert [r["block"] for r in rows] == ["north", "south"]
    assert all(r["confident"] == "True" for r in rows)
    assert float(rows[1]["scale"]) == pytest.approx(0.5, rel=0.01)  # metres per model unit
    png = (tmp_path / "many" / "overview.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_batch_command_is_resumable_and_says_so_in_its_exit_code(archive, one_process,
                                                                 tmp_path, capsys):
    root, blocks = archive
    out = tmp_path / "out"
    shutil.copytree(one_process[1], out)  # both blocks registered before
    assert (out / "reference-base.npz").is_file() and (out / "tile-index.json").is_file()
    done = out / "north" / "RESULT.json"
    stamp = done.stat().st_mtime_ns
    # a second run registers nothing again; what was done is kept as it was
    assert main(["batch", *map(str, blocks), str(root / "tiles"), "--out", str(out)]) == 0
    assert done.stat().st_mtime_ns == stamp
    assert "2 of 2 blocks confident (2 done before)" in capsys.readouterr().out
    # a block that is not in the lidar (another surface): ran, not confident, exit code 3
    rng = np.random.default_rng(3)
    stranger = tmp_path / "stranger.xyz"
    xy = rng.uniform(-600, 600, (800, 2))
    np.savetxt(stranger, np.column_stack([xy, surface(xy[:, 0], xy[:, 1], seed=9)]))
    assert main(["batch", str(stranger), str(root / "tiles"), "--out", str(out), "-q"]) == 3
    assert not json.loads((out / "stranger" / "RESULT.json").read_text())["confident"]


def test_batch_bad_input_is_a_one_line_error(archive, tmp_path, capsys):
    root, blocks = archive
    assert main(["batch", str(tmp_path / "missing.xyz"), str(root / "tiles"), "--out",
                 str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no such block" in err[0]
    assert not (tmp_path / "o").exists()
    assert main(["batch", str(blocks[0]), str(blocks[0]), str(root / "tiles"), "--out",
                 str(tmp_path / "o")]) == 2
    assert "share the folder" in capsys.readouterr().err


def test_screening_windows_hold_every_block_whole():
    from tiereg.mosaic import windows

    extent, side, block = (0.0, 0.0, 9600.0, 9600.0), 2400.0, 340.0
    boxes = windows(extent, side, side - block)
    assert all(b[2] - b[0] == pytest.approx(side) for b in boxes)
    assert boxes[0][:2] == (0.0, 0.0) and boxes[-1][2:] == pytest.approx((9600.0, 9600.0))
    rng = np.random.default_rng(1)
    for x, y in rng.uniform(0, 9600 - block, (500, 2)):  # a block's bounding square anywhere
        assert any(b[0] <= x and x + block <= b[2] and b[1] <= y and y + block <= b[3]
                   for b in boxes)


def test_window_reference_is_the_base_grid_cut_and_reads_only_its_tiles(archive):
    from tiereg.archive import TileIndex
    from tiereg.distributed import prepare_archive_reference
    from tiereg.mosaic import window_reference

    root, _ = archive
    # a base as fine as the window's own (1.25 point spacings of 4.5 m): the base grid is cut
    ref = prepare_archive_reference(TileIndex.build(root / "tiles"), base_cell=5.0)
    box = (-700.0, -300.0, -320.0, 100.0)  # local frame; meets 4 of the 16 tiles
    win = window_reference(ref, box)
    s, w = ref.base.spec, win.base.spec
    r0, c0 = round((s.y0 - w.y0) / s.cell_size), round((w.x0 - s.x0) / s.cell_size)
    np.testing.assert_array_equal(
        win.base.count, ref.base.count[r0:r0 + w.shape[0], c0:c0 + w.shape[1]])
    assert w.bounds[0] <= box[0] and w.bounds[2] >= box[2]
    assert len(win.source.paths) == 4 and np.array_equal(win.origin, ref.origin)
    pts = np.concatenate(list(win.local_chunks()))
    assert pts[:, 0].min() >= box[0] - 1e-6 and pts[:, 0].max() <= box[2] + 1e-6


def test_window_of_a_coarse_archive_base_is_gridded_from_its_tiles(archive, monkeypatch):
    """A wide archive's base grid is coarse (capped cells a side); a judged window is gridded
    anew from its own tiles at 1.25 point spacings (4.5 m here: 5.6 m cells, not 20 m), in the
    process that uses it: pickling it to a worker reads no point."""
    import pickle

    from tiereg.archive import ArchiveSource, TileIndex
    from tiereg.distributed import prepare_archive_reference
    from tiereg.grid import GridAccumulator
    from tiereg.mosaic import window_reference

    root, _ = archive
    ref = prepare_archive_reference(TileIndex.build(root / "tiles"), base_cell=20.0)
    box = (-700.0, -300.0, -320.0, 100.0)
    with monkeypatch.context() as m:
        m.setattr(ArchiveSource, "chunks", lambda *a, **k: pytest.fail("read on pickling"))
        win = pickle.loads(pickle.dumps(window_reference(ref, box)))
    spec = win.base.spec
    assert 5.0 < spec.cell_size < 6.5 and np.array_equal(win.origin, ref.origin)
    assert spec.bounds[0] <= box[0] < spec.bounds[0] + spec.cell_size
    assert spec.bounds[3] >= box[3] > spec.bounds[3] - spec.cell_size
    acc = GridAccumulator(spec, stats=("mean",))
    for chunk in win.local_chunks():  # the window's points, as the base grid was made of them
        acc.add(chunk)
    expected = acc.result()
    np.testing.assert_array_equal(win.base.count, expected.count)
    np.testing.assert_allclose(win.base.stats["mean"], expected.stats["mean"], rtol=0, atol=1e-9)
    assert win.base.count.sum() > 0.8 * 0.05 * 380 * 400  # 0.05 points per m2 of the box
