"""Hostile inputs and hostile disks, through the installed command as a user runs it.

Every case must end with exit code 2 and at most one line on stderr (no traceback), in bounded
time and memory, leave no file behind (not even a temporary one) and leave every input byte- and
mtime-identical. Outputs go onto device nodes, FIFOs, the inputs themselves and a full disk (a
64 kB tmpfs); inputs are truncated or hostile LAS/LAZ headers, NaN anywhere, FIFOs and symbolic
link loops. The full-disk and device-node cases need root (mount, mknod) and skip without it.
"""

from __future__ import annotations

import json
import math
import os
import resource
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import laspy
import numpy as np
import pytest

from tiereg import InputError, PointSet, Transform
from tiereg.io import as_point_source, write_points
from tiereg.points import validate_points

EXE = Path(sys.executable).with_name("tiereg")
TIMEOUT_S = 60  # a case that has not ended by then hangs
MEMORY_CAP = 1 << 30  # no case may grow past 1 GB (peak resident memory)
ENV = {**os.environ, "COLUMNS": "200", "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}


def run_cli(argv, *, cwd: Path | None = None) -> tuple[int, str, str, int]:
    """Run ``tiereg argv``: ``(exit code, stdout, stderr, peak resident bytes)``; fails the test
    on a hang. The child is reaped with ``wait4`` for its own peak memory."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen([str(EXE), *map(str, argv)], stdout=out, stderr=err, env=ENV,
                                cwd=cwd, stdin=subprocess.DEVNULL)
        # a runaway allocation fails at 2 GB of address space instead of taking the machine
        # (the cap on resident memory below is the assertion)
        resource.prlimit(proc.pid, resource.RLIMIT_AS, (2 * MEMORY_CAP, 2 * MEMORY_CAP))
        deadline = time.monotonic() + TIMEOUT_S
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.monotonic() > deadline:
                proc.kill()
                os.wait4(proc.pid, 0)
                proc.returncode = -9
                pytest.fail(f"tiereg {' '.join(map(str, argv))}: still running after "
                            f"{TIMEOUT_S} s")
            time.sleep(0.02)
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        return proc.returncode, out.read(), err.read(), usage.ru_maxrss * 1024


def assert_refused(code: int, stderr: str, peak: int, fragment: str = "") -> None:
    """Exit code 2, one line (naming ``fragment``), no traceback, bounded memory."""
    lines = stderr.strip().splitlines()
    assert code == 2, stderr
    assert len(lines) == 1, stderr
    assert "Traceback" not in stderr
    assert fragment.lower() in lines[0].lower(), lines[0]
    assert peak < MEMORY_CAP, f"peak memory {peak / 2**20:.0f} MB"


# ------------------------------------------------------------------------------------ the inputs
def _surface(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 100 + 5 * np.sin(x / 37.0) + 4 * np.cos(y / 23.0) + 10 * ((x // 60 + y // 60) % 2)


def _las(path: Path, xyz: np.ndarray, *, version: str = "1.4", point_format: int = 6) -> Path:
    header = laspy.LasHeader(version=version, point_format=point_format)
    header.scales = np.array([0.01, 0.01, 0.01])
    header.offsets = np.floor(xyz.min(axis=0))
    data = laspy.LasData(header)
    data.x, data.y, data.z = xyz.T
    data.write(str(path))
    return path


def _patched(src: Path, dst: Path, *patches: tuple[int, str, object]) -> Path:
    """A copy of ``src`` with ``struct`` values written at byte offsets."""
    b = bytearray(src.read_bytes())
    for offset, fmt, value in patches:
        struct.pack_into(fmt, b, offset, value)
    dst.write_bytes(bytes(b))
    return dst


def _hostile_las(d: Path) -> None:
    """LAS/LAZ files whose headers lie: counts that do not fit in the file, absurd scales."""
    rng = np.random.default_rng(3)
    small = _las(d / "small.las", np.column_stack([rng.uniform(0, 100, (200, 2)),
                                                   rng.uniform(0, 10, 200)]))
    size = small.stat().st_size
    # LAS 1.4 header: 94 header size, 96 offset to points, 100 VLR count, 107 legacy count,
    # 131 scales, 155 offsets, 179 bounds, 235 first EVLR, 243 EVLR count, 247 point count
    _patched(small, d / "vlrs.las", (100, "<I", 2**32 - 1))
    _patched(small, d / "evlrs.las", (235, "<Q", size - 10), (243, "<I", 2**32 - 1))
    evlr = bytearray(small.read_bytes()) + b"\0" * 2 + b"hostile".ljust(16, b"\0") + \
        struct.pack("<HQ", 1, 2**62) + b"\0" * 32
    struct.pack_into("<QI", evlr, 235, size, 1)
    (d / "evlr_length.las").write_bytes(bytes(evlr))
    _patched(small, d / "header_size.las", (94, "<H", 65535))
    _patched(small, d / "offset.las", (96, "<I", 2**32 - 1))
    _patched(small, d / "count.las", (247, "<Q", 2**64 - 1))
    _patched(small, d / "scale0.las", (131, "<d", 0.0))
    _patched(small, d / "scale_huge.las", (139, "<d", 1e300))
    _patched(small, d / "scale_nan.las", (147, "<d", math.nan))
    _patched(small, d / "bounds_nan.las", (179, "<d", math.nan))
    (d / "random.las").write_bytes(b"LASF" + np.random.default_rng(1).bytes(2000))
    # 70 VLRs of 65,000 bytes: well formed, but 4.5 MB of records that hold kilobytes
    b = bytearray(small.read_bytes())
    header_size, offset, n_vlrs = struct.unpack_from("<HII", b, 94)
    vlrs = b"".join(b"\0\0" + b"big".ljust(16, b"\0") + struct.pack("<HH", i, 65000) +
                    b"\0" * 32 + b"\1" * 65000 for i in range(70))
    big = b[:header_size] + vlrs + b[offset:]
    struct.pack_into("<II", big, 96, offset + len(vlrs), n_vlrs + 70)
    (d / "big_vlrs.las").write_bytes(bytes(big))
    # LAZ: cut short, a chunk table offset past the end, and a chunk count of 2^32 - 1
    laz = (d / "lidar.laz").read_bytes()
    (d / "cut.laz").write_bytes(laz[: len(laz) * 2 // 3])
    start = struct.unpack_from("<I", laz, 96)[0]
    table = struct.unpack_from("<q", laz, start)[0]
    _patched(d / "lidar.laz", d / "table.laz", (start, "<q", 2**62))
    _patched(d / "lidar.laz", d / "chunks.laz", (table + 4, "<I", 2**32 - 1))


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    """Small lidar (LAS and LAZ), tie points, transforms, and every hostile variant of them."""
    d = tmp_path_factory.mktemp("faults")
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 300, (30_000, 2)) + [500_000, 5_000_000]
    lidar = np.column_stack([xy, _surface(*(xy - [500_000, 5_000_000]).T)])
    write_points(d / "lidar.laz", lidar)
    write_points(d / "lidar.las", lidar)
    ties = lidar[rng.choice(len(lidar), 400, replace=False)]
    np.savetxt(d / "ties.xyz", ties, fmt="%.3f")
    (d / "T.txt").write_text(Transform.from_translation((1.0, 2.0, 3.0)).to_pdal() + "\n")
    (d / "R.json").write_text(json.dumps({"T_ref_mov": Transform.identity().matrix.tolist()}))
    far = Transform.from_translation((3e7, 0.0, 0.0))  # beyond int32 at the lidar's offsets
    (d / "far.txt").write_text(far.to_pdal() + "\n")
    _hostile_las(d)
    # NaN anywhere
    bad = ties.copy()
    bad[7, 0] = np.nan
    np.savetxt(d / "nan_x.xyz", bad)
    ref = lidar[:5000].copy()
    ref[11, 2] = np.inf
    np.savetxt(d / "ref_inf.xyz", ref)
    heights = ties.copy()
    heights[:, 2] = np.nan
    np.savetxt(d / "nan_z.xyz", heights)
    (d / "nan.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                                b"property float y\nproperty float z\nend_header\n"
                                b"1 2 3\nnan 5 6\n7 8 9\n")
    np.savetxt(d / "same.xyz", np.tile([500_000.123, 5_000_000.456, 101.7], (200, 1)))
    # broken transforms
    (d / "ragged.json").write_text(json.dumps({"T_ref_mov": [[1, 2], [3]]}))
    (d / "words.json").write_text(json.dumps({"T_ref_mov": [["a"] * 4] * 4}))
    (d / "cut.json").write_text(json.dumps({"T_ref_mov": Transform.identity().matrix.tolist(),
                                            "inputs": {"moving": "x"}}, indent=2)[:60])
    (d / "junk.dat").write_bytes(b"\x00\x01junk" * 50)
    os.symlink("loop", d / "loop")
    os.mkfifo(d / "fifo.xyz")
    return d


def _snapshot(d: Path) -> dict[str, tuple[bytes, int]]:
    return {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(d.iterdir())
            if p.is_file() and not p.is_symlink()}


def _leftovers(d: Path, before: dict) -> list[str]:
    return sorted(p.name for p in d.iterdir() if p.name not in before
                  and p.name not in ("loop", "fifo.xyz", "mynull"))


# ----------------------------------------------------------------------- refused in one line
CASES = [
    # item 7: header counts that do not fit in the file, and random bytes after the signature
    ("info", "vlrs.las", "VLR"),
    ("info", "evlrs.las", "extended"),
    ("info", "evlr_length.las", "extended"),
    ("info", "header_size.las", "header"),
    ("info", "offset.las", "point data"),
    ("info", "count.las", "truncated"),
    ("info", "random.las", "random.las"),
    ("info", "big_vlrs.las", "VLRs would take"),
    ("register", "vlrs.las", "VLR"),
    ("apply", "vlrs.las", "VLR"),
    # item 9: absurd scales and truncated or broken LAZ, in info and grid
    ("info", "scale0.las", "scale"),
    ("info", "scale_huge.las", "scale"),
    ("grid", "scale_nan.las", "scale"),
    ("info", "bounds_nan.las", "bounds"),
    ("info", "cut.laz", "truncated"),
    ("info", "table.laz", "truncated"),
    ("apply", "chunks.laz", "chunks.laz"),
    ("grid", "nan_z.xyz", "nan_z.xyz"),
    # item 5: NaN or infinity in a reference, in grid, in a PLY
    ("register", "ref_inf.xyz", "infinite"),
    ("grid", "ref_inf.xyz", "infinite"),
    ("grid", "nan_x.xyz", "nan"),
    ("info", "nan.ply", "nan"),
    # item 8: a FIFO is refused, not waited on
    ("info", "fifo.xyz", "fifo"),
    ("register", "fifo.xyz", "fifo"),
    # item 11: messages that say what is wrong
    ("info", "loop", "loop of symbolic links"),
    ("info", "junk.dat", "--format"),
    ("register", "same.xyz", "one horizontal position"),
]


def _argv(command: str, bad: str, d: Path) -> list:
    """The command with ``bad`` where a user would put a file, output into ``d/out``."""
    if command == "register":
        moving, reference = (d / bad, d / "lidar.laz") if bad.endswith(".xyz") and \
            bad != "ref_inf.xyz" else (d / "ties.xyz", d / bad)
        return ["register", moving, reference, "-o", d / "out.json"]
    if command == "apply":
        return ["apply", d / "T.txt", d / bad, d / "out.laz"]
    if command == "grid":
        return ["grid", d / bad, d / "out.tif", "--cell-size", "5"]
    return [command, d / bad]


@pytest.mark.parametrize("command, bad, fragment", CASES, ids=[f"{c}-{b}" for c, b, _ in CASES])
def test_hostile_input_is_refused_in_one_line(world, command, bad, fragment):
    before = _snapshot(world)
    code, _, err, peak = run_cli(_argv(command, bad, world))
    assert_refused(code, err, peak, fragment)
    assert "--moving-format" not in err or command == "register"
    assert _leftovers(world, before) == []
    assert _snapshot(world) == before


BROKEN_TRANSFORMS = [("ragged.json", "4 x 4"), ("words.json", "4 x 4"), ("cut.json", "JSON")]


@pytest.mark.parametrize("name, fragment", BROKEN_TRANSFORMS)
def test_apply_with_a_broken_transform_file(world, name, fragment):
    """Item 6: a RESULT.json whose T_ref_mov is not 4 x 4 numbers, or that is cut short."""
    before = _snapshot(world)
    code, _, err, peak = run_cli(["apply", world / name, world / "ties.xyz", world / "o.xyz"])
    assert_refused(code, err, peak, fragment)
    assert _leftovers(world, before) == [] and _snapshot(world) == before


# ------------------------------------------------------------------ outputs onto the inputs
ONTO_INPUTS = [
    ["apply", "T.txt", "ties.xyz", "T.txt"],
    ["apply", "R.json", "ties.xyz", "R.json"],
    ["apply", "T.txt", "ties.xyz", "ties_link.xyz"],  # a hard link to the input
    ["register", "ties.xyz", "lidar.laz", "--initial", "R.json", "-o", "R.json"],
    ["register", "ties.xyz", "lidar.laz", "--initial", "R.json", "-o", "out.json",
     "--output-points", "R.json"],
    ["grid", "lidar.las", "lidar.laz", "lidar.las", "--cell-size", "5"],
]


@pytest.mark.parametrize("argv", ONTO_INPUTS, ids=["-".join(a[:1] + a[-2:]) for a in ONTO_INPUTS])
def test_no_output_overwrites_an_input(world, argv):
    """Item 1: every file a command reads counts as an input, the transform included."""
    link = world / "ties_link.xyz"
    if not link.exists():
        os.link(world / "ties.xyz", link)
    before = _snapshot(world)
    code, _, err, peak = run_cli(argv, cwd=world)
    assert_refused(code, err, peak, "overwrite")
    assert _leftovers(world, before) == [] and _snapshot(world) == before


# ------------------------------------------------------------------- non-regular outputs
def test_outputs_onto_device_nodes_and_fifos_are_refused(world, tmp_path):
    """Item 2: the atomic rename would replace a device node or a FIFO by a regular file."""
    try:
        os.mknod(tmp_path / "mynull", 0o666 | 0o020000, os.makedev(1, 3))
    except PermissionError:
        pytest.skip("mknod needs root")
    os.mkfifo(tmp_path / "pipe.tif")
    for out in ("mynull", "pipe.tif"):
        code, _, err, peak = run_cli(["grid", world / "ties.xyz", tmp_path / out,
                                      "--cell-size", "5"])
        assert_refused(code, err, peak, "not a regular file")
    assert (tmp_path / "mynull").is_char_device() and (tmp_path / "pipe.tif").is_fifo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mynull", "pipe.tif"]


# ----------------------------------------------------------------------------- a full disk
@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A 64 kB tmpfs, unmounted at the end whatever happens."""
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    mnt = tmp_path_factory.mktemp("tiny")
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)],
                          capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {proc.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


FULL_DISK = [
    ["apply", "{d}/T.txt", "{d}/lidar.laz", "{t}/o.laz"],
    ["apply", "{d}/T.txt", "{d}/lidar.laz", "{t}/o.las"],
    ["grid", "{d}/lidar.laz", "{t}/o.tif", "--cell-size", "0.5"],
    ["register", "{d}/ties.xyz", "{d}/lidar.laz", "--coarse", "none", "--fine", "none",
     "-o", "{t}/R.json", "--output-points", "{t}/p.ply", "--report", "{t}/rep"],
]


@pytest.mark.parametrize("argv", FULL_DISK, ids=["laz", "las", "tif", "register-all"])
def test_a_full_disk_leaves_nothing(world, tiny, argv):
    """Item 3: one line, and no output of the command at all (not its result either)."""
    before = _snapshot(world)
    code, _, err, peak = run_cli([a.format(d=world, t=tiny) for a in argv])
    assert_refused(code, err, peak, "disk is full")
    assert list(tiny.iterdir()) == []
    assert _snapshot(world) == before


# -------------------------------------------------------------------------------- signals
@pytest.fixture(scope="module")
def big_laz(tmp_path_factory) -> Path:
    """A LAZ large enough that transforming it takes a moment (1.5 million points)."""
    d = tmp_path_factory.mktemp("big")
    rng = np.random.default_rng(5)
    xy = rng.uniform(0, 1000, (1_500_000, 2))
    return _las(d / "big.laz", np.column_stack([xy, _surface(*xy.T)]))


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["TERM", "INT"])
def test_a_signal_during_apply_leaves_no_temporary_file(world, big_laz, tmp_path, signum):
    """Item 4: the temporary file beside the target goes with the process."""
    out = tmp_path / "o.laz"
    for _ in range(3):  # on a busy machine the command may finish before it is caught writing
        # as from a terminal: a test run started in the background ignores SIGINT, and so would
        # the command it starts
        proc = subprocess.Popen([str(EXE), "apply", world / "T.txt", big_laz, out],
                                stderr=subprocess.PIPE, text=True, env=ENV,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        deadline = time.monotonic() + TIMEOUT_S
        while not list(tmp_path.glob(".o.laz.*.tmp")) and proc.poll() is None:
            assert time.monotonic() < deadline, "no temporary file appeared"
            time.sleep(0.005)
        if proc.poll() is None:
            break
        proc.communicate()
        out.unlink(missing_ok=True)
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=TIMEOUT_S)
    assert proc.returncode == 128 + signum, err
    assert "Traceback" not in err and len(err.strip().splitlines()) <= 1
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------- quiet success, no warnings
def test_apply_far_away_prints_no_warning(world, tmp_path):
    """Item 10: moving LAS points by 30,000 km makes laspy cast overflowing values (whose
    results are then replaced): no warning may reach the user, and the points are right."""
    code, out, err, _ = run_cli(["apply", "-q", world / "far.txt", world / "lidar.laz",
                                 tmp_path / "far.laz"])
    assert code == 0 and out == "" and err == ""
    a, b = laspy.read(world / "lidar.laz"), laspy.read(tmp_path / "far.laz")
    moved = np.column_stack([b.x, b.y, b.z]) - np.column_stack([a.x, a.y, a.z])
    assert np.abs(moved - [3e7, 0.0, 0.0]).max() <= 0.01  # the scale of the file


