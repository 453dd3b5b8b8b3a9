"""``gf4cal refine`` end to end: real RPC, GCP file, refined VRT that ``gdalwarp -rpc -to RPC_DEM=`` uses."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from osgeo import gdal, osr

from gdal_gf4cal import RPCModel
from gdal_gf4cal.cli import main
from gdal_gf4cal.compensation import CompensatedRPC, CompensationResult

gdal.UseExceptions()
DATA = Path(__file__).parents[1] / "data" / "compensation"
SIZE = 256
BLOBS = [(60.0, 70.0), (190.0, 100.0), (120.0, 200.0)]
SHIFT = (6.0, -4.0)   # true image-space error (sample, line) px of the RPC


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A 256 x 256 image with bright blobs, carrying the real WV3 RPC (re-centred on the chip) as .RPB; a DEM."""
    d = tmp_path_factory.mktemp("refine")
    base = RPCModel.from_file(DATA / "md_dg.RPB")
    # Pixel (0, 0) of the chip is pixel (900, 750) of the WV3 scene: shift the image offsets by that much.
    rpc = base.replace(samp_off=base.samp_off - 900, line_off=base.line_off - 750, source=None)
    img = d / "chip.tif"
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    arr = np.zeros((SIZE, SIZE))
    for bx, by in BLOBS:
        arr += 200.0 * np.exp(-((xx - bx) ** 2 + (yy - by) ** 2) / (2 * 3.0 ** 2))
    ds = gdal.GetDriverByName("GTiff").Create(str(img), SIZE, SIZE, 1, gdal.GDT_Float32)
    ds.GetRasterBand(1).WriteArray(arr)
    ds = None
    rpc.write_rpb(d / "chip.RPB")
    # DEM: a gentle slope in EPSG:4326 around the chip.
    lon, lat = rpc.localize(np.array([0, SIZE, 0, SIZE]), np.array([0, 0, SIZE, SIZE]), np.full(4, 100.0))
    x0, x1, y0, y1 = lon.min() - 0.01, lon.max() + 0.01, lat.min() - 0.01, lat.max() + 0.01
    n = 60
    dem_path = d / "dem.tif"
    dd = gdal.GetDriverByName("GTiff").Create(str(dem_path), n, n, 1, gdal.GDT_Float32)
    dd.SetGeoTransform((x0, (x1 - x0) / n, 0, y1, 0, -(y1 - y0) / n))
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(4326)
    dd.SetProjection(srs.ExportToWkt())
    gx = np.linspace(0, 1, n)
    dd.GetRasterBand(1).WriteArray(np.tile(80.0 + 150.0 * gx, (n, 1)).astype(np.float32))
    dd = None
    # GCPs from the "true" sensor = RPC shifted by SHIFT, noise 0.2 px, one blunder.
    truth = CompensatedRPC(rpc, CompensationResult.from_coefficients(
        "translation", (rpc.samp_off + 0.5, rpc.samp_scale, rpc.line_off + 0.5, rpc.line_scale),
        [SHIFT[0]], [SHIFT[1]]))
    rng = np.random.default_rng(0)
    m = 30
    s, l = rng.uniform(0, SIZE, m), rng.uniform(0, SIZE, m)
    h = rng.uniform(80, 230, m)
    glon, glat = truth.localize(s, l, h)
    gcps = pd.DataFrame({"id": [f"P{i:02d}" for i in range(m)], "lon": glon, "lat": glat, "h": h,
                         "sample": s + rng.normal(0, 0.2, m), "line": l + rng.normal(0, 0.2, m),
                         "role": ["control"] * 20 + ["check"] * 10})
    gcps.loc[5, "sample"] += 15.0
    gcps.to_csv(d / "gcps.csv", index=False)
    return {"dir": d, "image": img, "rpc": rpc, "truth": truth, "dem": dem_path, "gcps": d / "gcps.csv"}


def _warp(src, dem, dst, bounds, res):
    gdal.Warp(str(dst), str(src), rpc=True, transformerOptions=[f"RPC_DEM={dem}"], dstSRS="EPSG:4326",
              outputBounds=bounds, xRes=res, yRes=res, resampleAlg="bilinear", format="GTiff")
    ds = gdal.Open(str(dst))
    return ds.GetRasterBand(1).ReadAsArray().astype(float), ds.GetGeoTransform()


