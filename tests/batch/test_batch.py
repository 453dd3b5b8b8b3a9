"""Issue 14: batch apply-calibration / collect-gcps with a resumable summary, on a Dask LocalCluster."""
from __future__ import annotations

import json
import os
import shutil
import signal

import numpy as np
import pandas as pd
import pytest

from gdal_gf4cal.batch import apply_calibration_batch, expand_scenes
from gdal_gf4cal.cli import main
from gdal_gf4cal.executors import get_executor
from gdal_gf4cal.rpc import RPCModel

from gf4frame import HEIGHTS, dense_check, frame_model, make_cameras
from gdal_gf4cal.rpc_fit import fit_rpc_from_model


@pytest.fixture(scope="module")
def gf4(tmp_path_factory):
    """N simulated GF4 scenes (RPB of the current camera, different targets) and their true models."""
    folder = tmp_path_factory.mktemp("gf4")
    cur, true = make_cameras()
    scenes, truths = [], {}
    for i, (lon, lat) in enumerate([(88.5, 32.5), (92.0, 30.0), (100.0, 35.0)]):
        rpc, _ = fit_rpc_from_model(frame_model(cur, target=(lon, lat, 4500.0)), height_range=HEIGHTS)
        name = f"GF4_PMS_E{lon}_N{lat}_{i}"
        p = rpc.write_rpb(str(folder / f"{name}.RPB"))
        scenes.append(str(p))
        truths[str(p)] = frame_model(true, target=(lon, lat, 4500.0))
    return {"folder": folder, "current": cur, "true": true, "scenes": scenes, "truths": truths}


def _scene_list(gf4, tmp, n):
    """n scenes (copies of the 3 geometries), a corrupt one in the middle."""
    src = tmp / "in"
    src.mkdir()
    paths, truth = [], {}
    for k in range(n):
        base = gf4["scenes"][k % 3]
        p = src / f"S{k:03d}_{os.path.basename(base)}"
        if k == n // 2:
            p.write_text("this is not an RPC file\n")
        else:
            shutil.copy(base, p)
            truth[str(p)] = gf4["truths"][base]
        paths.append(str(p))
    return paths, truth


def _check_against_truth(out_dir, truth):
    for p, model in truth.items():
        stem = os.path.splitext(os.path.basename(p))[0]
        new = RPCModel.from_file(str(out_dir / f"{stem}.RPB"))
        lon, lat, h, S, L = dense_check(model, n=8)
        s, l = new.project(lon, lat, h)
        assert np.max(np.hypot(s - S, l - L)) < 0.05, stem


def test_fifty_gf4_scenes_on_a_local_cluster_one_corrupt_rerun_does_nothing(gf4, tmp_path):
    paths, truth = _scene_list(gf4, tmp_path, 50)
    out = tmp_path / "out"
    with get_executor("local:2") as ex:
        rep = apply_calibration_batch(gf4["current"], gf4["true"], paths, out, executor=ex)
    assert rep["counts"] == {"ok": 49, "failed": 1, "skipped": 0, "cancelled": 0}
    df = pd.read_csv(out / "batch_summary.csv")
    bad = df[df["status"] == "failed"]
    assert list(bad["scene"]) == [paths[25]] and "RPC" in bad["error"].iloc[0].upper()
    assert (df["image_shift_max_px"][df["status"] == "ok"] > 5).all()
    _check_against_truth(out, truth)
    mt = {p: os.stat(out / p).st_mtime_ns for p in os.listdir(out) if p.endswith(".RPB")}
    rep2 = apply_calibration_batch(gf4["current"], gf4["true"], paths, out)
    assert rep2["counts"] == {"ok": 0, "failed": 1, "skipped": 49, "cancelled": 0}
    assert {p: os.stat(out / p).st_mtime_ns for p in mt} == mt


def test_batch_threads_missing_and_corrupt_scene_reported_rerun_skips(gf4, tmp_path):
    paths, truth = _scene_list(gf4, tmp_path, 6)
    missing = str(tmp_path / "in" / "nope.RPB")
    lst = tmp_path / "scenes.txt"
    lst.write_text("# the batch\n" + "\n".join(paths[:3]) + f"\n{missing}\n")
    scenes = [f"@{lst}", str(tmp_path / "in" / "S00[3-5]*.RPB")]
    assert expand_scenes(scenes) == paths[:3] + [missing] + paths[3:]
    out = tmp_path / "out"
    with get_executor("threads:2") as ex:
        rep = apply_calibration_batch(gf4["current"], gf4["true"], scenes, out, executor=ex)
    assert rep["counts"] == {"ok": 5, "failed": 2, "skipped": 0, "cancelled": 0}
    rows = {r["scene"]: r for r in json.loads((out / "batch_summary.json").read_text())["scenes"]}
    assert rows[missing]["error"] == f"scene not found: {missing}"
    assert rows[paths[3]]["status"] == "failed" and rows[paths[3]]["error"]
    _check_against_truth(out, truth)
    rep2 = apply_calibration_batch(gf4["current"], gf4["true"], scenes, out)
    assert rep2["counts"] == {"ok": 0, "failed": 2, "skipped": 5, "cancelled": 0}
    rep3 = apply_calibration_batch(gf4["current"], gf4["true"], scenes, out, overwrite=True)
    assert rep3["counts"] == {"ok": 5, "failed": 2, "skipped": 0, "cancelled": 0}


