"""Issue 14: the batch algorithms in headless QGIS (applycalibrationbatch, collectgcpsbatch, refinerpcbatch):
many scenes, one output per scene + batch_summary.csv, failing scenes reported, reruns skip finished scenes, and
cancel mid-batch keeps the finished scenes while the running one leaves nothing."""
from __future__ import annotations

import csv
import os
import shutil

import numpy as np
import pytest

from gf4frame import HEIGHTS, dense_check, frame_model, make_cameras

SIZE = (256, 256)


def _summary(folder):
    with open(os.path.join(folder, "batch_summary.csv"), newline="") as fh:
        return {os.path.basename(r["scene"]): r for r in csv.DictReader(fh)}


@pytest.fixture(scope="module")
def gf4(tmp_path_factory):
    """4 GF4 RPB scenes of the current camera (different targets), the cameras as JSON, the true models."""
    from gdal_gf4cal.rpc_fit import fit_rpc_from_model
    d = tmp_path_factory.mktemp("gf4b")
    cur, true = make_cameras()
    scenes, truths = [], {}
    for i, (lon, lat) in enumerate([(88.5, 32.5), (92.0, 30.0), (100.0, 35.0), (95.0, 28.0)]):
        rpc, _ = fit_rpc_from_model(frame_model(cur, target=(lon, lat, 4500.0)), height_range=HEIGHTS)
        p = rpc.write_rpb(str(d / f"GF4_{i}.RPB"))
        scenes.append(str(p))
        truths[f"GF4_{i}"] = frame_model(true, target=(lon, lat, 4500.0))
    cur.to_json(str(d / "current.json"))
    true.to_json(str(d / "new.json"))
    return {"scenes": scenes, "truths": truths, "current": str(d / "current.json"), "new": str(d / "new.json")}


def test_applycalibrationbatch_missing_scene_reported_rerun_skips(run_alg, gf4, tmp_path):
    from gdal_gf4cal.rpc import RPCModel
    out = tmp_path / "out"
    params = {"INPUT": gf4["scenes"] + [str(tmp_path / "GF4_missing.RPB")], "CURRENT_CAMERA": gf4["current"],
              "NEW_CAMERA": gf4["new"], "OUTPUT_FOLDER": str(out), "THREADS": 2}
    res, fb = run_alg("gf4cal:applycalibrationbatch", params)
    assert (res["N_OK"], res["N_FAILED"], res["N_SKIPPED"]) == (4, 1, 0)
    rows = _summary(out)
    assert rows["GF4_missing.RPB"]["status"] == "failed" and "not found" in rows["GF4_missing.RPB"]["error"]
    assert "GF4_missing.RPB" in fb.text()
    for stem, model in gf4["truths"].items():
        assert rows[f"{stem}.RPB"]["status"] == "ok"
        new = RPCModel.from_file(str(out / f"{stem}.RPB"))
        lon, lat, h, S, L = dense_check(model, n=8)
        s, l = new.project(lon, lat, h)
        assert np.max(np.hypot(s - S, l - L)) < 0.05, stem
    assert res["SUMMARY"] == str(out / "batch_summary.csv")
    res2, _ = run_alg("gf4cal:applycalibrationbatch", params)
    assert (res2["N_OK"], res2["N_FAILED"], res2["N_SKIPPED"]) == (0, 1, 4)


def test_batch_refuses_a_local_cluster_inside_qgis_gui(run_alg, gf4, tmp_path, monkeypatch):
    """Inside the QGIS application sys.executable is QGIS: a LocalCluster would start QGIS processes."""
    import sys
    from qgis.core import QgsProcessingException
    monkeypatch.setattr(sys, "executable", "/usr/bin/qgis")
    with pytest.raises(QgsProcessingException, match="tcp://HOST:PORT"):
        run_alg("gf4cal:applycalibrationbatch", {"INPUT": gf4["scenes"][:1], "CURRENT_CAMERA": gf4["current"],
                                                 "NEW_CAMERA": gf4["new"], "OUTPUT_FOLDER": str(tmp_path / "o"),
                                                 "DASK": "local:2"})
    assert not (tmp_path / "o").exists()


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """Three copies of one rendered GF4 crop (image + RPB of the current model), a reference and the DEM."""
    from gdal_gf4cal.simulate import write_reference_ortho, write_scene
    from gdal_gf4cal.simulate.render import model_bounds
    d = tmp_path_factory.mktemp("rendered_batch")
    res = write_scene("gf4", str(d / "scene"), seed=2, size=SIZE, n_gcps=10, render=True, workers=1,
                      reference_ortho=False)
    sim = res.scene.images[0]
    ref = write_reference_ortho(str(d / "reference.tif"), model_bounds(sim.true, margin=0.1), 40.0 / 111320.0,
                                seed=2, scale_m=3.0 * sim.gsd_m)
    paths = res.images[""].paths
    scenes = []
    for name in ("a", "b", "c"):
        shutil.copy(paths["image"], d / f"{name}.tif")
        shutil.copy(paths["rpc"], d / f"{name}.RPB")
        scenes.append(str(d / f"{name}.tif"))
    return {"scenes": scenes, "dem": res.dem_path, "reference": ref, "true": sim.true}