def _centroids(arr, gt, around):
    """Intensity centroids (lon, lat) of the blobs, each in a window around its expected position."""
    out = []
    for lon, lat in around:
        c = (lon - gt[0]) / gt[1]
        r = (lat - gt[3]) / gt[5]
        r0, r1, c0, c1 = int(r) - 12, int(r) + 13, int(c) - 12, int(c) + 13
        win = arr[r0:r1, c0:c1]
        win = np.where(win > 0.2 * win.max(), win, 0.0)
        yy, xx = np.mgrid[r0:r1, c0:c1] + 0.5
        cx, cy = (win * xx).sum() / win.sum(), (win * yy).sum() / win.sum()
        out.append((gt[0] + cx * gt[1], gt[3] + cy * gt[5]))
    return np.array(out)


def test_refine_writes_vrt_that_gdalwarp_orthorectifies_with(scene):
    d = scene["dir"]
    out, report, resid = d / "refined.vrt", d / "report.json", d / "residuals.gpkg"
    code = main(["refine", str(scene["image"]), "--gcps", str(scene["gcps"]), "--model", "translation",
                 "--dem", str(scene["dem"]), "--out", str(out), "--report", str(report), "--residuals", str(resid)])
    assert code == 0
    rep = json.loads(report.read_text())
    for role, n in (("control", 19), ("check", 10)):
        for when in ("before", "after"):
            st = rep[role][when]
            assert st["n"] == n
            for ax in ("line", "sample"):
                assert set(st[ax]) >= {"mean", "rms", "std", "max"}
            assert st["ce90_m"] > 0
        assert rep[role]["after"]["sample"]["rms"] < 0.1 * rep[role]["before"]["sample"]["rms"]
    assert [o["id"] for o in rep["outliers"]] == ["P05"]
    assert rep["outliers"][0]["norm_res_sample"] > 10
    assert rep["apply"]["exact"] is True
    # The VRT carries the refined RPC over the untouched image.
    refined = RPCModel.from_file(out)
    vrt_ds = gdal.Open(str(out))
    assert vrt_ds.GetFileList()[1:] == [] or str(scene["image"].name) in " ".join(vrt_ds.GetFileList())
    lonc, latc = scene["truth"].localize(128.0, 128.0, 150.0)
    s_ref, l_ref = refined.project(lonc, latc, 150.0)
    assert abs(s_ref - 128.0) < 0.2 and abs(l_ref - 128.0) < 0.2
    # GCP GeoPackage has the schema fields.
    from osgeo import ogr
    gpkg = ogr.Open(str(resid))   # keep the data source alive while its layer is used
    lyr = gpkg.GetLayerByName("gcps")
    names = {lyr.GetLayerDefn().GetFieldDefn(i).GetName() for i in range(lyr.GetLayerDefn().GetFieldCount())}
    assert {"id", "lon", "lat", "h", "sample", "line", "role", "outlier", "res_sample_after"} <= names

    # Orthorectify the image with the original RPC and with the refined VRT onto one grid; measure the shift.
    rpc, dem = scene["rpc"], scene["dem"]
    lon, lat = rpc.localize(np.array([0, SIZE, 0, SIZE]), np.array([0, 0, SIZE, SIZE]), np.full(4, 150.0))
    res = 0.6 * (lon.max() - lon.min()) / SIZE
    bounds = (lon.min() - 40 * res, lat.min() - 40 * res, lon.max() + 40 * res, lat.max() + 40 * res)
    a0, gt0 = _warp(scene["image"], dem, d / "ortho_orig.tif", bounds, res)
    a1, gt1 = _warp(out, dem, d / "ortho_refined.tif", bounds, res)
    from gdal_gf4cal import DEM
    dem_obj = DEM.from_file(dem)
    bs = np.array([b[0] for b in BLOBS])
    bl = np.array([b[1] for b in BLOBS])
    exp0 = np.column_stack(rpc.localize_dem(bs, bl, dem_obj)[:2])
    exp1 = np.column_stack(refined.localize_dem(bs, bl, dem_obj)[:2])
    got0, got1 = _centroids(a0, gt0, exp0), _centroids(a1, gt1, exp1)
    shift_exp = (exp1 - exp0) / res
    shift_got = (got1 - got0) / res
    assert np.all(np.hypot(*shift_exp.T) > 5)                   # the refinement moves the ortho by > 5 px
    assert np.allclose(shift_got, shift_exp, atol=0.15), (shift_got, shift_exp)
    # ... and the refined ortho puts the blobs where the true sensor sees them.
    true_pos = np.column_stack(scene["truth"].localize_dem(bs, bl, dem_obj)[:2])
    assert np.max(np.hypot(*((got1 - true_pos) / res).T)) < 0.3