def test_large_evlrs_stay_on_disk_and_their_crs_is_read(tmp_path):
    """A LAS 1.4 file with 5 MB of EVLRs (waveforms) and its CRS in one more: the header is
    read without them, the CRS still is."""
    import pyproj
    from laspy.vlrs.known import WktCoordinateSystemVlr
    from laspy.vlrs.vlrlist import VLRList

    from tiereg.io import open_points

    xyz = np.column_stack([np.random.default_rng(0).uniform(0, 100, (100, 2)) + 500_000,
                           np.zeros(100)])
    header = laspy.LasHeader(version="1.4", point_format=6)
    data = laspy.LasData(header)
    data.x, data.y, data.z = xyz.T
    utm = pyproj.CRS.from_epsg(32632)
    data.evlrs = VLRList([laspy.VLR("waveform", 1000, "samples", b"\1" * (5 << 20)),
                          WktCoordinateSystemVlr(utm.to_wkt())])
    data.write(str(tmp_path / "w.las"))
    src = open_points(tmp_path / "w.las")
    assert src.headers[0].evlrs is not None and len(src.headers[0].evlrs) == 1
    assert pyproj.CRS.from_wkt(src.info.crs_wkt).equals(utm)
    assert np.allclose(src.read().xyz[:, :2], xyz[:, :2], atol=0.01)


