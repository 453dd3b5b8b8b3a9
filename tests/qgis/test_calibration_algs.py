"""simulatescene -> calibratelookangle -> applycalibration in real headless QGIS, checked against the simulator's
truth (GF4 look-angle calibration, METHODS §5 and §10)."""
from __future__ import annotations

import csv
import json
import math
import os

import numpy as np
import pytest

NOISE = 0.3


@pytest.fixture(scope="module")
def gf4(run_alg, tmp_path_factory):
    """A cropped GF4 scene from the provider's simulatescene, and the look-angle calibration on it."""
    folder = tmp_path_factory.mktemp("gf4")
    sim, fb = run_alg("gf4cal:simulatescene", {"SENSOR": 0, "SEED": 7, "WIDTH": 600, "HEIGHT": 500, "N_GCPS": 150,
                                               "GCP_NOISE": NOISE, "OUTLIER_FRACTION": 0.05, "CHECK_FRACTION": 0.3,
                                               "OUTPUT_FOLDER": str(folder / "scene")})
    cal, cal_fb = run_alg("gf4cal:calibratelookangle", {
        "INPUT": sim["IMAGE"], "GCPS": sim["GCPS"], "CAMERA": sim["CAMERA"], "OUTPUT_FOLDER": str(folder / "cal")})
    return sim, cal, cal_fb


def _check_grid(folder):
    with open(os.path.join(folder, "check_grid.csv")) as fh:
        rows = list(csv.DictReader(fh))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}


def _grid_error(rpc_path, grid):
    from gdal_gf4cal.rpc import RPCModel
    rpc = RPCModel.from_file(rpc_path)
    s, l = rpc.project(grid["lon"], grid["lat"], grid["h"])
    return s - grid["sample_true"], l - grid["line_true"]


def test_simulatescene_writes_a_consistent_scene(gf4):
    from osgeo import gdal, ogr

    from gdal_gf4cal.rpc import RPCModel
    sim, _, _ = gf4
    with open(sim["TRUTH"]) as fh:
        truth = json.load(fh)
    assert truth["sensor"] == "gf4" and truth["seed"] == 7
    ds = gdal.Open(sim["IMAGE"])
    assert (ds.RasterXSize, ds.RasterYSize) == (600, 500) and ds.GetMetadata("RPC")
    assert sim["RPC_FIT_MAX_PX"] < 0.01
    ds_gcps = ogr.Open(sim["GCPS"])  # keep the dataset alive while its layer is used
    layer = ds_gcps.GetLayer(0)
    assert layer.GetFeatureCount() == truth["images"]["scene"]["n_gcps"] >= 140
    names = {layer.GetLayerDefn().GetFieldDefn(i).GetName() for i in range(layer.GetLayerDefn().GetFieldCount())}
    assert {"id", "lon", "lat", "h", "sample", "line", "role"} <= names
    # the scene RPC is the *current* model: its error against the true positions is the calibration's target
    grid = _check_grid(sim["OUTPUT_FOLDER"])
    es, el = _grid_error(sim["RPC"], grid)
    assert np.sqrt(np.mean(es ** 2 + el ** 2)) > 1.0
    assert RPCModel.from_file(sim["RPC"]).image_size[0] == pytest.approx(600, abs=2)


