"""Bad input at the CLI, for every sub-command: one line on stderr, exit status 2, no traceback, nothing written."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A small simulated GF4 scene (fixed seed) written through the public CLI."""
    out = tmp_path_factory.mktemp("scene")
    proc = subprocess.run([sys.executable, "-m", "gdal_gf4cal.cli", "simulate", "--sensor", "gf4", "--out", str(out),
                           "--size", "1024", "1024", "--n-gcps", "40", "--seed", "1"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return out


def _run(*args, cwd):
    return subprocess.run([sys.executable, "-m", "gdal_gf4cal.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd)


@pytest.mark.parametrize("case, expected", [
    ("refine_too_few", "at least 3 control"),
    ("refine_missing_gcps", "not found"),
    ("refine_no_rpc", "no RPC"),
    ("refine_over_input", "input"),
    ("calibrate_too_few", "at least 10 control"),
    ("calibrate_bad_camera", "JSON"),
    ("collect_missing_reference", "not found"),
    ("intersect_one_rpc", "at least 2"),
    ("info_bad_dem", "DEM"),
    ("experiment_unknown", "unknown experiment"),
])
def test_bad_input_is_one_line_and_writes_nothing(scene, tmp_path, case, expected):
    one = tmp_path / "one.csv"
    not_rpc = tmp_path / "notes.txt"
    not_rpc.write_text("just some text\n")
    tif, rpb, gcps, cam = scene / "scene.tif", scene / "scene.RPB", scene / "gcps.csv", scene / "camera_current.json"
    one.write_text("".join(gcps.read_text().splitlines(keepends=True)[:2]))   # one real GCP of the scene
    before = sorted(os.listdir(scene))
    args = {
        "refine_too_few": ["refine", tif, "--gcps", one, "--model", "affine", "--out", tmp_path / "o" / "x.RPB"],
        "refine_missing_gcps": ["refine", tif, "--gcps", tmp_path / "none.csv", "--model", "affine",
                                "--out", tmp_path / "o" / "x.RPB"],
        "refine_no_rpc": ["refine", not_rpc, "--gcps", gcps, "--model", "affine", "--out", tmp_path / "o" / "x.RPB"],
        "refine_over_input": ["refine", tif, "--gcps", gcps, "--model", "affine", "--out", rpb],
        "calibrate_too_few": ["calibrate-lookangle", "--rpc", rpb, "--gcps", one, "--camera", cam,
                              "--out", tmp_path / "o"],
        "calibrate_bad_camera": ["calibrate-lookangle", "--rpc", rpb, "--gcps", gcps, "--camera", not_rpc,
                                 "--out", tmp_path / "o"],
        "collect_missing_reference": ["collect-gcps", tif, "--reference", tmp_path / "none.tif", "--dem",
                                      scene / "dem.tif", "--out", tmp_path / "o" / "g.gpkg"],
        "intersect_one_rpc": ["intersect", "--rpc", rpb, "--points", one],
        "info_bad_dem": ["info", tif, "--dem", not_rpc],
        "experiment_unknown": ["experiment", "nosuch", "--out", tmp_path / "o"],
    }[case]
    proc = _run(*args, cwd=tmp_path)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("gf4cal: error:") and expected in lines[0], proc.stderr
    assert not (tmp_path / "o").exists()                 # no partial output, not even an empty folder
    assert sorted(os.listdir(scene)) == before           # inputs untouched
