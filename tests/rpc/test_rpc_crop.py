"""Cropped RPCs localise like GDAL (METHODS §1, issue 11).

Crops keep the scene's image offsets: ``gdal_translate -srcwin`` shifts LINE_OFF/SAMP_OFF by the window origin,
and s2p/rpcm-style crops keep offsets that lie tens of scales away from the crop's pixels (LINE_OFF 19403.5,
LINE_SCALE 512 on a 1024 x 1024 image). The Newton start used to be a cubic in image space that extrapolates far
outside [-1, 1] (NaN for every pixel); it now starts from the RPC's ground cube. Both kinds of crop are built from
the real RPCs in tests/data/rpc and compared with GDAL's RPC transformer at a 1e-8 px threshold.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from osgeo import gdal

from rasters import write_tif

from gdal_gf4cal import DEM, RPCModel
from gdal_gf4cal._gdal import gdal_exceptions

DATA_RPC = Path(__file__).parents[1] / "data" / "rpc"
GDAL_PRECISE = ["RPC_PIXEL_ERROR_THRESHOLD=1e-8", "RPC_MAX_ITERATIONS=100"]
SIZE = 1024
TOL_PX = 1e-6

#: (file, samp_off, line_off) of the far crops, LINE/SAMP_SCALE 512: offsets 10 to 38 scales from the pixels.
FAR_CROPS = [("rpc_WV2.xml", 13582.5, 19403.5), ("rpc_IKONOS.txt", 13582.5, 19403.5),
             ("rpc_PLEIADES.xml", 3500.5, 5000.5), ("rpc_SPOT6.xml", 3500.5, 5000.5),
             ("RPC_PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.XML", 3500.5, 5000.5)]
SRCWIN_CROPS = ["rpc_WV2.xml", "rpc_PLEIADES.xml", "md_dg.RPB", "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML",
                "JAX_068_001_RGB.json"]


def _far_crop(name, samp_off, line_off) -> RPCModel:
    rpc = RPCModel.from_file(DATA_RPC / name)
    return rpc.replace(samp_off=samp_off, line_off=line_off, samp_scale=512.0, line_scale=512.0, source=None)


def _srcwin_crop(name, tmp_path) -> str:
    """``gdal_translate -srcwin`` of a (sparse) full-size GeoTIFF carrying the real RPC: GDAL shifts the offsets."""
    rpc = RPCModel.from_file(DATA_RPC / name)
    w, h = rpc.image_size
    with gdal_exceptions():
        full = gdal.GetDriverByName("GTiff").Create(str(tmp_path / "full.tif"), w, h, 1, gdal.GDT_Byte,
                                                    ["SPARSE_OK=TRUE", "TILED=YES"])
        full.SetMetadata(rpc.to_gdal_metadata(), "RPC")
        x0, y0 = int(0.37 * w), int(0.61 * h)
        out = str(tmp_path / "crop.tif")
        gdal.Translate(out, full, srcWin=[x0, y0, min(SIZE, w - x0), min(SIZE, h - y0)])
        full = None
    return out


def _gdal_localize(ds, s, l, options):
    with gdal_exceptions():
        tr = gdal.Transformer(ds, None, ["METHOD=RPC"] + GDAL_PRECISE + options)
        out, ok = tr.TransformPoints(0, np.column_stack([s, l, np.zeros(s.size)]))
    out = np.asarray(out)
    ok = np.asarray(ok, dtype=bool) & np.all(np.isfinite(out), axis=1)
    return out, ok


def _px_difference(rpc, lon, lat, h, glon, glat):
    """Distance of two ground points in image pixels, through the RPC's Jacobian at ours."""
    J = rpc.project_jacobian(lon, lat, h)[:, :, :2]
    return np.hypot(*np.einsum("nij,nj->ni", J, np.column_stack([glon - lon, glat - lat])).T)


def _pixels(seed=0, n=400):
    rng = np.random.default_rng(seed)
    s, l = rng.uniform(0, SIZE, (2, n))
    return np.r_[s, 0.5, SIZE - 0.5, 0.5, SIZE - 0.5], np.r_[l, 0.5, 0.5, SIZE - 0.5, SIZE - 0.5]


