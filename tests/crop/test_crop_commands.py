"""Every command pairs a crop with its product's RPC (issue 19 item 8): the real Ventoux crop geometry (500 x 500 px at
product pixel (5000, 5000), no RPC of its own) with the product's .geom, through the CLI, checked against the
product's physical location grid (tests/data/crop_ventoux/PROVENANCE.txt)."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pandas as pd
import pytest

from gdal_gf4cal import RPCModel
from gdal_gf4cal.cli import main
from ventouxcrop import BIAS, GEOM, NOTE, grid_gcps, max_error_px, write_crop


@pytest.fixture()
def crop(tmp_path):
    path = write_crop(tmp_path / "left_image.tif")
    grid_gcps().to_csv(tmp_path / "gcps.csv", index=False)
    return path


@pytest.mark.parametrize("paired", ["--rpc", "beside"])
def test_refine_a_crop_with_its_products_rpc(tmp_path, crop, paired, capsys):
    """gf4cal refine left_image.tif --rpc left_image.geom (or the .geom beside the crop): the refined RPC is the
    crop's, and with the bias removed it lands on the grid's nodes (a product RPC unshifted would be 7000 px off)."""
    args = ["refine", str(crop), "--gcps", str(tmp_path / "gcps.csv"), "--model", "translation",
            "--out", str(tmp_path / "out" / "refined.RPB"), "--report", str(tmp_path / "rep.json")]
    if paired == "--rpc":
        args += ["--rpc", str(GEOM)]
    else:
        shutil.copy(GEOM, tmp_path / "left_image.geom")
    (tmp_path / "out").mkdir()
    assert main(args) == 0
    assert f"note: {NOTE}" in capsys.readouterr().err
    assert max_error_px(RPCModel.from_file(tmp_path / "out" / "refined.RPB")) < 0.01
    rep = json.loads((tmp_path / "rep.json").read_text())
    assert any(n.startswith(NOTE) for n in rep["notes"])
    assert rep["control"]["before"]["sample"]["rms"] == pytest.approx(BIAS[0], abs=0.01)


@pytest.mark.parametrize("paired", ["--rpc", "beside"])
def test_info_prints_the_crops_footprint(tmp_path, crop, paired, capsys):
    """gf4cal info left_image.tif --rpc left_image.geom: the footprint of the crop's 500 x 500 px (its corners where
    the product's RPC puts product pixels (5000, 5000) .. (5500, 5500)), not of the product."""
    product = RPCModel.from_file(GEOM)
    args = ["info", str(crop), "--json"]
    if paired == "--rpc":
        args += ["--rpc", str(GEOM)]
    else:
        shutil.copy(GEOM, tmp_path / "left_image.geom")
    assert main(args) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["size"] == [500, 500] and info["size_from_image"] and info["format"] == "geom"
    assert info["notes"][0].startswith(NOTE)
    lon, lat, h = np.array(info["corners"]).T
    ps, pl = product.project(lon, lat, h)
    assert np.max(np.abs(ps - [5000, 5500, 5500, 5000])) < 1e-3 and np.max(np.abs(pl - [5000, 5000, 5500, 5500])) < 1e-3
    assert main(args[:2] + args[3:]) == 0
    text = capsys.readouterr().out
    assert "500 x 500 px" in text and f"note: {NOTE}" in text and "left_image.geom" in text


def test_assess_a_crop_with_its_products_rpc(tmp_path, crop):
    """assess_accuracy(crop, gcps, rpc=geom): residuals are the GCPs' bias to 1e-3 px, the origin noted."""
    from gdal_gf4cal.workflows import assess_accuracy
    rep = assess_accuracy(crop, tmp_path / "gcps.csv", rpc=GEOM, image_size=(500, 500))
    assert rep["notes"][0].startswith(NOTE) and rep["n"] == 50
    assert rep["all"]["sample"]["mean"] == pytest.approx(BIAS[0], abs=1e-3)
    assert rep["all"]["line"]["mean"] == pytest.approx(BIAS[1], abs=1e-3)
    assert rep["all"]["sample"]["std"] < 1e-3