def _collect_params(rendered, out, **kw):
    return dict({"INPUT": rendered["scenes"], "REFERENCE": rendered["reference"], "DEM": rendered["dem"],
                 "SPACING": 32, "WINDOW": 64, "OUTPUT_FOLDER": str(out), "THREADS": 2}, **kw)


def test_collectgcpsbatch_then_refinerpcbatch(run_alg, rendered, tmp_path):
    from gdal_gf4cal.gcp import read_gcps
    gout, rout = tmp_path / "gcps", tmp_path / "rpcs"
    res, fb = run_alg("gf4cal:collectgcpsbatch", _collect_params(rendered, gout))
    assert (res["N_OK"], res["N_FAILED"]) == (3, 0), fb.text()
    for name in ("a", "b", "c"):
        g = read_gcps(str(gout / f"{name}.gpkg"))
        assert len(g) >= 20
        ts, tl = rendered["true"].project(g["lon"].to_numpy(), g["lat"].to_numpy(), g["h"].to_numpy())
        assert np.sqrt(np.mean((g["sample"].to_numpy() - ts) ** 2 + (g["line"].to_numpy() - tl) ** 2)) <= 0.1
    rows = _summary(gout)
    assert int(rows["a.tif"]["n_gcps"]) == len(read_gcps(str(gout / "a.gpkg")))
    res, fb = run_alg("gf4cal:refinerpcbatch", {"INPUT": rendered["scenes"], "GCP_FOLDER": str(gout), "MODEL": 2,
                                                "OUTPUT_FOLDER": str(rout)})
    assert (res["N_OK"], res["N_FAILED"]) == (3, 0), fb.text()
    for name, r in _summary(rout).items():
        assert float(r["control_rms_after_px"]) < 0.25, name
        assert (rout / f"{name[:-4]}.RPB").is_file() and (rout / f"{name[:-4]}.report.json").is_file()


@pytest.mark.parametrize("threads", [1, 2])
def test_collectgcpsbatch_cancel_mid_batch_keeps_finished_scenes_only(qgis_app, rendered, tmp_path, threads):
    """Cancel once the batch is past 45 %: scenes finished before stay (complete GeoPackages), the running ones
    leave no file (not even a temporary), and the summary says 'cancelled'."""
    import processing
    from qgis.core import QgsProcessingContext, QgsProcessingException, QgsProcessingFeedback, QgsProject

    fb = QgsProcessingFeedback()
    fb.progressChanged.connect(lambda p: fb.cancel() if p > 45 else None)
    ctx = QgsProcessingContext()
    ctx.setProject(QgsProject.instance())
    out = tmp_path / "out"
    with pytest.raises(QgsProcessingException, match="(?i)cancelled.*finished scenes are kept"):
        processing.run("gf4cal:collectgcpsbatch", _collect_params(rendered, out, THREADS=threads), feedback=fb,
                       context=ctx)
    rows = _summary(out)
    statuses = [rows[f"{n}.tif"]["status"] for n in ("a", "b", "c")]
    assert "cancelled" in statuses and set(statuses) <= {"ok", "cancelled"}
    if threads == 1:
        assert statuses == ["ok", "cancelled", "cancelled"]
    files = sorted(os.listdir(out))
    assert files == sorted(["batch_summary.csv", "batch_summary.json"]
                           + [f"{n}.gpkg" for n, s in zip("abc", statuses) if s == "ok"])
    from gdal_gf4cal.gcp import read_gcps
    for n, s in zip("abc", statuses):
        if s == "ok":
            assert len(read_gcps(str(out / f"{n}.gpkg"))) >= 20