def test_all_or_nothing_writes_every_output_or_none(tmp_path):
    from tiereg.io import all_or_nothing, read_points
    from tiereg.io.base import write_text_atomic

    xyz = np.random.default_rng(0).uniform(0, 10, (20, 3))
    with pytest.raises(RuntimeError), all_or_nothing(folders=[tmp_path / "new" / "deeper"]):
        write_points(tmp_path / "a.xyz", xyz)
        (tmp_path / "new" / "deeper").mkdir(parents=True)
        write_text_atomic(tmp_path / "new" / "deeper" / "b.txt", "b")
        raise RuntimeError("the third output failed")
    assert list(tmp_path.iterdir()) == []  # no file, no temporary file, no folder
    with all_or_nothing():
        write_points(tmp_path / "a.xyz", xyz)
        assert not (tmp_path / "a.xyz").exists()  # renamed into place at the end only
        write_text_atomic(tmp_path / "b.txt", "b")
    assert np.allclose(read_points(tmp_path / "a.xyz").xyz, xyz)
    assert (tmp_path / "b.txt").read_text() == "b"


def test_all_or_nothing_never_replaces_a_file_read_in_it(tmp_path):
    """The last line of defence, for outputs no early check knew of: a file read in the block
    is not replaced, and nothing else is written either."""
    from tiereg.io import all_or_nothing, read_points

    xyz = np.random.default_rng(0).uniform(0, 10, (20, 3))
    write_points(tmp_path / "in.xyz", xyz)
    before = (tmp_path / "in.xyz").read_bytes()
    with pytest.raises(InputError, match="overwrite the input"), all_or_nothing():
        points = read_points(tmp_path / "in.xyz")
        write_points(tmp_path / "other.xyz", points.xyz)
        write_points(tmp_path / "in.xyz", points.xyz + 1)
    assert (tmp_path / "in.xyz").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.xyz"]