def _mem(rpc):
    with gdal_exceptions():
        ds = gdal.GetDriverByName("MEM").Create("", SIZE, SIZE, 1)
        ds.SetMetadata(rpc.to_gdal_metadata(), "RPC")
    return ds


def _plane_dem(tmp_path, rpc, lon, lat) -> str:
    """A planar DEM (bilinear interpolation is exact on it) over the crop's footprint, inside the height range."""
    lo, hi = rpc.height_range
    west, east, south, north = lon.min(), lon.max(), lat.min(), lat.max()
    mx, my = 0.3 * (east - west), 0.3 * (north - south)
    nx = ny = 64
    gt = (west - mx, (east - west + 2 * mx) / nx, 0.0, north + my, 0.0, -(north - south + 2 * my) / ny)
    xc = gt[0] + gt[1] * (np.arange(nx) + 0.5)
    yc = gt[3] + gt[5] * (np.arange(ny) + 0.5)
    X, Y = np.meshgrid((xc - xc.mean()) / np.ptp(xc), (yc - yc.mean()) / np.ptp(yc))
    z = 0.5 * (lo + hi) + 0.3 * (hi - lo) * (0.6 * X - 0.4 * Y)
    return write_tif(tmp_path / "plane_dem.tif", z.astype("float64"), gt=gt, epsg=4326)


def _check_localize(rpc, ds, h):
    s, l = _pixels()
    out, ok = _gdal_localize(ds, s, l, [f"RPC_HEIGHT={h}"])
    assert ok.mean() > 0.9
    lon, lat = rpc.localize(s, l, h)
    gs, gl = rpc.project(out[ok, 0], out[ok, 1], h)
    assert np.max(np.hypot(gs - s[ok], gl - l[ok])) <= 1e-6        # GDAL's own answers are exact here
    assert np.all(np.isfinite(lon[ok])), "GDAL localises pixels that we return as NaN"
    d = _px_difference(rpc, lon[ok], lat[ok], np.full(ok.sum(), h), out[ok, 0], out[ok, 1])
    assert d.max() <= TOL_PX
    s2, l2 = rpc.project(lon[ok], lat[ok], h)
    assert np.max(np.hypot(s2 - s[ok], l2 - l[ok])) <= 1e-6
    return lon[ok], lat[ok]


def _check_localize_dem(rpc, ds, tmp_path, lon0, lat0):
    dem_path = _plane_dem(tmp_path, rpc, lon0, lat0)
    s, l = _pixels(seed=1)
    out, ok = _gdal_localize(ds, s, l, [f"RPC_DEM={dem_path}", "RPC_DEMINTERPOLATION=bilinear",
                                        "RPC_DEM_APPLY_VDATUM_SHIFT=FALSE"])
    assert ok.mean() > 0.9
    dem = DEM.from_file(dem_path, geoid=False, nodata="nan")
    lon, lat, h = rpc.localize_dem(s, l, dem, tol_m=1e-7)
    # GDAL now and then reports success for a point it left 0.1-1 px off (its DEM iteration stops on a step
    # size): compare only where GDAL's own answer re-projects onto its pixel, and require that to be nearly all.
    gs, gl = rpc.project(out[ok, 0], out[ok, 1], dem.height(out[ok, 0], out[ok, 1]))
    ok[ok] = np.hypot(gs - s[ok], gl - l[ok]) <= 1e-6
    assert ok.mean() > 0.9
    assert np.all(np.isfinite(h[ok])), "GDAL localises pixels on the DEM that we return as NaN"
    d = _px_difference(rpc, lon[ok], lat[ok], h[ok], out[ok, 0], out[ok, 1])
    assert d.max() <= TOL_PX