def test_apply_calibration_to_a_crop_recalibrates_its_products_rpc(tmp_path):
    """apply-calibration crop.tif --rpc crop.tif=product.RPB (GF4-type frame, tests/gf4frame.py): the product's RPC
    (the camera's pixels) is recalibrated, then moved to the crop: the crop's RPB is the product's recalibrated RPC
    shifted by the origin, and lands where the true camera puts the crop's pixels."""
    from gf4frame import HEIGHTS, frame_model, make_cameras
    from gdal_gf4cal.rpc_fit import fit_rpc_from_model
    cur, true = make_cameras()
    product, _ = fit_rpc_from_model(frame_model(cur), height_range=HEIGHTS)
    product.write_rpb(tmp_path / "product.RPB")
    cur.to_json(tmp_path / "current.json")
    true.to_json(tmp_path / "true.json")
    origin = (4000.0, 6000.0)
    crop = write_crop(tmp_path / "crop.tif", gt=(origin[0], 1.0, 0.0, origin[1], 0.0, 1.0))
    cams = ["--current", str(tmp_path / "current.json"), "--new", str(tmp_path / "true.json")]
    assert main(["apply-calibration", str(tmp_path / "product.RPB"), *cams, "--out", str(tmp_path / "full")]) == 0
    assert main(["apply-calibration", str(crop), "--rpc", f"{crop}={tmp_path / 'product.RPB'}", *cams,
                 "--out", str(tmp_path / "crop")]) == 0
    rep = json.loads((tmp_path / "crop" / "report.json").read_text())
    assert rep["notes"] == ["crop.tif is a crop at (4000, 6000) of the product its RPC describes: RPC shifted by "
                            "the origin"]
    full, cropped = (RPCModel.from_file(tmp_path / d / f"{n}.RPB") for d, n in (("full", "product"), ("crop", "crop")))
    S, L = (a.ravel() for a in np.meshgrid(origin[0] + np.linspace(0, 500, 6), origin[1] + np.linspace(0, 500, 6)))
    h = np.full(S.size, float(np.mean(HEIGHTS)))
    lon, lat = full.localize(S, L, h)
    s, l = cropped.project(lon, lat, h)
    assert np.max(np.hypot(s - (S - origin[0]), l - (L - origin[1]))) < 1e-6
    ts, tl = frame_model(true).project(lon, lat, h)               # the true camera: the RPC fit's error only
    assert np.max(np.hypot(s - (ts - origin[0]), l - (tl - origin[1]))) < 0.05
    assert (tmp_path / "crop" / "crop.vrt").is_file()


def test_calibrate_lookangle_on_a_crop_works_in_the_cameras_pixels(tmp_path):
    """calibrate-lookangle --rpc product.RPB --image crop.tif (GF4-type frame, tests/gf4frame.py), GCPs measured in
    the crop's pixels: the camera is calibrated in the product's pixels (the camera's), the same camera as from the
    product with the same GCPs there; the crop's RPB is the product's recalibrated RPC moved to the crop."""
    from gcpsim import gcps_from_truth
    from gf4frame import HEIGHTS, W, frame_model, make_cameras
    from gdal_gf4cal.camera import LookAngleModel
    from gdal_gf4cal.rpc_fit import fit_rpc_from_model
    cur, true = make_cameras()
    product, _ = fit_rpc_from_model(frame_model(cur), height_range=HEIGHTS)
    product.write_rpb(tmp_path / "product.RPB")
    cur.to_json(tmp_path / "current.json")
    gcps, _ = gcps_from_truth(frame_model(true), 60, size=(W, W), heights=HEIGHTS, sigma_px=0.3, seed=4)
    gcps = gcps.drop(columns=["truth_sample", "truth_line"])
    origin = (4000.0, 6000.0)
    gcps.to_csv(tmp_path / "product_gcps.csv", index=False)
    gcps.assign(sample=gcps["sample"] - origin[0], line=gcps["line"] - origin[1]).to_csv(tmp_path / "crop_gcps.csv",
                                                                                         index=False)
    crop = write_crop(tmp_path / "crop.tif", gt=(origin[0], 1.0, 0.0, origin[1], 0.0, 1.0), size=(2000, 2000))
    common = ["calibrate-lookangle", "--rpc", str(tmp_path / "product.RPB"), "--camera", str(tmp_path / "current.json")]
    assert main(common + ["--gcps", str(tmp_path / "product_gcps.csv"), "--out", str(tmp_path / "full")]) == 0
    assert main(common + ["--gcps", str(tmp_path / "crop_gcps.csv"), "--image", str(crop),
                          "--out", str(tmp_path / "crop")]) == 0
    rep = json.loads((tmp_path / "crop" / "report.json").read_text())
    assert rep["notes"] == ["crop.tif is a crop at (4000, 6000) of the product its RPC describes: RPC shifted by "
                            "the origin"]
    a, b = (LookAngleModel.from_json(tmp_path / d / "camera_new.json") for d in ("full", "crop"))
    S, L = (x.ravel() for x in np.meshgrid(np.linspace(0, W, 5), np.linspace(0, W, 5)))
    assert np.max(np.abs(np.subtract(a.tan_angles(S, L), b.tan_angles(S, L)))) < 1e-12
    full = RPCModel.from_file(tmp_path / "full" / "product.RPB")
    cropped = RPCModel.from_file(tmp_path / "crop" / "crop.RPB")
    h = np.full(S.size, float(np.mean(HEIGHTS)))
    lon, lat = full.localize(S, L, h)
    s, l = cropped.project(lon, lat, h)
    assert np.max(np.hypot(s - (S - origin[0]), l - (L - origin[1]))) < 1e-6