# ------------------------------------------------------------------------------ the Python API
@pytest.mark.parametrize("obj, fragment", [
    (None, "None"),
    (5, "int"),
    ([[1.0, 2.0, 3.0]] * 40, "list"),
    (np.array([["a", "b", "c"]] * 40), "numbers"),
    (np.zeros((40, 2)), "(N, 3)"),
    ("", "empty"),
])
def test_as_point_source_refuses_what_is_not_points(obj, fragment):
    with pytest.raises(InputError, match=None) as info:
        as_point_source(obj, role="moving")
    assert fragment.lower() in str(info.value).lower()
    assert "moving" in str(info.value)


def test_as_point_source_refuses_longitude_and_latitude():
    import pyproj

    xy = np.random.default_rng(0).uniform(0, 0.01, (100, 2)) + [9.0, 45.0]
    points = PointSet(np.column_stack([xy, np.zeros(100)]),
                      crs_wkt=pyproj.CRS.from_epsg(4326).to_wkt())
    with pytest.raises(InputError, match="reference.*longitude and latitude"):
        as_point_source(points, role="reference")


def test_register_refuses_a_point_set_in_longitude_and_latitude():
    """As the command line refuses a file in them (the check lives where arrays become
    sources)."""
    import pyproj

    import tiereg

    xy = np.random.default_rng(0).uniform(0, 0.01, (100, 2)) + [9.0, 45.0]
    lonlat = PointSet(np.column_stack([xy, np.zeros(100)]),
                      crs_wkt=pyproj.CRS.from_epsg(4326).to_wkt())
    with pytest.raises(InputError, match="longitude and latitude"):
        tiereg.register(np.column_stack([xy * 1e5, np.zeros(100)]), lonlat)


