"""Crops that state their origin in the product (issue 19 item 8): the real Ventoux Pleiades crop geometry (500 x 500 px
at product pixel (5000, 5000), pixel-unit geotransform without CRS) with the product's real RPC, checked against the
product's physical-model location grid (CNES, independent of the RPC; tests/data/crop_ventoux/PROVENANCE.txt)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from osgeo import gdal, osr
from scipy.ndimage import map_coordinates

from gdal_gf4cal import RPCModel
from gdal_gf4cal.crop import crop_origin, image_rpc
from gdal_gf4cal.dem import DEM
from gdal_gf4cal.errors import RPCFormatError
from gdal_gf4cal.workflows import orthorectify

from ventouxcrop import DATA, DIMAP, GEOM, GRID, ORIGIN, SIZE, grid_nodes, write_crop


@pytest.fixture()
def crop(tmp_path):
    return write_crop(tmp_path / "left_image.tif")


def test_crop_origin_reads_the_pixel_geotransform(tmp_path, crop):
    assert crop_origin(crop) == ORIGIN
    assert crop_origin(write_crop(tmp_path / "plain.tif", gt=None)) is None
    assert crop_origin(write_crop(tmp_path / "map.tif", gt=(600000.0, 1.0, 0.0, 5e6, 0.0, 1.0), epsg=32631)) is None
    local = write_crop(tmp_path / "local.tif")           # an engineering CRS (as CNES location grids carry)
    ds = gdal.Open(str(local), gdal.GA_Update)
    ds.SetSpatialRef(gdal.Open(str(GRID)).GetSpatialRef())
    ds = None
    assert crop_origin(local) == ORIGIN


@pytest.mark.parametrize("rpc_path", [GEOM, DIMAP], ids=["geom", "dimap"])
def test_product_rpc_shifted_to_the_crop_matches_the_location_grid(crop, rpc_path):
    rpc, note = image_rpc(crop, rpc_path)
    assert note == ("left_image.tif is a crop at (5000, 5000) of the product its RPC describes: "
                    "RPC shifted by the origin")
    col, row, alts, lon, lat = grid_nodes()
    for k, h in enumerate(alts):
        s, l = rpc.project(lon[k], lat[k], np.full(col.size, h))
        assert np.max(np.abs(s - (col - ORIGIN[0]))) < 2e-3
        assert np.max(np.abs(l - (row - ORIGIN[1]))) < 2e-3


def test_own_rpc_and_already_shifted_rpc_are_not_shifted(tmp_path):
    product = RPCModel.from_file(GEOM)
    own = write_crop(tmp_path / "own.tif", rpc=product)          # tags: the crop's by GDAL's definition
    rpc, note = image_rpc(own)
    assert note is None and rpc.samp_off == product.samp_off
    rpc, note = image_rpc(own, own)
    assert note is None and rpc.samp_off == product.samp_off
    crop = write_crop(tmp_path / "crop.tif")
    shifted, _ = image_rpc(crop, GEOM)
    (tmp_path / "out").mkdir()
    rpb = shifted.write_rpb(tmp_path / "out" / "crop_refined.RPB")
    again, note = image_rpc(crop, rpb)                             # an RPC written for the crop: not shifted twice
    assert again.samp_off == pytest.approx(shifted.samp_off) and "origin not applied" in note
    again, note = image_rpc(crop, shifted)
    assert again.samp_off == pytest.approx(shifted.samp_off) and "origin not applied" in note


def test_ambiguous_crops_are_refused(tmp_path):
    with pytest.raises(RPCFormatError, match="pixel size 2 x 2"):
        image_rpc(write_crop(tmp_path / "half.tif", gt=(5000.0, 2.0, 0.0, 5000.0, 0.0, 2.0)), GEOM)
    with pytest.raises(RPCFormatError, match="outside the RPC's image domain"):
        image_rpc(write_crop(tmp_path / "far.tif", gt=(2e6, 1.0, 0.0, 2e6, 0.0, 1.0)), GEOM)
    map_image = write_crop(tmp_path / "map.tif", gt=(600000.0, 0.5, 0.0, 5e6, 0.0, -0.5), epsg=32631)
    rpc, note = image_rpc(map_image, GEOM)
    assert note is None and rpc.samp_off == RPCModel.from_file(GEOM).samp_off


def test_ortho_of_the_crop_lands_on_its_product_pixels(tmp_path, crop, srtm_path):
    """Each grid node inside the crop (product pixels 5000-5500) is found in the ortho where the physical model puts
    it on the terrain: the ortho of the crop's coordinate bands there reads the node's crop position."""
    rep = orthorectify(crop, dem=srtm_path, geoid="egm96", rpc=GEOM, out=tmp_path / "ortho.tif", res_m=1.0,
                       crs="EPSG:32631")
    assert any("crop at (5000, 5000)" in n for n in rep["notes"])
    col, row, alts, lon, lat = grid_nodes()
    m = 2.0                                             # away from the border (bilinear reads of the ortho)
    inside = ((col > ORIGIN[0] + m) & (col < ORIGIN[0] + SIZE[0] - m) & (row > ORIGIN[1] + m)
              & (row < ORIGIN[1] + SIZE[1] - m))
    assert inside.sum() == 4
    dem = DEM.from_file(srtm_path, geoid="egm96")
    h = np.full(inside.sum(), 800.0)
    for _ in range(10):                                 # the node's line of sight meets the terrain
        x = np.array([np.interp(hh, alts, lon[:, inside][:, n]) for n, hh in enumerate(h)])
        y = np.array([np.interp(hh, alts, lat[:, inside][:, n]) for n, hh in enumerate(h)])
        h = dem.sample(x, y)
    from pyproj import Transformer
    e, n = Transformer.from_crs("EPSG:4326", "EPSG:32631", always_xy=True).transform(x, y)
    ds = gdal.Open(str(tmp_path / "ortho.tif"))
    gt = ds.GetGeoTransform()
    px, py = (e - gt[0]) / gt[1] - 0.5, (n - gt[3]) / gt[5] - 0.5
    got_s = map_coordinates(ds.GetRasterBand(1).ReadAsArray(), [py, px], order=1, cval=np.nan)
    got_l = map_coordinates(ds.GetRasterBand(2).ReadAsArray(), [py, px], order=1, cval=np.nan)
    assert np.max(np.abs(got_s - (col[inside] - ORIGIN[0]))) < 1.0
    assert np.max(np.abs(got_l - (row[inside] - ORIGIN[1]))) < 1.0


def test_intersect_of_the_stereo_crops_with_their_products_rpcs(tmp_path):
    """gf4cal intersect with IMAGE=RPC entries: tie points measured in the two crops' own pixels (left: where the
    physical grid puts each ground point; right: the right product's RPC minus the right crop's origin (4915, 5162))
    intersect back on the grid's ground points."""
    import pandas as pd
    from gdal_gf4cal.cli import main
    left = write_crop(tmp_path / "left_image.tif")
    right = write_crop(tmp_path / "right_image.tif", gt=(4915.0, 1.0, 0.0, 5162.0, 0.0, 1.0), size=(498, 495))
    right_geom = DATA / "crop_ventoux" / "right_image.geom"
    col, row, alts, lon, lat = grid_nodes()
    inside = (col > ORIGIN[0]) & (col < ORIGIN[0] + SIZE[0]) & (row > ORIGIN[1]) & (row < ORIGIN[1] + SIZE[1])
    k = list(alts).index(485.0)
    x, y, h = lon[k, inside], lat[k, inside], np.full(inside.sum(), 485.0)
    s2, l2 = RPCModel.from_file(right_geom).project(x, y, h)
    pts = pd.DataFrame({"id": [f"n{i}" for i in range(x.size)], "sample_1": col[inside] - ORIGIN[0],
                        "line_1": row[inside] - ORIGIN[1], "sample_2": s2 - 4915.0, "line_2": l2 - 5162.0,
                        "lon": x, "lat": y, "h": h})
    pts.to_csv(tmp_path / "ties.csv", index=False)
    assert main(["intersect", "--rpc", f"{left}={GEOM}", f"{right}={right_geom}", "--points",
                 str(tmp_path / "ties.csv"), "--out", str(tmp_path / "pts.csv"), "--report",
                 str(tmp_path / "rep.json")]) == 0
    out = pd.read_csv(tmp_path / "pts.csv")
    assert np.max(np.abs(out["err_h_m"])) < 0.05
    assert np.max(np.hypot(out["err_east_m"], out["err_north_m"])) < 0.05
    import json
    notes = json.loads((tmp_path / "rep.json").read_text())["notes"]
    assert any("right_image.tif is a crop at (4915, 5162)" in n for n in notes)