def test_ortho_of_a_crop_with_its_products_rpc_beside_it(tmp_path, crop, srtm_path, capsys):
    """gf4cal ortho left_image.tif with left_image.geom beside it: the same ortho as with --rpc left_image.geom (the
    crop's pixels at product pixels 5000-5500; tests/crop/test_crop.py checks that ortho against the grid)."""
    common = ["--dem", str(srtm_path), "--geoid", "egm96", "--res", "2", "--crs", "EPSG:32631"]
    assert main(["ortho", str(crop), "--rpc", str(GEOM), *common, "--out", str(tmp_path / "paired.tif")]) == 0
    shutil.copy(GEOM, tmp_path / "left_image.geom")
    assert main(["ortho", str(crop), *common, "--out", str(tmp_path / "beside.tif")]) == 0
    assert f"note: {NOTE}: RPC shifted by the origin (RPC from left_image.geom beside it)" in capsys.readouterr().err
    from osgeo import gdal
    a, b = gdal.Open(str(tmp_path / "paired.tif")), gdal.Open(str(tmp_path / "beside.tif"))
    assert a.GetGeoTransform() == b.GetGeoTransform()
    assert (a.RasterXSize, a.RasterYSize) == (b.RasterXSize, b.RasterYSize)
    assert np.array_equal(a.ReadAsArray(), b.ReadAsArray())


@pytest.mark.parametrize("pair, words", [("other.tif=product.RPB", "other.tif is not among the images given"),
                                         ("crop.tif=", "give IMAGE=RPC")])
def test_rpc_pairs_naming_no_image_are_refused(tmp_path, pair, words, capsys):
    """apply-calibration --rpc with a pair that names no image given (or no RPC): one line, exit 2, nothing written."""
    from gf4frame import HEIGHTS, frame_model, make_cameras
    from gdal_gf4cal.rpc_fit import fit_rpc_from_model
    cur, _ = make_cameras()
    fit_rpc_from_model(frame_model(cur), height_range=HEIGHTS)[0].write_rpb(tmp_path / "product.RPB")
    cur.to_json(tmp_path / "cam.json")
    crop = write_crop(tmp_path / "crop.tif", gt=(4000.0, 1.0, 0.0, 6000.0, 0.0, 1.0))
    pair = pair.replace("product.RPB", str(tmp_path / "product.RPB"))
    assert main(["apply-calibration", str(crop), "--rpc", pair, "--current", str(tmp_path / "cam.json"), "--new",
                 str(tmp_path / "cam.json"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err
    assert not (tmp_path / "out").exists()
