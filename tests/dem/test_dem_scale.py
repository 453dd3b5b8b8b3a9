"""DEM band scale/offset are applied, implausible DEM heights are warned about (METHODS §2, issue 11)."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from osgeo import gdal

from rasters import write_tif

from gdal_gf4cal import DEM, RPCModel
from gdal_gf4cal._gdal import gdal_exceptions

GT = (5.0, 0.01, 0.0, 45.0, 0.0, -0.01)   # 1 x 1 degree, 100 x 100 px


def _metres():
    y, x = np.mgrid[0:100, 0:100]
    return 300.0 + 8.0 * x + 5.0 * y + 40.0 * np.sin(x / 7.0)       # 300..1600 m


def _scaled_tif(path, scale, offset):
    z = np.round((_metres() - offset) / scale).astype("int16") if scale < 1 else None
    stored = z if z is not None else ((_metres() - offset) / scale).astype("float32")
    write_tif(path, stored.astype("float32"), gt=GT, epsg=4326)
    with gdal_exceptions():
        ds = gdal.Open(str(path), gdal.GA_Update)
        band = ds.GetRasterBand(1)
        band.SetScale(scale)
        band.SetOffset(offset)
        ds = None
    return str(path)


@pytest.mark.parametrize("scale,offset", [(0.1, 0.0), (0.1, -50.0), (2.0, 100.0)])
def test_band_scale_and_offset_give_metres(tmp_path, scale, offset):
    ref = DEM.from_file(write_tif(tmp_path / "m.tif", _metres().astype("float32"), gt=GT, epsg=4326),
                        geoid=False)
    dem = DEM.from_file(_scaled_tif(tmp_path / "dm.tif", scale, offset), geoid=False)
    rng = np.random.default_rng(3)
    lon, lat = rng.uniform(5.02, 5.97, 500), rng.uniform(44.03, 44.97, 500)
    # The decimetre DEM rounds to 0.1 m: heights agree with the metre DEM within that quantisation.
    assert np.max(np.abs(dem.height(lon, lat) - ref.height(lon, lat))) <= 0.5 * scale + 1e-3
    lo, hi = dem.height_range()
    assert lo == pytest.approx(ref.height_range()[0], abs=scale) and hi == pytest.approx(ref.height_range()[1],
                                                                                          abs=scale)
    z, gx, gy = dem.sample_with_gradient(lon, lat)
    z_ref, gx_ref, gy_ref = ref.sample_with_gradient(lon, lat)
    # Slopes (m per degree) of the bilinear surface: two quantised values over a 0.01 degree cell.
    assert np.max(np.abs(gx - gx_ref)) <= scale / 0.01 + 1e-6 and np.max(np.abs(gy - gy_ref)) <= scale / 0.01 + 1e-6
    assert np.max(np.abs(z - z_ref)) <= 0.5 * scale + 1e-3


def test_localize_dem_on_a_decimetre_dem_warns_without_scale(tmp_path, caplog):
    """Without applying the scale the heights were ten times too large; now they are metres. A DEM that really
    holds implausible heights for the RPC is warned about."""
    rpc = RPCModel.from_file(Path(__file__).parents[1] / "data" / "rpc" /
                             "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML")
    lon0, lat0 = rpc.long_off, rpc.lat_off
    gt = (lon0 - 0.5, 0.01, 0.0, lat0 + 0.5, 0.0, -0.01)
    metres = np.full((100, 100), 800.0)
    dm = write_tif(tmp_path / "dm.tif", (metres * 10).astype("float32"), gt=gt, epsg=4326)
    with gdal_exceptions():
        ds = gdal.Open(dm, gdal.GA_Update)
        ds.GetRasterBand(1).SetScale(0.1)
        ds = None
    w, h = rpc.image_size
    s, l = np.array([0.3 * w, 0.6 * w]), np.array([0.4 * h, 0.7 * h])
    with caplog.at_level(logging.WARNING, logger="gdal_gf4cal.localization"):
        _, _, hh = rpc.localize_dem(s, l, DEM.from_file(dm, geoid=False))
    assert np.allclose(hh, 800.0, atol=1e-3)
    assert not [r for r in caplog.records if "height range" in r.getMessage()]
    raw = write_tif(tmp_path / "raw.tif", (metres * 10).astype("float32"), gt=gt, epsg=4326)   # 8000 m
    with caplog.at_level(logging.WARNING, logger="gdal_gf4cal.localization"):
        _, _, hh = rpc.localize_dem(s, l, DEM.from_file(raw, geoid=False))
    assert [r for r in caplog.records if "far outside the RPC's height range" in r.getMessage()]
