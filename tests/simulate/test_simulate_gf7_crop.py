"""``gf4cal simulate --sensor gf7 --render`` (issue 20): the 4-band MS through the one scene writer, and ``--crop``:
a window of the full product rendered alone, keeping its place (pixel-unit geotransform without CRS, as the CNES
Ventoux crops; the product's RPC), with its truth (field on the crop's MS grid, sub-CCD edges in crop MS px)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from osgeo import gdal

from gdal_gf4cal.cli import main
from gdal_gf4cal.crop import crop_origin, image_rpc
from gdal_gf4cal.rpc import RPCModel
from gdal_gf4cal.simulate import SimulationError
from gdal_gf4cal.simulate.gf7 import (crop_misregistration, crop_sub_ccd_edges, gf7_crop, make_gf7_scene,
                                      write_gf7_scene)

#: Across the first MS sub-CCD edge (MS column 2560 = crop MS column 96), 512 x 512 pan px.
CROP = (10240 - 384, 14000, 512, 512)


@pytest.fixture(scope="module")
def full():
    return make_gf7_scene(seed=2)


@pytest.fixture(scope="module")
def cli_crop(tmp_path_factory):
    out = tmp_path_factory.mktemp("crop") / "sim"
    rc = main(["simulate", "--sensor", "gf7", "--render", "--seed", "2", "--n-gcps", "10", "--out", str(out),
               "--crop", *map(str, CROP)])
    assert rc == 0
    return out


def test_cli_render_writes_the_4_band_ms_with_band_colours(cli_crop):
    ds = gdal.Open(str(cli_crop / "ms" / "scene.tif"))
    assert (ds.RasterXSize, ds.RasterYSize, ds.RasterCount) == (128, 128, 4)
    bands = [ds.GetRasterBand(k + 1) for k in range(4)]
    assert [b.GetDescription() for b in bands] == ["blue", "green", "red", "nir"]
    assert [gdal.GetColorInterpretationName(b.GetColorInterpretation()) for b in bands] == \
        ["Blue", "Green", "Red", "Undefined"]
    arr = ds.ReadAsArray().astype(float)
    assert all(arr[k].std() > 5 for k in range(4))
    # the bands are the same ground: strongly correlated with each other and with the pan at MS resolution
    pan = gdal.Open(str(cli_crop / "pan" / "scene.tif")).ReadAsArray().astype(float)
    pan4 = pan.reshape(128, 4, 128, 4).mean(axis=(1, 3))
    assert min(np.corrcoef(arr[k].ravel(), pan4.ravel())[0, 1] for k in range(4)) > 0.7
    truth = json.loads((cli_crop / "truth.json").read_text())
    assert truth["gf7"]["bands"] == ["blue", "green", "red", "nir"] and truth["gf7"]["rendered"]


def test_crop_keeps_its_place_with_the_product_rpc(cli_crop, full):
    """Pixel-unit geotransform (x0, 1, 0, y0, 0, +1) without CRS (the sign of the Ventoux crops), and product.RPB
    (not a sidecar GDAL attaches) is the full product's RPC: the ground a crop pixel shows projects to that
    pixel plus the origin, up to the (small) misregistration of the current model."""
    for name, win in gf7_crop(CROP).windows().items():
        ds = gdal.Open(str(cli_crop / name / "scene.tif"))
        assert ds.GetGeoTransform() == (win[0], 1.0, 0.0, win[1], 0.0, 1.0)
        assert ds.GetSpatialRef() is None and not ds.GetMetadata("RPC")
        assert (ds.RasterXSize, ds.RasterYSize) == win[2:]
        rpc = RPCModel.from_file(str(cli_crop / name / "product.RPB"))
        im = full.image(name)
        s, l = np.array([0.5, win[2] - 0.5, 10.5]) + win[0], np.array([0.5, win[3] - 0.5, 20.5]) + win[1]
        lon, lat, h = im.current.localize_dem(s, l, full.dem)
        ps, pl = rpc.project(lon, lat, h)
        assert np.max(np.abs(ps - s)) < 0.01 and np.max(np.abs(pl - l)) < 0.01
        # the product's domain, not the crop's
        assert abs(rpc.samp_off - im.size[0] / 2) < 0.01 * im.size[0]
    truth = json.loads((cli_crop / "truth.json").read_text())
    assert truth["crop"]["windows"] == {k: list(v) for k, v in gf7_crop(CROP).windows().items()}


def test_crop_read_back_through_the_crop_convention(cli_crop, full):
    """gdal_gf4cal.crop reads the place back: the origin, and the product RPC shifted to the crop's pixels."""
    for name, win in gf7_crop(CROP).windows().items():
        image = cli_crop / name / "scene.tif"
        assert crop_origin(image) == win[:2]
        rpc, note = image_rpc(image, cli_crop / name / "product.RPB")
        assert note is not None and f"crop at ({win[0]}, {win[1]})" in note
        s, l = np.array([0.5, win[2] - 0.5, 7.5]), np.array([0.5, win[3] - 0.5, 30.5])
        lon, lat, h = full.image(name).current.localize_dem(s + win[0], l + win[1], full.dem)
        ps, pl = rpc.project(lon, lat, h)
        assert np.max(np.abs(ps - s)) < 0.01 and np.max(np.abs(pl - l)) < 0.01


