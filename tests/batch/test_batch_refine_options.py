"""`gf4cal refine --batch` passes the GCP reader and plausibility options to every scene (issue 15/11 leftovers):
``--columns``, ``--gcp-pixel-convention``, ``--max-uncertainty`` and ``--no-plausibility-check`` act in each scene
exactly as in a single-scene run."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pandas as pd
import pytest

from gdal_gf4cal.cli import main
from gdal_gf4cal.rpc import RPCModel

COLUMNS = "line,sample,-,id,lon,lat,h,role"


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """Two small simulated GF4 scenes (RPB + GCPs with a header) and their GCPs as header-less CSVs with
    pixel centres at integers (GDAL - 0.5), columns in the order of COLUMNS, one per scene in a folder."""
    from gdal_gf4cal.simulate import write_scene
    d = tmp_path_factory.mktemp("bref")
    gdir = d / "gcps"
    gdir.mkdir()
    out = []
    for k, seed in enumerate((5, 6)):
        write_scene("gf4", d / f"w{k}", seed=seed, size=(192, 192), n_gcps=12, render=False, reference_ortho=False)
        rpb = d / f"scene{k}.RPB"
        shutil.copy(d / f"w{k}" / "scene.RPB", rpb)
        g = pd.read_csv(d / f"w{k}" / "gcps.csv")
        t = pd.DataFrame({"line": g["line"] - 0.5, "sample": g["sample"] - 0.5, "junk": 7, "id": g["id"],
                          "lon": g["lon"], "lat": g["lat"], "h": g["h"], "role": g["role"]})
        t.to_csv(gdir / f"scene{k}.csv", index=False, header=False, float_format="%.12f")
        out.append((str(rpb), d / f"w{k}" / "gcps.csv"))
    return d, gdir, out


def _grid_shift(a, b, rpc):
    """Largest image distance between two RPCs' projections of one ground grid (px)."""
    s, l = (x.ravel() for x in np.meshgrid(np.linspace(0, 192, 7), np.linspace(0, 192, 7)))
    lon, lat = rpc.localize(s, l, np.full(s.size, rpc.height_off))
    sa, la = a.project(lon, lat, rpc.height_off)
    sb, lb = b.project(lon, lat, rpc.height_off)
    return float(np.max(np.hypot(sa - sb, la - lb)))


def test_batch_reads_header_less_centre_gcps_like_a_single_run(scenes, tmp_path):
    d, gdir, sc = scenes
    out = tmp_path / "b"
    assert main(["refine", *(p for p, _ in sc), "--batch", "--gcps", str(gdir), "--model", "translation",
                 "--columns", COLUMNS, "--gcp-pixel-convention", "center", "--out", str(out)]) == 0
    for k, (rpb, gcps_csv) in enumerate(sc):
        single = tmp_path / f"single{k}.RPB"
        assert main(["refine", rpb, "--gcps", str(gcps_csv), "--model", "translation", "--out", str(single)]) == 0
        rpc = RPCModel.from_file(rpb)
        got, ref = RPCModel.from_file(out / f"scene{k}.RPB"), RPCModel.from_file(single)
        assert _grid_shift(got, ref, rpc) < 1e-6       # the same GCPs, the same correction
        assert _grid_shift(got, rpc, rpc) > 0.3        # and the correction is not nothing
    # read as corners (the CSV default) the same files give corrections 0.5 px off on both axes
    corner = tmp_path / "c"
    assert main(["refine", sc[0][0], "--batch", "--gcps", str(gdir), "--model", "translation",
                 "--columns", COLUMNS, "--out", str(corner)]) == 0
    rpc = RPCModel.from_file(sc[0][0])
    shift = _grid_shift(RPCModel.from_file(corner / "scene0.RPB"), RPCModel.from_file(out / "scene0.RPB"), rpc)
    assert shift == pytest.approx(np.hypot(0.5, 0.5), abs=1e-6)


def test_batch_max_uncertainty_and_plausibility_reach_each_scene(scenes, tmp_path, capsys):
    d, gdir, sc = scenes
    paths = [p for p, _ in sc]
    base = ["refine", *paths, "--batch", "--gcps", str(gdir), "--model", "affine", "--columns", COLUMNS,
            "--gcp-pixel-convention", "center"]
    # an uncertainty bound no real layout meets: every scene refused with the layout-strength message
    assert main(base + ["--max-uncertainty", "1e-6", "--out", str(tmp_path / "u")]) == 1
    err = capsys.readouterr().err
    assert err.count("uncertainty") >= 2
    rows = json.loads((tmp_path / "u" / "batch_summary.json").read_text())["scenes"]
    assert [r["status"] for r in rows] == ["failed", "failed"] and not list((tmp_path / "u").glob("*.RPB"))
    # a value that makes no sense is refused once, before any scene
    assert main(base + ["--max-uncertainty", "0", "--out", str(tmp_path / "z")]) == 2
    assert "makes no sense" in capsys.readouterr().err and not (tmp_path / "z").exists()
    # a GCP 30,000 px outside the image: refused by the plausibility check, accepted (flagged) without it
    bad = tmp_path / "bad"
    shutil.copytree(gdir, bad)
    t = pd.read_csv(bad / "scene0.csv", header=None)
    t.iloc[1, 1] += 30000.0            # the sample column of a control point
    t.to_csv(bad / "scene0.csv", index=False, header=False, float_format="%.12f")
    cmd = ["refine", paths[0], "--batch", "--gcps", str(bad), "--model", "translation", "--columns", COLUMNS,
           "--gcp-pixel-convention", "center"]
    assert main(cmd + ["--out", str(tmp_path / "p1")]) == 1
    assert "GCPs are measured outside the 192 x 192 px image" in capsys.readouterr().err
    assert main(cmd + ["--no-plausibility-check", "--out", str(tmp_path / "p2")]) == 0
    rep = json.loads((tmp_path / "p2" / "scene0.report.json").read_text())
    assert [o["id"] for o in rep["outliers"]] == [t.iloc[1, 3]]
