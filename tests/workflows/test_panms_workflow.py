"""register-pan-ms (METHODS §9) end to end on a rendered GF7 crop with known truth: outputs, accuracy against the
true field, gdal_pansharpen.py on ms_on_pan.tif, and bad inputs (one line, exit 2, nothing written)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from osgeo import gdal

from gdal_gf4cal import panms
from gdal_gf4cal.simulate.gf7 import make_gf7_scene, write_gf7_scene
from panmssim import synth_cells

pytestmark = pytest.mark.slow

KW = dict(seed=0, jitter=False, size=(2048, 2048), crop_center_ms_px=2560)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    """A rendered GF7 crop (pan 2048², MS 512², one MS sub-CCD edge at column 256), no jitter."""
    d = tmp_path_factory.mktemp("gf7")
    write_gf7_scene(d, workers=2, **KW)
    return d


@pytest.fixture(scope="module")
def inputs(scene_dir):
    return scene_dir / "pan" / "scene.tif", scene_dir / "ms" / "scene.tif", scene_dir / "dem.tif"


@pytest.fixture(scope="module")
def registered(inputs, tmp_path_factory):
    pan, ms, dem = inputs
    out = tmp_path_factory.mktemp("reg") / "out"
    cells = synth_cells(make_gf7_scene(**KW), cell=32, sigma=0.03)
    rep = panms_workflow()(pan, ms, dem=dem, out=out, breaks="256", cells=cells)
    return out, rep


def panms_workflow():
    from gdal_gf4cal.workflows import register_pan_ms
    return register_pan_ms


def test_outputs_and_report(registered):
    out, rep = registered
    assert sorted(os.listdir(out)) == sorted(["correction.tif", "ms_on_pan.tif", "model.json", "ms_approx.RPB",
                                              "report.json", "cells.gpkg", "residual_maps.png",
                                              "residual_along_line.png", "spectrum.png"])
    r = json.loads((out / "report.json").read_text())
    assert [s["step"] for s in r["steps"]] == ["before", "linear", "piecewise", "jitter"]
    assert r["steps"][1]["p_le_0.25"] < 0.9 and r["steps"][-1]["p_le_0.25"] >= 0.99
    assert r["jitter"]["sample"]["components"] == [] and r["jitter"]["line"]["components"] == []
    assert r["sizes"] == {"pan": [2048, 2048], "ms": [512, 512], "ratio": 4, "ms_on_pan": [512, 512]}
    assert 0 < r["ms_approx_rpc"]["max_px"] < 1.0
    m = panms.PanMSModel.from_json(out / "model.json")
    assert m.breaks == (256.0,)
    ds = gdal.OpenEx(str(out / "cells.gpkg"))
    assert ds.GetLayerByName("gcps").GetFeatureCount() == 256
    assert ds.GetLayerByName("residual_vectors") is not None


def test_correction_against_the_true_field(registered, scene_dir):
    out, _ = registered
    c = gdal.Open(str(out / "correction.tif"))
    assert (c.RasterXSize, c.RasterYSize, c.RasterCount) == (512, 512, 2)
    assert c.GetRasterBand(1).DataType == gdal.GDT_Float32
    e = c.ReadAsArray() - gdal.Open(str(scene_dir / "ms" / "misregistration_truth.tif")).ReadAsArray()
    assert np.sqrt(np.mean(e[0] ** 2)) <= 0.03 and np.sqrt(np.mean(e[1] ** 2)) <= 0.03
    assert np.hypot(e[0], e[1]).max() <= 0.15


def test_gdal_pansharpen_on_ms_on_pan_removes_the_halo(registered, inputs, tmp_path):
    out, _ = registered
    pan, ms, dem = inputs
    from gdal_gf4cal.dem import DEM
    from gdal_gf4cal.rpc import RPCModel
    raw = tmp_path / "ms_on_pan_rpc_only.tif"
    panms.resample_ms_on_pan(None, pan, ms, raw, pan_rpc=RPCModel.from_file(pan), ms_rpc=RPCModel.from_file(ms),
                             dem=DEM.from_user_input(str(dem)), ratio=4)
    metrics = {}
    for name, img in (("before", raw), ("after", out / "ms_on_pan.tif")):
        fused = tmp_path / f"fused_{name}.tif"
        proc = subprocess.run(["gdal_pansharpen.py", "-q", str(pan), str(img), str(fused)], capture_output=True,
                              text=True)
        assert proc.returncode == 0, proc.stderr
        f = gdal.Open(str(fused))
        assert (f.RasterXSize, f.RasterYSize, f.RasterCount) == (2048, 2048, 4)
        metrics[name] = (panms.edge_misregistration(pan, fused, band=1),
                         panms.edge_misregistration(pan, img, band=1))
    fused_before, input_before = metrics["before"]
    fused_after, input_after = metrics["after"]
    assert input_before["rms_px"] > 0.5 and input_after["rms_px"] <= 0.05
    assert fused_before["rms_px"] > 0.1 and fused_after["rms_px"] <= 0.1
    assert fused_after["rms_px"] < 0.25 * fused_before["rms_px"]


def _run(*args, cwd):
    return subprocess.run([sys.executable, "-m", "gdal_gf4cal.cli", "register-pan-ms", *map(str, args)],
                          capture_output=True, text=True, cwd=cwd)


@pytest.mark.parametrize("case, expected", [
    ("no_overlap", "overlap"),
    ("no_ratio", "integer ratio"),
    ("reuse_other_camera", "reuse"),
    ("sub_ccds_and_breaks", "not allowed with"),
])
def test_bad_input_is_one_line_exit_2_nothing_left(inputs, scene_dir, tmp_path, case, expected):
    pan, ms, dem = inputs
    before = sorted(os.listdir(scene_dir / "ms"))
    extra = []
    if case == "no_overlap":
        from gdal_gf4cal.rpc_io import write_rpc_vrt
        other = write_gf7_scene(tmp_path / "other", seed=3, center=(100.0, 40.0), size=(2048, 2048), render=False)
        ms = write_rpc_vrt(ms, other.images["ms"].rpc, tmp_path / "ms_elsewhere.vrt")
    elif case == "no_ratio":
        ms2 = tmp_path / "ms_cut.tif"
        gdal.Translate(str(ms2), str(ms), srcWin=[0, 0, 500, 512])
        ms = ms2
    elif case == "reuse_other_camera":
        model = panms.PanMSModel(ms_size=(7680, 7680), breaks=panms.default_breaks(7680))
        extra = ["--reuse", model.to_json(tmp_path / "other_camera.json")]
    elif case == "sub_ccds_and_breaks":
        extra = ["--sub-ccds", "3", "--breaks", "256"]
    proc = _run(pan, ms, "--dem", dem, "--out", tmp_path / "o", *extra, cwd=tmp_path)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) >= 1 and expected in proc.stderr, proc.stderr
    assert not (tmp_path / "o").exists()
    assert sorted(os.listdir(scene_dir / "ms")) == before
    shutil.rmtree(tmp_path / "other", ignore_errors=True)