def test_crop_truth_from_the_api_and_on_file(cli_crop, full):
    assert crop_sub_ccd_edges(full, CROP) == [96.0]
    assert crop_sub_ccd_edges(full, (4 * 2432, 0, 4 * 2816, 256)) == [128.0, 2688.0]
    assert crop_sub_ccd_edges(full, (14848, 0, 1024, 1024)) == []
    ds = gdal.Open(str(cli_crop / "ms" / "misregistration_truth.tif"))
    assert ds.GetGeoTransform() == (2464.0, 1.0, 0.0, 3500.0, 0.0, 1.0)
    grid = ds.ReadAsArray()
    j, i = np.meshgrid(np.arange(0, 128, 7), np.arange(0, 128, 5))
    j, i = j.ravel(), i.ravel()
    ds_, dl_ = crop_misregistration(full, CROP, j + 0.5, i + 0.5)
    away = np.abs(j + 0.5 - 96) > 1
    for band, exact in ((0, ds_), (1, dl_)):     # bicubic between 8 px nodes (the terrain's fine structure)
        err = np.abs(grid[band][i, j] - exact)[away]
        assert np.max(err) < 0.01 and np.sqrt(np.mean(err ** 2)) < 2e-3
    jump = np.hypot(grid[0][:, 96] - grid[0][:, 95], grid[1][:, 96] - grid[1][:, 95])
    assert jump.min() > 0.05
    before = json.loads((cli_crop / "truth.json").read_text())["gf7"]["misregistration_before"]
    assert before["ms_sub_ccd_edges_px"] == [96.0] and before["rms_sample_px"] > 0.2


def test_a_window_renders_the_product_pixels(cli_crop, tmp_path):
    """Rendering a window renders those product pixels: an overlapping crop (other tiles, other tile corners) has
    the same values where the two overlap."""
    other = (CROP[0] + 128, CROP[1] + 64, 256, 256)
    write_gf7_scene(tmp_path / "o", seed=2, crop=other, n_gcps=5, tile=96)
    for name, r in (("pan", 1), ("ms", 4)):
        a = gdal.Open(str(cli_crop / name / "scene.tif")).ReadAsArray()
        b = gdal.Open(str(tmp_path / "o" / name / "scene.tif")).ReadAsArray()
        dx, dy = 128 // r, 64 // r
        sub = a[..., dy:dy + 256 // r, dx:dx + 256 // r]
        d = np.abs(sub.astype(int) - b)          # lines of sight interpolated from 32 px nodes of each tile:
        assert d.max() <= 1 and np.mean(d > 0) < 1e-3   # at most a rounding flip of 1 DN here and there


@pytest.mark.parametrize("args, words", [
    (["--crop", "0", "0", "510", "512"], "multiples of 4"),
    (["--crop", "30000", "0", "1024", "1024"], "leaves the 30720 x 30720 pan product"),
    (["--crop", "0", "0", "32", "32"], "too small"),
    (["--crop", "0", "0", "512", "512", "--size", "512", "512"], "not both"),
])
def test_bad_crops_one_line_exit_2_nothing_written(tmp_path, capsys, args, words):
    out = tmp_path / "sim"
    rc = main(["simulate", "--sensor", "gf7", "--out", str(out), *args])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and words in err[0] and not out.exists()


def test_crop_is_refused_for_sensors_without_crop_windows(tmp_path, capsys):
    rc = main(["simulate", "--sensor", "zy3", "--out", str(tmp_path / "z"), "--crop", "0", "0", "512", "512"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--crop is not available for zy3" in err[0]
    with pytest.raises(SimulationError, match="crop truth needs the full-product scene"):
        crop_sub_ccd_edges(make_gf7_scene(seed=2, size=(256, 256)), CROP)
