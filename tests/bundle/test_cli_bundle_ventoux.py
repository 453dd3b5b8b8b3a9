"""``gf4cal bundle-adjust`` on the real Pleiades Ventoux stereo crops (issue 22 "must show"; tests/ventouxpair.py):
ties matched raw to raw through the product RPCs moved to the crops and SRTM above EGM96; the written RPCs (RPB and
VRT) reproduce the adjusted tie rays, ``gdalwarp -rpc`` warps the VRT; shareloc's right RPC biased by 60 lines is
recovered within 0.1 px of the unbiased run, and the residual relative bias of the unbiased pair is reported."""
from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from osgeo import gdal, ogr

import ventouxpair as V
from gdal_gf4cal import RPCModel
from gdal_gf4cal.cli import main


def _run(capsys, folder, out, *extra, biased=False):
    left, right = V.pair(folder, biased=biased)
    rc = main(["bundle-adjust", str(left), str(right), "--match-ties", *V.dem_args(), *extra, "--out", str(out)])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    with open(out / "report.json") as fh:
        return json.load(fh), cap


@pytest.fixture(scope="module")
def unbiased(tmp_path_factory):
    """The pair as delivered, default options (the realcheck case): (report, stdout, out folder)."""
    base = tmp_path_factory.mktemp("ventoux")
    left, right = V.pair(base / "in")
    out = base / "out"
    assert main(["bundle-adjust", str(left), str(right), "--match-ties", *V.dem_args(), "--out", str(out)]) == 0
    with open(out / "report.json") as fh:
        return json.load(fh), out


def test_outputs_and_numbers(unbiased):
    rep, out = unbiased
    assert sorted(p.name for p in out.iterdir()) == ["left.RPB", "left.vrt", "report.json", "residuals.gpkg",
                                                      "right.RPB", "right.vrt", "ties.csv", "ties.png"]
    assert rep["ties"]["n_points"] >= 150 and rep["ties"]["source"] == "raw-to-raw matching"
    before, after = rep["reprojection_px"]["before"], rep["reprojection_px"]["after"]
    # RMS per component: the vendor RPCs disagree by ~1.7 px on these ties; one translation per view leaves the
    # matching noise
    assert 1.4 < before["all"] < 2.2
    assert after["all"] < 0.09 and after["per_pair"]["left|right"] < 0.09
    assert set(rep["views"]) == {"left", "right"} and all(v["model_used"] == "translation"
                                                         for v in rep["views"].values())
    assert any("translation estimated instead" in n for n in rep["notes"])     # ties span 22 % of the lines
    # the residual relative bias of the pair, with its sigma from the full covariance
    rel = rep["relative_to_first_view_px"]["views"]["right"]
    assert rel["sample_std"] > 0 and rel["line_std"] > rel["sample_std"]       # along the epipolar: the heights
    assert abs(rel["sample"]) > 3 * rel["sample_std"]
    assert rep["views"]["right"]["correction"]["parameter_std_px"]["sample_1"] > 0
    assert rep["views"]["left"]["precision_px"]["max"] > 0
    assert np.isfinite(rep["datum_drift_m"]) and rep["estimate"]["converged"]


def test_written_rpcs_reproduce_the_adjusted_rays(unbiased):
    """The files, not the engine's memory: the tie points' adjusted ground (residuals.gpkg 'tie_points') projects
    through each written RPC (the RPB, and the VRT's RPC) onto the matched measurements (ties.csv) at the reported
    after RMS (over the rays the adjustment kept: the view's layer flags the others); the VRT carries the same RPC
    as the RPB."""
    rep, out = unbiased
    pts = _layer(out / "residuals.gpkg", "tie_points").set_index("point_id")
    ties = pd.read_csv(out / "ties.csv", dtype={"point_id": str})
    for k in ("left", "right"):
        rpb, vrt = RPCModel.from_file(out / f"{k}.RPB"), RPCModel.from_file(out / f"{k}.vrt")
        kept = _layer(out / "residuals.gpkg", f"{k}_gcps")
        kept = set(kept.loc[~kept["outlier"].astype(bool), "id"].astype(str))
        assert len(kept) > 0.8 * rep["ties"]["n_points"]
        t = ties[(ties["image_id"] == k) & ties["point_id"].isin(kept)]
        g = pts.loc[t["point_id"]]
        s, l = rpb.project(g["lon"].to_numpy(), g["lat"].to_numpy(), g["h"].to_numpy())
        sv, lv = vrt.project(g["lon"].to_numpy(), g["lat"].to_numpy(), g["h"].to_numpy())
        assert np.max(np.hypot(s - sv, l - lv)) < 1e-9
        rms = float(np.sqrt(np.mean((t["sample"].to_numpy() - s) ** 2 + (t["line"].to_numpy() - l) ** 2) / 2))
        assert rms == pytest.approx(rep["views"][k]["reprojection_px"]["after"], abs=2e-3)