@pytest.mark.parametrize("name,samp_off,line_off", FAR_CROPS)
def test_far_offset_crop_localises_like_gdal(name, samp_off, line_off, tmp_path):
    crop = _far_crop(name, samp_off, line_off)
    x, y = (SIZE / 2 - samp_off) / 512.0, (SIZE / 2 - line_off) / 512.0
    assert max(abs(x), abs(y)) >= 8.0                      # the pixels lie ~9-38 scales from the offsets
    path = write_tif(tmp_path / "far.tif", np.zeros((SIZE, SIZE), "uint8"), rpc=crop)
    rpc = RPCModel.from_file(path)
    with gdal_exceptions():
        ds = gdal.Open(path)
    h = rpc.height_off + 0.25 * rpc.height_scale
    lon, lat = _check_localize(rpc, ds, h)
    _check_localize_dem(rpc, ds, tmp_path, lon, lat)


@pytest.mark.parametrize("name", SRCWIN_CROPS)
def test_gdal_translate_srcwin_crop_localises_like_gdal(name, tmp_path):
    path = _srcwin_crop(name, tmp_path)
    rpc = RPCModel.from_file(path)
    full = RPCModel.from_file(DATA_RPC / name)
    assert rpc.line_off < full.line_off and rpc.line_scale == pytest.approx(full.line_scale)
    with gdal_exceptions():
        ds = gdal.Open(path)
    h = rpc.height_off - 0.2 * rpc.height_scale
    lon, lat = _check_localize(rpc, ds, h)
    _check_localize_dem(rpc, ds, tmp_path, lon, lat)


def test_far_crop_used_to_give_nan_for_every_pixel():
    """The issue's case: offsets ~38 scales from a 1024 x 1024 crop. Every pixel localises, exactly."""
    rpc = _far_crop("rpc_WV2.xml", 13582.5, 19403.5)
    s, l = _pixels(seed=2)
    lon, lat, stats = rpc.localize(s, l, rpc.height_off, full_output=True)
    assert stats.n_failed == 0
    s2, l2 = rpc.project(lon, lat, rpc.height_off)
    assert np.max(np.hypot(s2 - s, l2 - l)) <= 1e-6


def test_points_beyond_the_extrapolation_limit_stay_nan():
    rpc = _far_crop("rpc_WV2.xml", 13582.5, 19403.5)
    lon, lat = rpc.localize(np.array([512.0, -1e9]), np.array([512.0, 1e9]), rpc.height_off)
    assert np.isfinite(lon[0]) and np.isnan(lon[1])


def test_info_of_a_far_crop_takes_the_image_size_and_warns(tmp_path):
    """``gf4cal info`` guessed 38893 x 39830 px from the scales and printed NaN corners silently."""
    from gdal_gf4cal.cli.info import format_info
    from gdal_gf4cal.describe import describe_rpc
    crop = _far_crop("rpc_WV2.xml", 13582.5, 19403.5)
    tif = write_tif(tmp_path / "far.tif", np.zeros((SIZE, SIZE), "uint8"), rpc=crop)
    crop.write_rpb(tmp_path / "side.RPB")
    write_tif(tmp_path / "side.tif", np.zeros((SIZE, 700), "uint8"))            # the sidecar's image, no tags
    for source, size in ((tif, [SIZE, SIZE]), (tmp_path / "side.RPB", [700, SIZE])):
        info = describe_rpc(source)
        assert info["size"] == size and info["size_from_image"]
        assert np.all(np.isfinite(np.array(info["corners"])))
        assert len(info["warnings"]) == 1 and "does not cover" in info["warnings"][0]
        text = format_info(info)
        assert "nan" not in text.lower() and "warning: the RPC's image domain" in text
    ul = describe_rpc(tif)["corners"][0]
    lon, lat = crop.localize(0.0, 0.0, crop.height_off)
    assert ul[:2] == pytest.approx([lon, lat], abs=1e-12)


def test_info_of_a_full_image_has_no_warning(data_dir):
    from gdal_gf4cal.describe import describe_rpc
    info = describe_rpc(data_dir / "rpc" / "PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.tif")
    assert info["size"] == [128, 128] and info["warnings"] == []
