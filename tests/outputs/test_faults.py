"""The output policy under real OS faults (issue 11 "Faults"): a full file system (RLIMIT_FSIZE in the child, so
writes fail with EFBIG as on a full disk); SIGINT/SIGTERM mid-run are in test_output_policy.py. Each case runs the real CLI in a subprocess and checks:
a non-zero exit, one clear line and no traceback, no output file left (hidden temporaries included), inputs
unchanged (checksums before/after).
"""
from __future__ import annotations

import hashlib
import os
import resource
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from gdal_gf4cal.cli import main


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A rendered 384 x 384 GF4 scene (seed 5) with GCPs: the inputs of the runs below."""
    d = tmp_path_factory.mktemp("faults") / "scene"
    assert main(["simulate", "--sensor", "gf4", "--out", str(d), "--size", "384", "384", "--n-gcps", "30",
                 "--seed", "5", "--render", "--no-reference-ortho"]) == 0
    return d


def _checksums(folder: Path) -> dict:
    return {p.relative_to(folder): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _limited(max_bytes: int):
    """preexec_fn of a child whose files cannot grow beyond ``max_bytes`` (SIGXFSZ ignored: writes get EFBIG)."""
    def apply():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (max_bytes, max_bytes))
    return apply


def _run(args, **kw):
    env = dict(os.environ, GF4CAL_DEBUG="0")
    return subprocess.run([sys.executable, "-m", "gdal_gf4cal.cli", *map(str, args)], capture_output=True, text=True,
                          env=env, timeout=600, **kw)


def _assert_one_clear_line(proc):
    """Exit 2, no traceback, one ``gf4cal: error:`` line that says a write failed (GDAL may add its own ERROR
    line); never the catch-all's "unexpected"."""
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    ours = [line for line in proc.stderr.splitlines() if line.startswith("gf4cal: error:")]
    assert len(ours) == 1, proc.stderr
    assert ("disk is full" in ours[0] or "write" in ours[0]) and "unexpected" not in ours[0], ours[0]


@pytest.mark.parametrize("limit", [2_000, 40_000, 150_000])
def test_refine_on_a_full_file_system_leaves_nothing(scene, tmp_path, limit):
    """The limit falls inside a different output each time (the VRT/report are small, the GeoPackage and the
    plot larger): whichever write fails, no output and no temporary remains."""
    before = _checksums(scene)
    out = tmp_path / "out"
    out.mkdir()
    proc = _run(["refine", scene / "scene.tif", "--gcps", scene / "gcps.csv", "--model", "affine",
                 "--out", out / "refined.vrt", "--report", out / "report.json", "--residuals", out / "res.gpkg",
                 "--plot", out / "res.png"], preexec_fn=_limited(limit))
    _assert_one_clear_line(proc)
    assert sorted(os.listdir(out)) == [], os.listdir(out)
    assert _checksums(scene) == before


def test_simulate_on_a_full_file_system_leaves_nothing(tmp_path):
    proc = _run(["simulate", "--sensor", "gf4", "--out", tmp_path / "scene", "--size", "256", "256",
                 "--n-gcps", "10", "--render"], preexec_fn=_limited(100_000))
    _assert_one_clear_line(proc)
    assert os.listdir(tmp_path) == []


@pytest.fixture
def immutable_folder(tmp_path):
    """An empty folder nobody can write in, root included: the tests run as root, for whom permission bits do not
    apply, so the folder gets the ext4/overlayfs *immutable* attribute (``chattr +i``): creating a file in it fails
    with EPERM for every user. Removed again afterwards. Skipped where the file system has no such attribute."""
    folder = tmp_path / "locked"
    folder.mkdir()
    if subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode != 0:
        pytest.skip("chattr +i is not supported here")
    try:
        try:
            (folder / "probe").write_text("x")
        except OSError:
            pass
        else:
            pytest.skip("the immutable attribute does not stop writes here")
        yield folder
    finally:
        subprocess.run(["chattr", "-i", str(folder)], capture_output=True)


@pytest.mark.parametrize("where", ["folder", "subfolder"])
def test_unwritable_output_folder_one_line_exit_2_nothing_written(scene, tmp_path, immutable_folder, where):
    """Every output in a folder nobody can write in (or a new folder inside it): refused before any work with one
    line naming the folder, exit 2, nothing written anywhere, inputs unchanged."""
    before = _checksums(scene)
    out = immutable_folder if where == "folder" else immutable_folder / "new"
    proc = _run(["refine", scene / "scene.tif", "--gcps", scene / "gcps.csv", "--model", "affine",
                 "--out", out / "refined.vrt", "--report", out / "report.json", "--residuals", out / "res.gpkg",
                 "--plot", out / "res.png"])
    _assert_one_clear_line(proc)
    assert str(immutable_folder) in proc.stderr and "Operation not permitted" in proc.stderr
    assert os.listdir(immutable_folder) == [] and sorted(os.listdir(tmp_path)) == ["locked"]
    assert _checksums(scene) == before


def test_output_under_a_regular_file_one_line_exit_2(scene, tmp_path):
    """An output folder that is a regular file (ENOTDIR, which fails for root too): one line, exit 2, the file
    untouched and nothing else written."""
    blocker = tmp_path / "afile"
    blocker.write_text("not a folder\n")
    proc = _run(["refine", scene / "scene.tif", "--gcps", scene / "gcps.csv", "--model", "affine",
                 "--out", blocker / "refined.RPB", "--report", tmp_path / "report.json"])
    _assert_one_clear_line(proc)
    assert sorted(os.listdir(tmp_path)) == ["afile"] and blocker.read_text() == "not a folder\n"