def test_gdalwarp_uses_the_vrt_and_the_rpb(unbiased, tmp_path):
    """``gdalwarp -rpc`` on the VRT, and on the image with the RPB put beside it (GDAL reads it as the image's RPC):
    both open with the new RPC and warp to the same ground."""
    import shutil
    rep, out = unbiased
    shutil.copyfile(V.LEFT_TIF, tmp_path / "left.tif")
    shutil.copyfile(out / "left.RPB", tmp_path / "left.RPB")
    new = RPCModel.from_file(out / "left.RPB")
    warped = {}
    for name, src in (("vrt", out / "left.vrt"), ("rpb", tmp_path / "left.tif")):
        md = gdal.Open(str(src)).GetMetadata("RPC")
        assert float(md["LINE_OFF"]) == pytest.approx(new.line_off) and float(md["SAMP_OFF"]) == pytest.approx(
            new.samp_off)
        ds = gdal.Warp(str(tmp_path / f"ortho_{name}.tif"), str(src), rpc=True, dstSRS="EPSG:4326",
                       transformerOptions=[f"RPC_DEM={V.SRTM}"])
        assert ds is not None and ds.RasterXSize > 100
        assert np.count_nonzero(ds.GetRasterBand(1).ReadAsArray()) > 0.3 * ds.RasterXSize * ds.RasterYSize
        warped[name] = ds.GetGeoTransform()
    assert warped["vrt"] == pytest.approx(warped["rpb"])


def test_residual_layers_are_styled(unbiased):
    rep, out = unbiased
    ds = ogr.Open(str(out / "residuals.gpkg"))
    names = {ds.GetLayer(i).GetName() for i in range(ds.GetLayerCount())}
    assert {"left_gcps", "left_residual_vectors", "left_residual_vectors_before", "right_gcps", "tie_points",
            "layer_styles"} <= names
    styles = ds.ExecuteSQL("SELECT f_table_name FROM layer_styles")
    styled = {f.GetField(0) for f in styles}
    ds.ReleaseResultSet(styles)
    assert {"left_gcps", "left_residual_vectors", "right_residual_vectors_before", "tie_points"} <= styled
    assert ds.GetLayerByName("right_gcps").GetFeatureCount() == rep["ties"]["n_points"]


def _layer(path, name):
    ds = ogr.Open(str(path))
    lyr = ds.GetLayerByName(name)
    rows = [{**f.items(), "lon": f.GetGeometryRef().GetX(), "lat": f.GetGeometryRef().GetY()} for f in lyr]
    return pd.DataFrame(rows)


def _delta(a, b):
    """Biased run minus unbiased run: each view's correction at its image centre and the right one's relative to
    the left (px, (sample, line))."""
    per = {k: np.array([b["views"][k]["correction"]["parameters_px"][f"{c}_1"]
                        - a["views"][k]["correction"]["parameters_px"][f"{c}_1"] for c in ("sample", "line")])
           for k in ("left", "right")}
    ra, rb = (r["relative_to_first_view_px"]["views"]["right"] for r in (a, b))
    return per, np.array([rb["sample"] - ra["sample"], rb["line"] - ra["line"]])


@pytest.mark.slow
def test_sixty_pixel_bias_recovered_relative_to_the_unbiased_run(tmp_path, capsys):
    """shareloc's right_image_bias.geom = the right RPC with LINE_OFF + 60 px: between an unbiased and a biased run
    (the same options) the right view's correction must move by (0, -60) px and the left's not at all, relative
    and per view. Tie points fix the part across the epipolar lines; along them (57.9 of the 60 px here) a relative
    bias is a height shift of the ties, fixed by the DEM's height prior on every tie (± 5 m, re-sampled where the
    ties move). The user says which RPC is off (left 3 px, right 100 px): measured relative (+0.013, -60.038) px,
    left (-0.008, +0.051), right (+0.005, -59.988)."""
    opts = ("--prior-sigma", "left=3", "right=100")
    a, _ = _run(capsys, tmp_path / "a", tmp_path / "oa", *opts)
    b, cap = _run(capsys, tmp_path / "b", tmp_path / "ob", *opts, biased=True)
    per, rel = _delta(a, b)
    assert rel == pytest.approx([0.0, -V.BIAS_LINE_PX], abs=0.1), rel
    assert per["left"] == pytest.approx([0.0, 0.0], abs=0.1), per
    assert per["right"] == pytest.approx([0.0, -V.BIAS_LINE_PX], abs=0.1), per
    assert b["reprojection_px"]["before"]["all"] > 7 and b["reprojection_px"]["after"]["all"] < 0.09
    assert "right: translation correction" in cap.out
    assert not [w for r in (a, b) for w in r["warnings"] if "prior sigmas" in w]