def test_refine_affine_to_sidecars_with_check_fraction(scene, tmp_path):
    for name in ("out.RPB", "out_RPC.TXT"):
        out = tmp_path / name
        code = main(["refine", str(scene["image"]), "--gcps", str(scene["gcps"]), "--model", "affine",
                     "--check-fraction", "0.3", "--seed", "1", "--leave-one-out", "--out", str(out),
                     "--report", str(tmp_path / f"{name}.json")])
        assert code == 0
        rep = json.loads((tmp_path / f"{name}.json").read_text())
        assert rep["check"]["before"]["n"] + rep["check"]["n_outliers"] == 9
        assert rep["apply"]["method"] == "refit" and rep["apply"]["refit_max_px"] <= 0.01
        assert rep["leave_one_out"]["n"] == rep["control"]["after"]["n"]
        back = RPCModel.from_file(out)
        lonc, latc = scene["truth"].localize(200.0, 40.0, 150.0)
        s, l = back.project(lonc, latc, 150.0)
        assert abs(s - 200.0) < 0.3 and abs(l - 40.0) < 0.3


def test_refine_errors_are_one_line(scene, tmp_path, capsys):
    img, gcps = str(scene["image"]), str(scene["gcps"])
    rpb = str(scene["dir"] / "chip.RPB")
    cases = [
        (["refine", img, "--gcps", gcps, "--model", "affine", "--out", rpb], "input"),
        (["refine", rpb, "--gcps", gcps, "--model", "affine", "--out", str(tmp_path / "a.vrt")], "not an image"),
        (["refine", img, "--gcps", str(tmp_path / "none.csv"), "--model", "affine", "--out",
          str(tmp_path / "b.RPB")], "not found"),
        (["refine", img, "--gcps", gcps, "--model", "detector-poly", "--out", str(tmp_path / "c.RPB")], "order"),
        (["refine", img, "--gcps", gcps, "--model", "affine", "--out", str(tmp_path / "d.tif")], ".RPB"),
    ]
    before = Path(rpb).read_bytes()
    for argv, needle in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("gf4cal: error:") and needle in err[0], err
    assert Path(rpb).read_bytes() == before
    few = tmp_path / "few.csv"
    pd.read_csv(gcps).iloc[:5].to_csv(few, index=False)
    assert main(["refine", img, "--gcps", str(few), "--model", "poly2", "--out", str(tmp_path / "e.RPB")]) == 2
    assert "at least 6 control" in capsys.readouterr().err


def test_refine_from_qgis_points_with_heights_from_dem(scene, tmp_path):
    """GCPs picked in the QGIS Georeferencer (no heights): heights come from --dem."""
    from gdal_gf4cal import DEM
    rng = np.random.default_rng(5)
    s, l = rng.uniform(0, SIZE, 15), rng.uniform(0, SIZE, 15)
    lon, lat, _ = scene["truth"].localize_dem(s, l, DEM.from_file(scene["dem"]))
    pts = tmp_path / "chip.tif.points"
    rows = "\n".join(f"{a!r},{b!r},{x!r},{-y!r},1,0,0,0" for a, b, x, y in zip(lon, lat, s, l))
    pts.write_text("#CRS: EPSG:4326\nmapX,mapY,sourceX,sourceY,enable,dX,dY,residual\n" + rows + "\n")
    out, rep = tmp_path / "p.RPB", tmp_path / "p.json"
    assert main(["refine", str(scene["image"]), "--gcps", str(pts), "--model", "translation", "--out", str(out),
                 "--report", str(rep)]) == 2          # no heights and no DEM: a clear error
    assert main(["refine", str(scene["image"]), "--gcps", str(pts), "--model", "translation", "--dem",
                 str(scene["dem"]), "--out", str(out), "--report", str(rep)]) == 0
    r = json.loads(rep.read_text())
    assert r["control"]["before"]["sample"]["rms"] > 5 and r["control"]["after"]["sample"]["rms"] < 1e-3