def test_calibratelookangle_removes_the_systematic_error(gf4):
    from osgeo import ogr
    sim, cal, fb = gf4
    floor = math.sqrt(2) * NOISE
    assert cal["CONTROL_RMS_BEFORE"] > 3 * floor and cal["CHECK_RMS_BEFORE"] > 3 * floor
    assert cal["CONTROL_RMS_AFTER"] < 1.15 * floor
    assert cal["ITERATIONS"] <= 5
    # the blunders the simulator injected on control points are the ones flagged
    src, res = ogr.Open(sim["GCPS"]), ogr.Open(cal["OUTPUT_GPKG"])
    injected = {f["id"]: f["role"] for f in src.GetLayer(0) if f["truth_outlier"]}
    rows = {f["id"]: (f["role"], bool(f["outlier"]), f["res_sample_after"], f["res_line_after"])
            for f in res.GetLayerByName("gcps")}
    # (issue 10: check points are tested for blunders too, so the injected check blunders are now flagged as well;
    # N_OUTLIERS still counts the control points)
    flagged = {i for i, r in rows.items() if r[1] and r[0] == "control"}
    injected_control = {i for i, role in injected.items() if role == "control"}
    assert injected_control and injected_control <= flagged and len(flagged - injected_control) <= 2
    assert cal["N_OUTLIERS"] == len(flagged)
    flagged_check = {i for i, r in rows.items() if r[1] and r[0] == "check"}
    assert {i for i, role in injected.items() if role == "check"} <= flagged_check
    # check points (never estimated from), leaving out those the simulator gave a blunder: at the noise level
    chk = np.array([(r[2], r[3]) for i, r in rows.items() if r[0] == "check" and i not in injected])
    assert len(chk) > 30 and np.sqrt(np.mean(np.sum(chk ** 2, axis=1))) < 1.3 * floor
    # the recalibrated RPC against the true model on the dense check grid: only propagated GCP noise is left
    grid = _check_grid(sim["OUTPUT_FOLDER"])
    es, el = _grid_error(cal["OUTPUT_RPC"], grid)
    assert np.sqrt(np.mean(es ** 2)) < 0.15 and np.sqrt(np.mean(el ** 2)) < 0.15
    for key in ("OUTPUT_CAMERA", "OUTPUT_VRT", "OUTPUT_GPKG", "OUTPUT_PLOT", "OUTPUT_REPORT"):
        assert os.path.exists(cal[key]), key
    with open(cal["OUTPUT_CAMERA"]) as fh:
        cam = json.load(fh)
    assert cam["model"] == "lookangle-cubic" and len(cam["x"]) == 10
    # the layer reaches the engine directly: no CSV round trip left in the output folder
    assert not os.path.exists(os.path.join(cal["OUTPUT_FOLDER"], "gcps_used.csv"))


def test_applycalibration_reproduces_the_recalibrated_rpc(gf4, run_alg, tmp_path):
    sim, cal, _ = gf4
    res, fb = run_alg("gf4cal:applycalibration", {"INPUT": [sim["IMAGE"]], "CURRENT_CAMERA": sim["CAMERA"],
                                                  "NEW_CAMERA": cal["OUTPUT_CAMERA"],
                                                  "OUTPUT_FOLDER": str(tmp_path / "applied")})
    assert len(res["OUTPUT_RPCS"]) == 1 and os.path.exists(res["OUTPUT_REPORT"])
    assert res["MAX_FIT_ERROR_PX"] < 0.01 and res["MAX_SHIFT_PX"] > 1.0
    grid = _check_grid(sim["OUTPUT_FOLDER"])
    a = np.hypot(*_grid_error(res["OUTPUT_RPCS"][0], grid))
    b = np.hypot(*_grid_error(cal["OUTPUT_RPC"], grid))
    assert np.abs(a - b).max() < 0.02  # the same recalibration, through the other algorithm
    assert np.sqrt(np.mean(a ** 2)) < 0.2
    assert os.path.exists(os.path.join(tmp_path, "applied", "scene.vrt"))


def test_calibratelookangle_bad_input(gf4, run_alg, tmp_path):
    from qgis.core import QgsProcessingException
    sim, _, _ = gf4
    out = tmp_path / "cal"
    with pytest.raises(QgsProcessingException, match="(?i)camera"):
        run_alg("gf4cal:calibratelookangle", {"INPUT": sim["IMAGE"], "GCPS": sim["GCPS"],
                                              "CAMERA": str(tmp_path / "missing.json"), "OUTPUT_FOLDER": str(out)})
    assert not out.exists() or os.listdir(out) == []
    # An engine error after the output folder was made: the folder this run created goes away with it.
    bad = tmp_path / "bad_camera.json"
    bad.write_text('{"model": "lookangle-cubic", "size": [10]}')
    with pytest.raises(QgsProcessingException):
        run_alg("gf4cal:calibratelookangle", {"INPUT": sim["IMAGE"], "GCPS": sim["GCPS"], "CAMERA": str(bad),
                                              "OUTPUT_FOLDER": str(out / "sub")})
    assert not out.exists()