@pytest.mark.slow
def test_default_options_recover_the_bias_relative_to_the_first_view(unbiased, tmp_path, capsys):
    """Default options, as a user runs it: a pair is adjusted relative to its first view (the second view's prior
    1000x wider), so the 60 lines of the right RPC go to the right view whole, per view and relative, within 0.1 px
    of the unbiased run. (Equal priors split them, +31/-31 lines: the block moved ~15 m along track and, on Ventoux's
    slopes, the DEM's heights there moved the relative correction to -62.4 lines.)"""
    a, _ = unbiased
    b, cap = _run(capsys, tmp_path / "b", tmp_path / "ob", biased=True)
    per, rel = _delta(a, b)
    assert rel == pytest.approx([0.0, -V.BIAS_LINE_PX], abs=0.1), rel
    assert per["left"] == pytest.approx([0.0, 0.0], abs=0.1), per
    assert per["right"] == pytest.approx([0.0, -V.BIAS_LINE_PX], abs=0.1), per
    assert "the pair follows its first view, left" in cap.err
    assert not [w for r in (a, b) for w in r["warnings"] if "prior sigmas" in w]


def _three(capsys, folder, *, biased=False):
    """The pair plus the left product's 4-band MS crop (2.8 m pixels; tests/data/panms_ventoux), matched, default
    options: the report."""
    import shutil
    left, right = V.pair(folder / "in", biased=biased)
    for ext in ("tif", "geom"):
        shutil.copyfile(V.DATA / "panms_ventoux" / f"lowres_color_image.{ext}", folder / "in" / f"ms.{ext}")
    out = folder / "out"
    rc = main(["bundle-adjust", str(left), str(right), str(folder / "in" / "ms.tif"), "--match-ties",
               *V.dem_args(), "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    with open(out / "report.json") as fh:
        return json.load(fh), out


@pytest.mark.slow
def test_three_views_of_two_resolutions(tmp_path, capsys):
    """The pair plus the left product's MS crop: the three overlapping pairs matched (scale 4 between pan and MS),
    every view adjusted, the stereo pair as good as alone. Then the right RPC 60 lines off, default options: with
    three views the odd one is known (left and MS agree): its prior is down-weighted (Tukey, a warning names it)
    and the right view's correction relative to the left moves by (-0.03, -59.92) px between the runs (the block
    held by two views instead of three: the left's own correction moves by 1.3 px)."""
    rep, out = _three(capsys, tmp_path / "a")
    pairs = {tuple(p["pair"]): p["n_ties"] for p in rep["ties"]["pairs_matched"]}
    assert set(pairs) == {("left", "right"), ("left", "ms"), ("right", "ms")} and min(pairs.values()) >= 30
    after = rep["reprojection_px"]["after"]
    assert after["per_pair"]["left|right"] < 0.1
    assert all(after["per_view"][k] < rep["reprojection_px"]["before"]["per_view"][k] for k in ("left", "right", "ms"))
    assert sorted(p.name for p in out.iterdir() if p.suffix == ".vrt") == ["left.vrt", "ms.vrt", "right.vrt"]
    assert not [w for w in rep["warnings"] if "sigmas" in w]
    b, _ = _three(capsys, tmp_path / "b", biased=True)
    odd = [w for w in b["warnings"] if "beyond what the other views agree on" in w]
    assert len(odd) == 1 and odd[0].startswith("view(s) right (")
    ra, rb = (r["relative_to_first_view_px"]["views"]["right"] for r in (rep, b))
    rel = np.array([rb["sample"] - ra["sample"], rb["line"] - ra["line"]])
    assert rel == pytest.approx([0.0, -V.BIAS_LINE_PX], abs=0.1), rel