def _kill_one_worker_then_run(scene, outputs, *, delay_s, victim_file, overwrite=False):
    """Scene function for the killed-worker test: the first task to claim ``victim_file`` kills its worker."""
    import time
    try:
        fd = os.open(victim_file, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        os.close(fd)
        os.kill(os.getpid(), signal.SIGKILL)
    except FileExistsError:
        pass
    time.sleep(delay_s)
    with open(outputs["out"], "w") as fh:
        fh.write(scene)
    return {"pid": os.getpid()}


def test_a_worker_killed_mid_batch_its_tasks_are_retried(tmp_path):
    from gdal_gf4cal.batch import run_batch
    scenes = []
    for k in range(8):
        p = tmp_path / f"s{k}.txt"
        p.write_text(str(k))
        scenes.append(str(p))
    out = tmp_path / "out"
    with get_executor("local:2") as ex:
        rep = run_batch(_kill_one_worker_then_run, scenes, out, lambda s: {"out": str(out / os.path.basename(s))},
                        params={"delay_s": 0.2, "victim_file": str(tmp_path / "victim")}, executor=ex)
    assert rep["counts"] == {"ok": 8, "failed": 0, "skipped": 0, "cancelled": 0}, [r["error"] for r in rep["scenes"]]
    for s in scenes:
        assert (out / os.path.basename(s)).read_text() == s


def test_cli_apply_calibration_batch_and_bad_scheduler(gf4, tmp_path, capsys):
    cur, new = tmp_path / "cur.json", tmp_path / "new.json"
    gf4["current"].to_json(str(cur))
    gf4["true"].to_json(str(new))
    out = tmp_path / "out"
    rc = main(["apply-calibration", *gf4["scenes"], "--current", str(cur), "--new", str(new), "--out", str(out),
               "--batch", "--dask", "threads:2"])
    assert rc == 0 and (out / "batch_summary.csv").is_file()
    _check_against_truth(out, gf4["truths"])
    rc = main(["apply-calibration", *gf4["scenes"], "--current", str(cur), "--new", str(new), "--out",
               str(tmp_path / "o2"), "--dask", "tcp://127.0.0.1:9"])
    assert rc == 2 and "cannot reach the Dask scheduler" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_collect_gcps_then_refine_batch_on_a_local_cluster(tmp_path, capsys):
    """Batch collect-gcps (2 scenes of one area with different RPC errors + a missing one) on a LocalCluster,
    then batch refine with each scene's own table: GCPs and refined RPCs agree with the truth; the summary names
    the missing scene; a rerun skips."""
    from osgeo import gdal
    from gdal_gf4cal.gcp import read_gcps
    from matchscene import build_scene, error_affine
    scenes = []
    for k, shift in enumerate([(12.2, -9.4), (-7.5, 10.1)]):
        d = tmp_path / f"s{k}"
        d.mkdir()
        sc = build_scene(d, texture="pleiades", size=(320, 320), seed=3, error=error_affine(shift=shift))
        named = tmp_path / f"scene{k}.tif"
        gdal.Translate(str(named), sc.image)
        sc.rpc.write_rpb(str(tmp_path / f"scene{k}.RPB"))
        scenes.append((str(named), sc))
    ref, dem = scenes[0][1].reference, scenes[0][1].dem_path
    missing = str(tmp_path / "scene9.tif")
    gout = tmp_path / "gcps"
    rc = main(["collect-gcps", scenes[0][0], scenes[1][0], missing, "--reference", ref, "--dem", dem,
               "--out", str(gout), "--spacing", "40", "--dask", "local:2"])
    assert rc == 1   # the missing scene failed, the others are written
    assert f"scene not found: {missing}" in capsys.readouterr().err
    df = pd.read_csv(gout / "batch_summary.csv")
    assert list(df["status"]) == ["ok", "ok", "failed"] and (df["n_gcps"][:2] >= 20).all()
    for path, sc in scenes:
        g = read_gcps(gout / (os.path.splitext(os.path.basename(path))[0] + ".gpkg"))
        ts, tl = sc.truth(g["lon"].to_numpy(), g["lat"].to_numpy(), g["h"].to_numpy())
        assert np.sqrt(np.mean((g["sample"] - ts) ** 2 + (g["line"] - tl) ** 2)) <= 0.1
    rout = tmp_path / "refined"
    rc = main(["refine", scenes[0][0], scenes[1][0], "--batch", "--gcps", str(gout), "--model", "affine",
               "--out", str(rout), "--dask", "local:2"])
    assert rc == 0
    df = pd.read_csv(rout / "batch_summary.csv")
    assert list(df["status"]) == ["ok", "ok"] and (df["control_rms_after_px"] < 0.1).all()
    for path, sc in scenes:
        stem = os.path.splitext(os.path.basename(path))[0]
        new = RPCModel.from_file(str(rout / f"{stem}.RPB"))
        g = read_gcps(gout / f"{stem}.gpkg")
        lon, lat, h = g["lon"].to_numpy(), g["lat"].to_numpy(), g["h"].to_numpy()
        s, l = new.project(lon, lat, h)
        ts, tl = sc.truth(lon, lat, h)
        assert np.max(np.hypot(s - ts, l - tl)) < 0.3
    assert main(["refine", scenes[0][0], scenes[1][0], "--batch", "--gcps", str(gout), "--model", "affine",
                 "--out", str(rout)]) == 0
    assert list(pd.read_csv(rout / "batch_summary.csv")["status"]) == ["skipped", "skipped"]