def test_rpc_file_named_like_the_image_beside_it_is_the_products(tmp_path):
    """Shareloc's layout: left_image.tif (origin (5000, 5000), no RPC) + left_image.geom (the product's RPC) in one
    folder: image_rpc(image) takes the .geom, shifts it by the origin and says so; the shifted RPC matches the
    physical grid. Without a sidecar, the image's own error stands."""
    import shutil
    crop = write_crop(tmp_path / "left_image.tif")
    with pytest.raises(RPCFormatError, match="no RPC"):
        image_rpc(crop)
    shutil.copy(GEOM, tmp_path / "left_image.geom")
    rpc, note = image_rpc(crop)
    assert note == ("left_image.tif is a crop at (5000, 5000) of the product its RPC describes: RPC shifted by the "
                    "origin (RPC from left_image.geom beside it)")
    col, row, alts, lon, lat = grid_nodes()
    s, l = rpc.project(lon[1], lat[1], np.full(col.size, alts[1]))
    assert np.max(np.abs(s - (col - ORIGIN[0]))) < 2e-3 and np.max(np.abs(l - (row - ORIGIN[1]))) < 2e-3
    plain = write_crop(tmp_path / "plain.tif", gt=None)                  # no origin: the sidecar as it is
    shutil.copy(DIMAP, tmp_path / "plain.XML")
    rpc, note = image_rpc(plain)
    assert note == "plain.tif: RPC from plain.XML beside it" and rpc.samp_off == RPCModel.from_file(DIMAP).samp_off
    own = write_crop(tmp_path / "own.tif", rpc=RPCModel.from_file(GEOM).with_image_affine(-1.0, 0.0))
    shutil.copy(GEOM, tmp_path / "own.geom")                              # the image's own RPC wins
    rpc, note = image_rpc(own)
    assert note is None and rpc.samp_off == pytest.approx(RPCModel.from_file(GEOM).samp_off - 1.0)