def test_refine_refuses_a_sidecar_that_would_shadow_the_input_rpc(scene, tmp_path, capsys):
    """An image with its RPC in TIFF tags: GDAL would read a new ``<stem>.RPB`` / ``<stem>_RPC.TXT`` next to it
    as *the image's* RPC, silently changing the input. Refused, nothing written, the image reads as before."""
    img = tmp_path / "tagged.tif"
    gdal.Translate(str(img), str(scene["image"]))          # RPC from chip.RPB copied into the TIFF tags
    assert gdal.Open(str(img)).GetFileList() == [str(img)]
    md = gdal.Open(str(img)).GetMetadata("RPC")
    for name in ("tagged.RPB", "tagged_RPC.TXT", "TAGGED.rpb", "tagged_rpc.txt"):
        code = main(["refine", str(img), "--gcps", str(scene["gcps"]), "--model", "translation", "--out",
                     str(tmp_path / name)])
        assert code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "would be read by GDAL as the RPC of" in err[0], err
        assert not (tmp_path / name).exists()
    assert gdal.Open(str(img)).GetMetadata("RPC") == md
    # Any other name is fine.
    assert main(["refine", str(img), "--gcps", str(scene["gcps"]), "--model", "translation", "--out",
                 str(tmp_path / "tagged_refined.RPB")]) == 0
    assert gdal.Open(str(img)).GetMetadata("RPC") == md


def _refined(scene, tmp_path, gcps, name, *extra):
    """``gf4cal refine --model translation`` with ``gcps``: (RPCModel written, report dict)."""
    out, rep = tmp_path / f"refined_{name}.RPB", tmp_path / f"refined_{name}.json"
    assert main(["refine", str(scene["image"]), "--gcps", str(gcps), "--model", "translation", "--out", str(out),
                 "--report", str(rep), *extra]) == 0
    return RPCModel.from_file(out), json.loads(rep.read_text())


def _same_rpc(a, b, tol=1e-9):
    """Both RPCs project a grid of ground points to the same image points within ``tol`` px."""
    lon, lat = a.localize(*np.meshgrid(np.linspace(0, SIZE, 7), np.linspace(0, SIZE, 7)), 150.0)
    pa, pb = np.asarray(a.project(lon, lat, 150.0)), np.asarray(b.project(lon, lat, 150.0))
    return float(np.abs(pa - pb).max()) <= tol


def test_refine_reads_headerless_csv_and_orthority_geojson_as_the_csv(scene, tmp_path):
    """Issue 15: a header-less CSV (``--columns``, either ``--gcp-pixel-convention``) and an orthority GeoJSON
    written from the CSV give the same refined RPC as the CSV; the wrong convention shifts it by 0.5 px."""
    from gdal_gf4cal.gcp_formats import write_orthority_geojson
    gcps = pd.read_csv(scene["gcps"])
    ref, ref_rep = _refined(scene, tmp_path, scene["gcps"], "csv")
    bare = tmp_path / "bare.txt"            # other column order, no header, pixel centres at integers
    centred = gcps.assign(sample=gcps["sample"] - 0.5, line=gcps["line"] - 0.5)
    centred[["line", "sample", "id", "lat", "lon", "h", "role"]].to_csv(bare, index=False, header=False)
    cols = ["--columns", "line,sample,id,lat,lon,h,role"]
    from_bare, bare_rep = _refined(scene, tmp_path, bare, "bare", *cols, "--gcp-pixel-convention", "center")
    assert _same_rpc(ref, from_bare, 1e-6)
    assert bare_rep["control"]["after"]["n"] == ref_rep["control"]["after"]["n"] == 19   # one blunder out
    corner = tmp_path / "corner.csv"
    gcps[["id", "sample", "line", "lon", "lat", "h", "role"]].to_csv(corner, index=False, header=False)
    assert _same_rpc(ref, _refined(scene, tmp_path, corner, "corner", "--columns", "id,sample,line,lon,lat,h,role",
                                   "--gcp-pixel-convention", "corner")[0], 1e-9)
    geojson = tmp_path / "gcps.geojson"
    write_orthority_geojson(gcps, geojson, image=str(scene["image"]))
    from_oty, oty_rep = _refined(scene, tmp_path, geojson, "oty")
    assert _same_rpc(ref, from_oty, 1e-6)
    assert oty_rep["check"]["after"]["n"] == ref_rep["check"]["after"]["n"] == 10
    # Read with the wrong convention, every image coordinate is 0.5 px short: the translation follows.
    wrong, wrong_rep = _refined(scene, tmp_path, geojson, "wrong", "--gcp-pixel-convention", "corner")
    pw, pr = wrong_rep["model"]["parameters_px"], ref_rep["model"]["parameters_px"]
    shift = [np.subtract(pw[k], pr[k]) for k in sorted(pr)]
    assert len(np.ravel(shift)) == 2                        # one shift per axis
    np.testing.assert_allclose(np.ravel(shift), -0.5, atol=1e-6)