def test_as_point_source_names_the_role_in_format_errors(world):
    with pytest.raises(InputError, match="`reference_format`"):
        as_point_source(world / "junk.dat", role="reference")


def test_as_point_source_opens_what_register_accepts(world):
    xyz = np.random.default_rng(0).uniform(0, 10, (50, 3))
    assert as_point_source(xyz, role="moving").info.count == 50
    assert as_point_source(PointSet(xyz), role="moving").info.count == 50
    assert as_point_source(world / "lidar.laz", role="reference").info.count == 30_000
    assert as_point_source([world / "lidar.laz"], role="reference").info.format == "las"


@pytest.mark.parametrize("obj", [None, 5, [[1.0, 2.0, 3.0]] * 40, []])
def test_register_refuses_what_is_not_points(obj):
    """The Python API as it stands: open_points, which register calls for whatever is not an
    array, a PointSet or a source, says what it got instead of a TypeError."""
    import tiereg

    with pytest.raises(InputError, match="points are"):
        tiereg.register(obj, np.zeros((50, 3)))


def test_point_set_of_strings_is_an_input_error():
    with pytest.raises(InputError, match="numbers"):
        PointSet(np.array([["a", "b", "c"]]))


def test_a_reference_array_with_nan_is_an_input_error():
    """Item 5 from Python: the reference as an array with one NaN coordinate."""
    rng = np.random.default_rng(0)
    ref = np.column_stack([rng.uniform(0, 100, (2000, 2)), rng.uniform(0, 5, 2000)])
    ref[17, 1] = np.nan
    with pytest.raises(InputError, match="1 of 2000 points.*row 17"):
        as_point_source(ref, role="reference")


def test_identical_points_are_one_position_not_a_line():
    points = PointSet(np.tile([500_000.123, 5_000_000.456, 101.7], (200, 1)))
    with pytest.raises(InputError, match="one horizontal position"):
        validate_points(points, min_count=30, role="moving")
