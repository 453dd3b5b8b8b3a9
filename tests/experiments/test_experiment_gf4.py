"""End to end: ``gf4cal experiment gf4`` (seed 000's Tables 2-4) and the look-angle CLI on simulated GF4 scenes.

Full 10240 x 10240 geometry (the simulator and the calibration are fast enough); every number is checked against
the simulator's truth.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from gdal_gf4cal.camera import LookAngleModel
from gdal_gf4cal.cli import main
from gdal_gf4cal.rpc import RPCModel
from gdal_gf4cal.simulate.scene import write_scene

NOISE = 0.6


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    out = tmp_path_factory.mktemp("gf4exp")
    assert main(["experiment", "gf4", "--out", str(out), "--quiet"]) == 0
    with open(out / "report.json") as fh:
        return json.load(fh), out


def test_experiment_report_has_the_papers_tables(experiment):
    rep, out = experiment
    scenes = ["PMS1", "PMS2", "PMS3", "PMS4"]
    assert list(rep["table2"]) == scenes
    for t in rep["table2"].values():
        assert set(t) == {"line", "sample"} and set(t["line"]) == {"mean", "rms", "max"}
    assert list(rep["table3"]) == ["initial", "low_order_removed", "rigorous", "rpc"]
    for t in rep["table3"].values():
        assert set(t["sample"]) == {"mean", "rms", "std"}
    assert list(rep["table4"]) == scenes[1:]
    for t in rep["table4"].values():
        assert set(t) == {"before", "rigorous", "rpc"}
        for col in t.values():
            assert set(col) == {"line", "sample"} and {"mean", "rms"} <= set(col["line"])
    assert [rep["table1"][s]["gcps"] for s in scenes] == [134, 142, 139, 215]
    for name in ("camera_new.json", "camera_current.json", "PMS2_recalibrated.RPB", "residuals.png",
                 "residuals_internal.png", "residuals.gpkg"):
        assert (out / name).exists()


def test_experiment_meets_the_papers_claims(experiment):
    rep, _ = experiment
    # Table 2: RPC-based and rigorous calibrations agree to <= 0.01 px everywhere.
    for t in rep["table2"].values():
        assert t["line"]["max"] <= 0.01 and t["sample"]["max"] <= 0.01
    # Table 3: ~10 px initially (rotation), 1-2 px after removing rotation + translation, the noise after calibration.
    t3 = rep["table3"]
    assert t3["initial"]["line"]["rms"] > 5 and t3["initial"]["sample"]["rms"] > 5
    assert 0.9 < t3["low_order_removed"]["line"]["rms"] < 3 and 0.9 < t3["low_order_removed"]["sample"]["rms"] < 3
    for key in ("rigorous", "rpc"):
        for axis in ("line", "sample"):
            assert t3[key][axis]["rms"] <= 1.15 * NOISE
            assert abs(t3[key][axis]["mean"]) < 0.1
    # Table 4: independent scenes' internal accuracy from ~1.5 px to the noise.
    for t in rep["table4"].values():
        for axis in ("line", "sample"):
            assert t["before"][axis]["rms"] > 1.0
            assert t["rpc"][axis]["rms"] <= 1.15 * NOISE and t["rigorous"][axis]["rms"] <= 1.15 * NOISE
            assert abs(t["rpc"][axis]["rms"] - t["rigorous"][axis]["rms"]) < 0.005
    # Against the truth on the dense check grid: only the propagated GCP noise remains.
    for t in rep["check_grid"].values():
        for axis in ("line", "sample"):
            assert t["rpc"][axis]["rms"] <= 1.5 * t["floor_px"]
    assert rep["check_grid"]["PMS1"]["floor_px"] == pytest.approx(NOISE * math.sqrt(10 / 134))
    for c in rep["calibration"].values():
        assert c["rpc"]["iterations"] <= 5


def test_experiment_prints_the_tables(tmp_path, capsys):
    from gdal_gf4cal.experiments import gf4
    rep = gf4.run(tmp_path, write_files=False, n_gcps={"PMS4": 60})
    text = capsys.readouterr().out
    for title in ("Table 1", "Table 2", "Table 3", "Table 4", "Calibration based on RPC model"):
        assert title in text
    assert rep["table1"]["PMS4"]["gcps"] == 60


def test_unknown_experiment_is_a_one_line_error(tmp_path, capsys):
    assert main(["experiment", "nope", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert "gf4" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "x").exists()


# ------------------------------------------------------------------------------------------------ CLI
@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """Two GF4 scenes with the same cameras (same seed, other centre): calibrate on A, apply to B."""
    a = tmp_path_factory.mktemp("simA")
    b = tmp_path_factory.mktemp("simB")
    write_scene("gf4", a, seed=3, n_gcps=150, gcp_noise_px=NOISE, check_fraction=0.25)
    write_scene("gf4", b, seed=3, center=(92.8, 31.4), n_gcps=50, gcp_noise_px=NOISE)
    return a, b


def _truth_rms(rpc, grid_csv):
    g = pd.read_csv(grid_csv)
    s, l = rpc.project(g["lon"].to_numpy(), g["lat"].to_numpy(), g["h"].to_numpy())
    return (float(np.sqrt(np.mean((s - g["sample_true"]) ** 2))),
            float(np.sqrt(np.mean((l - g["line_true"]) ** 2))))


def test_cli_calibrate_then_apply(sim, tmp_path, capsys):
    from osgeo import gdal, ogr
    a, b = sim
    out = tmp_path / "cal"
    args = ["calibrate-lookangle", "--rpc", str(a / "scene.RPB"), "--gcps", str(a / "gcps.csv"),
            "--camera", str(a / "camera_current.json"), "--out", str(out), "--image", str(a / "scene.tif")]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "look-angle calibration" in text and "wrote camera" in text
    for name in ("camera_new.json", "scene.RPB", "scene.vrt", "residuals.gpkg", "residuals.png", "report.json"):
        assert (out / name).exists(), name
    rep = json.loads((out / "report.json").read_text())
    assert rep["calibration"]["iterations"] <= 5
    # The least-squares floor of this GCP layout: the covariance propagated over the array (the random layout of
    # 113 control points leaves corners thinner than sigma sqrt(10/n) assumes, so use the layout's own floor).
    prec = rep["calibration"]["precision_px"]
    n_used = rep["calibration"]["n_control"] - rep["calibration"]["n_outliers"]
    assert NOISE * math.sqrt(10 / n_used) < prec["sample"]["rms"] < 1.5 * NOISE * math.sqrt(10 / n_used)
    new_rpc = RPCModel.from_file(out / "scene.RPB")
    rms = _truth_rms(new_rpc, a / "check_grid.csv")
    assert rms[0] <= 1.5 * prec["sample"]["rms"] and rms[1] <= 1.5 * prec["line"]["rms"]
    assert min(_truth_rms(RPCModel.from_file(a / "scene.RPB"), a / "check_grid.csv")) > 5   # it was off
    # GDAL reads the new RPC through the VRT over the untouched image.
    ds = gdal.Open(str(out / "scene.vrt"))
    tr = gdal.Transformer(ds, None, ["METHOD=RPC", "RPC_HEIGHT=5000"])
    lon0, lat0 = new_rpc.localize(5120.5, 4000.25, 5000.0)
    ok, pt = tr.TransformPoint(1, lon0, lat0, 0.0)           # ground -> image: GDAL's forward RPC, exact
    assert ok and abs(pt[0] - 5120.5) < 1e-6 and abs(pt[1] - 4000.25) < 1e-6
    # The GeoPackage holds GCPs with residuals and outlier flags, and residual vectors.
    gp = ogr.Open(str(out / "residuals.gpkg"))
    names = [gp.GetLayer(i).GetName() for i in range(gp.GetLayerCount())]
    assert "gcps" in names and "residual_vectors" in names
    fields = [f.GetName() for f in gp.GetLayerByName("gcps").schema]
    assert {"res_sample_before", "res_line_after", "outlier"} <= set(fields)
    assert LookAngleModel.from_json(out / "camera_new.json").size == (10240, 10240)

    # Apply the new camera to another scene made with the same current camera.
    out2 = tmp_path / "applied"
    assert main(["apply-calibration", "--current", str(a / "camera_current.json"), "--new",
                 str(out / "camera_new.json"), "--out", str(out2), str(b / "scene.tif")]) == 0
    assert (out2 / "scene.RPB").exists() and (out2 / "scene.vrt").exists() and (out2 / "report.json").exists()
    rms_b = _truth_rms(RPCModel.from_file(out2 / "scene.RPB"), b / "check_grid.csv")
    assert rms_b[0] <= 1.5 * prec["sample"]["rms"] and rms_b[1] <= 1.5 * prec["line"]["rms"]
    assert min(_truth_rms(RPCModel.from_file(b / "scene.RPB"), b / "check_grid.csv")) > 5


def test_cli_refuses_bad_layouts_and_writes_nothing(sim, tmp_path, capsys):
    a, _ = sim
    g = pd.read_csv(a / "gcps.csv")
    corner = g[(g["sample"] < 3000) & (g["line"] < 3000)].assign(role="control")
    assert len(corner) >= 10
    few = g[g["role"] == "control"].head(8)
    for name, table, needle in (("corner", corner, "condition number"), ("few", few, "at least 10")):
        path = tmp_path / f"{name}.csv"
        table.to_csv(path, index=False)
        out = tmp_path / f"out_{name}"
        rc = main(["calibrate-lookangle", "--rpc", str(a / "scene.RPB"), "--gcps", str(path), "--camera",
                   str(a / "camera_current.json"), "--out", str(out)])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and needle in err and len(err.splitlines()) == 1
        assert not out.exists()


def test_cli_never_overwrites_without_asking(sim, tmp_path, capsys):
    a, _ = sim
    args = ["calibrate-lookangle", "--rpc", str(a / "scene.RPB"), "--gcps", str(a / "gcps.csv"), "--camera",
            str(a / "camera_current.json"), "--out", str(tmp_path)]
    assert main(args) == 0
    capsys.readouterr()
    assert main(args) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(args + ["--overwrite"]) == 0
    # Writing into the scene's own folder would replace its RPB: refused.
    args_in = args[:-1] + [str(a)]
    assert main(args_in + ["--overwrite"]) == 2
    assert "input" in capsys.readouterr().err
