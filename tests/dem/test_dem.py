"""DEM sampling: bilinear like GDAL, any CRS, windowed reads, geoid, nodata policies (METHODS §2)."""
from __future__ import annotations

import numpy as np
import pytest
from osgeo import gdal, osr

from rasters import write_tif

from gdal_gf4cal import DEM, DEMError

gdal.UseExceptions()


def _write_dem(path, array, gt, epsg=4326, nodata=None):
    return write_tif(path, np.asarray(array, dtype=np.float32), gt=gt, epsg=epsg, nodata=nodata)


def test_constant_dem():
    dem = DEM.constant(123.5)
    assert dem.height(10.0, 20.0) == 123.5
    np.testing.assert_array_equal(dem.height(np.zeros(3), np.zeros(3)), 123.5)


def test_bilinear_is_exact_on_a_plane(tmp_path):
    y, x = np.mgrid[0:50, 0:60]
    plane = 100 + 2.0 * x - 3.0 * y
    path = _write_dem(tmp_path / "plane.tif", plane.astype(np.float32), (10.0, 0.01, 0, 45.0, 0, -0.01))
    dem = DEM.from_file(path)
    rng = np.random.default_rng(0)
    px, py = rng.uniform(0.5, 59.5, 500), rng.uniform(0.5, 49.5, 500)   # between outer pixel centres
    lon, lat = 10.0 + px * 0.01, 45.0 - py * 0.01
    np.testing.assert_allclose(dem.height(lon, lat), 100 + 2.0 * (px - 0.5) - 3.0 * (py - 0.5), atol=1e-4)


def test_matches_gdal_bilinear_on_real_srtm(srtm_path):
    """Our windowed bilinear sampling equals GDAL's (gdal.Warp bilinear onto the exact points)."""
    dem = DEM.from_file(srtm_path, nodata="nan")   # the tile has real SRTM voids
    ds = gdal.Open(str(srtm_path))
    gt = ds.GetGeoTransform()
    arr = ds.ReadAsArray().astype(float)
    arr[arr == ds.GetRasterBand(1).GetNoDataValue()] = np.nan
    rng = np.random.default_rng(1)
    px, py = rng.uniform(1, 1199, 2000), rng.uniform(1, 1199, 2000)
    lon, lat = gt[0] + px * gt[1], gt[3] + py * gt[5]
    x, y = px - 0.5, py - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    ref = (arr[y0, x0] * (1 - fx) + arr[y0, x0 + 1] * fx) * (1 - fy) + (arr[y0 + 1, x0] * (1 - fx)
                                                                         + arr[y0 + 1, x0 + 1] * fx) * fy
    ours = dem.height(lon, lat)
    np.testing.assert_array_equal(np.isnan(ours), np.isnan(ref))   # voids propagate, never interpolated over
    assert np.isfinite(ref).mean() > 0.95
    np.testing.assert_allclose(ours[np.isfinite(ref)], ref[np.isfinite(ref)], atol=1e-6)


def test_projected_crs_dem_agrees_with_geographic(srtm_path, data_dir):
    """The UTM copy of the tile gives the same terrain (to the resampling's precision) through pyproj."""
    geo = DEM.from_file(srtm_path, nodata="nan")
    utm = DEM.from_file(data_dir / "dem" / "N44E005_UTM.tif", nodata="nan")
    rng = np.random.default_rng(2)
    lon, lat = rng.uniform(5.1, 5.9, 300), rng.uniform(44.1, 44.9, 300)
    d = utm.height(lon, lat) - geo.height(lon, lat)
    assert np.isfinite(d).mean() > 0.9
    assert np.nanmedian(np.abs(d)) < 15.0      # 90 m resampled relief vs 3" original


def test_geoid_egm96_adds_the_undulation(srtm_path):
    """Shareloc's reference: SRTM + EGM96 at the Ventoux point is 503.51202 m ellipsoidal."""
    lon, lat = 5.193406151946084, 44.20805807814395
    ortho = DEM.from_file(srtm_path).height(lon, lat)
    ellipsoidal = DEM.from_file(srtm_path, geoid="egm96").height(lon, lat)
    assert ellipsoidal == pytest.approx(503.51202179, abs=1e-3)
    assert 45 < ellipsoidal - ortho < 55    # EGM96 undulation in Provence is ~50 m


def test_nodata_policies(tmp_path):
    arr = np.full((20, 20), 50.0, dtype=np.float32)
    arr[5:10, 5:10] = -9999
    path = _write_dem(tmp_path / "holes.tif", arr, (0.0, 0.1, 0, 2.0, 0, -0.1), nodata=-9999)
    inside_hole, outside = (0.75, 1.25), (5.0, 5.0)
    with pytest.raises(DEMError, match="outside the DEM or on no-data"):
        DEM.from_file(path).height(*inside_hole)
    with pytest.raises(DEMError):
        DEM.from_file(path).height(*outside)
    assert np.isnan(DEM.from_file(path, nodata="nan").height(*inside_hole))
    assert DEM.from_file(path, nodata=12.0).height(*outside) == 12.0
    assert DEM.from_file(path).height(0.05 + 1.5, 1.5) == pytest.approx(50.0)


def test_windowed_and_whole_raster_sampling_agree(tmp_path):
    rng = np.random.default_rng(5)
    arr = rng.normal(500, 100, (1500, 1300)).astype(np.float32)
    arr[700:720, 600:640] = -32768
    path = _write_dem(tmp_path / "r.tif", arr, (10.0, 0.001, 0, 46.0, 0, -0.001), nodata=-32768)
    whole = DEM.from_file(path, nodata="nan")
    tiled = DEM.from_file(path, nodata="nan")
    tiled._whole_limit = 0
    lon, lat = rng.uniform(9.999, 11.301, 20000), rng.uniform(44.499, 46.001, 20000)
    a, b = whole.height(lon, lat), tiled.height(lon, lat)
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    assert np.isnan(a).any() and np.isfinite(a).mean() > 0.95
    np.testing.assert_allclose(a[np.isfinite(a)], b[np.isfinite(b)], atol=1e-9)


def test_windowed_reads_touch_only_needed_tiles(tmp_path):
    arr = np.arange(3000 * 3000, dtype=np.float32).reshape(3000, 3000)
    path = _write_dem(tmp_path / "big.tif", arr, (0.0, 0.001, 0, 3.0, 0, -0.001))
    dem = DEM.from_file(path)
    dem._whole_limit = 1_000_000          # treat it as a large DEM (the real limit is 16 Mpx)
    dem.height(np.array([0.1, 0.2]), np.array([2.9, 2.8]))
    assert len(dem._cache) == 1 and dem._whole is None   # one 1024 px tile, not the raster


def test_bad_inputs(tmp_path):
    with pytest.raises(DEMError, match="not found"):
        DEM.from_file(tmp_path / "missing.tif")
    ds = gdal.GetDriverByName("GTiff").Create(str(tmp_path / "nogeo.tif"), 4, 4, 1)
    ds = None
    with pytest.raises(DEMError, match="geotransform|CRS"):
        DEM.from_file(tmp_path / "nogeo.tif")
    with pytest.raises(DEMError, match="geoid grid"):
        DEM.from_file(_write_dem(tmp_path / "d.tif", np.zeros((4, 4), np.float32), (0, 1, 0, 4, 0, -1)),
                      geoid=str(tmp_path / "nogrid.gtx"))


def test_geographic_dem_longitudes_wrap_across_the_antimeridian(tmp_path):
    """A -180..180 DEM answers for lon 180.3 and a 0..360 one for lon -179.5 (same place, one turn apart)."""
    y, x = np.mgrid[0:180, 0:360]
    world = _write_dem(tmp_path / "world.tif", (10.0 * x + y).astype(np.float32), (-180.0, 1.0, 0, 90.0, 0, -1.0))
    dem = DEM.from_file(world)
    np.testing.assert_allclose(dem.height([180.3, 540.3, -539.7], [0.2, 0.2, 0.2]), dem.height(-179.7, 0.2))
    across = _write_dem(tmp_path / "across.tif", np.full((20, 20), 50.0, np.float32), (179.0, 0.1, 0, 1.0, 0, -0.1))
    assert DEM.from_file(across).height(-179.5, 0.5) == DEM.from_file(across).height(180.5, 0.5) == 50.0
    with pytest.raises(DEMError, match="outside the DEM"):
        DEM.from_file(across).height(-178.5, 0.5)           # 181.5: still east of the raster


def test_all_nodata_dem_is_a_clear_error(tmp_path):
    path = _write_dem(tmp_path / "void.tif", np.full((8, 8), -9999, np.float32), (5.0, 0.1, 0, 45.0, 0, -0.1),
                      nodata=-9999)
    with pytest.raises(DEMError, match="no valid height"):
        DEM.from_file(path, nodata="nan").height_range()


def test_geoid_declared_by_a_compound_crs_is_applied(tmp_path, srtm_path):
    """A GeoTIFF tagged EPSG:4326+5773 (EGM96 height) holds orthometric heights: they are converted, as GDAL's
    RPC transformer does by default, never used as ellipsoidal by mistake; geoid=False opts out."""
    src = gdal.Open(str(srtm_path))
    srs = osr.SpatialReference()
    srs.SetFromUserInput("EPSG:4326+5773")
    path = str(tmp_path / "srtm_egm96.tif")
    gdal.Translate(path, src, outputSRS=srs.ExportToWkt())
    lon, lat = 5.193406151946084, 44.20805807814395
    declared = DEM.from_file(path)
    assert declared.geoid_applied == "egm96"
    assert declared.height(lon, lat) == pytest.approx(DEM.from_file(srtm_path, geoid="egm96").height(lon, lat),
                                                      abs=1e-6)
    assert DEM.from_file(path, geoid=False).height(lon, lat) == pytest.approx(
        DEM.from_file(srtm_path).height(lon, lat), abs=1e-6)
    assert DEM.from_file(path, geoid="none").geoid_applied is None     # the CLI's spelling of geoid=False
    assert DEM.from_file(srtm_path).geoid_applied is None     # a plain WGS 84 .hgt says nothing: no conversion


def test_unknown_vertical_datum_is_an_error(tmp_path, srtm_path):
    srs = osr.SpatialReference()
    srs.SetFromUserInput("EPSG:4326+5703")            # NAVD88 height: no grid we know of
    path = str(tmp_path / "navd88.tif")
    gdal.Translate(path, gdal.Open(str(srtm_path)), outputSRS=srs.ExportToWkt())
    with pytest.raises(DEMError, match="vertical datum"):
        DEM.from_file(path)
    assert np.isfinite(DEM.from_file(path, geoid=False, nodata="nan").height(5.5, 44.5))


def test_raster_space_access_agrees_with_sample(data_dir, tmp_path):
    """to_pixel + sample_pixel + geoid_undulation (the line-of-sight march's sampler) give DEM.sample; the CRS
    polynomial of a small projected DEM reproduces PROJ."""
    import pyproj
    dem = DEM.from_file(data_dir / "dem" / "N44E005_UTM.tif", geoid="egm96", nodata="nan")
    rng = np.random.default_rng(5)
    lon, lat = rng.uniform(5.1, 5.6, 500), rng.uniform(44.05, 44.4, 500)
    px, py = dem.to_pixel(lon, lat)
    h = dem.sample_pixel(px, py) + dem.geoid_undulation(lon, lat)
    np.testing.assert_allclose(h, dem.sample(lon, lat), atol=1e-6)
    # A 200 m UTM DSM: its CRS transform is a fitted cubic, within 1e-6 pixel of PROJ over its footprint.
    gt = (682857.0, 0.5, 0.0, 4889588.0, 0.0, -0.5)
    small = DEM.from_file(write_tif(tmp_path / "small.tif", np.zeros((400, 400), np.float32), gt=gt, epsg=32631))
    to_utm = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:32631", always_xy=True)
    lo, la = to_utm.transform(gt[0] + rng.uniform(0, 200, 300), gt[3] - rng.uniform(0, 200, 300),
                              direction="INVERSE")
    xp, yp = small.to_pixel(lo, la)
    xe, ye = to_utm.transform(lo, la)
    np.testing.assert_allclose(xp, (xe - gt[0]) / 0.5 - 0.5, atol=1e-6)
    np.testing.assert_allclose(yp, (ye - gt[3]) / -0.5 - 0.5, atol=1e-6)


def test_local_max_and_slopes(tmp_path):
    """Windowed maxima of the heights (no-data ignored, -inf where a window holds none) and of the slopes."""
    arr = np.zeros((64, 64), np.float32)
    arr[10, 20] = 50.0                    # a 50 m spike: slopes 50 m / 10 m around it
    arr[40:50, 40:50] = -9999.0           # a hole
    path = write_tif(tmp_path / "spike.tif", arr, gt=(500000.0, 10.0, 0, 4900000.0, 0, -10.0), epsg=32631,
                     nodata=-9999.0)
    dem = DEM.from_file(path, nodata="nan")
    z4 = dem.local_max(np.array([20.0, 20.0, 28.0, 45.0]), np.array([10.0, 13.6, 10.0, 45.0]), 4)
    np.testing.assert_array_equal(z4, [50.0, 50.0, 0.0, -np.inf])     # radius 4: the spike 8 px away is not seen
    z1, z8 = dem.local_max(np.array([45.0]), np.array([45.0]), (1, 8))
    assert z1[0] == -np.inf and z8[0] == 0.0
    np.testing.assert_allclose(dem.local_max_slope(np.array([20.0, 40.0]), np.array([10.0, 40.0]), 2), [5.0, 0.0])
    assert dem.max_step_px() == (50.0, 50.0) and dem.pixel_size_m() == (10.0, 10.0)


@pytest.mark.parametrize("tiled", [False, True])
def test_newton_sampler_with_a_geoid_is_sample_and_its_slopes(srtm_path, data_dir, tiled):
    """SRTM + EGM96: the DEM intersection's Newton sampler (stored surface + the geoid between its grid's nodes, no
    PROJ call) gives sample()'s heights to 1e-6 m and the slopes of its own surface; none for a projected DEM."""
    dem = DEM.from_file(srtm_path, geoid="egm96", nodata=-5.0)
    if tiled:
        dem._whole_limit = 0          # the windowed tile reads of a large DEM, on this small tile
        dem._tile = 256
    assert not dem.gradient_is_analytic
    sampler = dem.newton_sampler()
    rng = np.random.default_rng(7)
    lon = np.r_[rng.uniform(5.02, 5.98, 2000), 7.5]          # the last one off the DEM: the numeric policy
    lat = np.r_[rng.uniform(44.02, 44.98, 2000), 44.5]
    z, gx, gy = sampler(lon, lat)
    ref = dem.sample(lon, lat)
    assert ref[-1] == z[-1] == -5.0 and gx[-1] == gy[-1] == 0.0
    np.testing.assert_array_equal(dem.newton_sampler(gradient=False)(lon, lat), z)    # heights alone: same bits
    n = dem.geoid_undulation(lon, lat)
    assert np.ptp(n[:-1]) > 0.5                               # the undulation varies over the tile
    assert np.max(np.abs(dem.geoid_undulation(lon, lat, exact=False) - n)) <= 1e-6     # the lattice's (no PROJ)
    assert np.nanmax(np.abs(z - ref)) <= 1e-6 and np.isfinite(z).all()
    e = 1e-6                                                  # central differences within a DEM cell
    fx = (sampler(lon + e, lat)[0] - sampler(lon - e, lat)[0]) / (2 * e)
    fy = (sampler(lon, lat + e)[0] - sampler(lon, lat - e)[0]) / (2 * e)
    fx_px, fy_px = ((lon - 5.0) * 1200.0) % 1.0, ((45.0 - lat) * 1200.0) % 1.0
    interior = (np.minimum(fx_px, 1 - fx_px) > 0.01) & (np.minimum(fy_px, 1 - fy_px) > 0.01) & (ref != -5.0)
    assert interior.sum() > 1500
    np.testing.assert_allclose(gx[interior], fx[interior], rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(gy[interior], fy[interior], rtol=1e-4, atol=1e-3)
    assert DEM.from_file(data_dir / "dem" / "N44E005_UTM.tif", geoid="egm96").newton_sampler() is None


@pytest.mark.parametrize("tiled", [False, True])
def test_newton_sampler_small_calls_give_the_bits_of_a_large_one(srtm_path, tiled):
    """SRTM + EGM96: a small call samples the raster and the geoid's lattice in one bilinear pass, a large one
    (over 1024 points) one at a time (windowed tiles for a large raster): the same operations on each point, the same
    bits, points off the DEM and NaN included."""
    dem = DEM.from_file(srtm_path, geoid="egm96", nodata="nan")
    if tiled:
        dem._whole_limit = 0
        dem._tile = 256
    rng = np.random.default_rng(11)
    lon, lat = rng.uniform(4.98, 6.02, 3000), rng.uniform(43.98, 45.02, 3000)    # a few just off the tile
    lon[5], lat[7] = np.nan, np.nan
    for gradient in (True, False):
        sampler = dem.newton_sampler(gradient=gradient)
        large = np.array(sampler(lon, lat), dtype=float)
        heights = np.atleast_2d(large)[0]
        assert np.isnan(heights[[5, 7]]).all() and 2 < np.isnan(heights).sum() < 300
        for a, b in ((0, 1), (1, 5), (9, 25), (100, 356), (356, 1380)):
            np.testing.assert_array_equal(np.array(sampler(lon[a:b], lat[a:b]), dtype=float), large[..., a:b])


@pytest.mark.parametrize("geoid", [None, "egm96"])
def test_a_small_call_without_outside_points_gives_the_masked_paths_bits(srtm_path, geoid):
    """A call whose points all lie inside the DEM (and inside [west, west + 360)) skips the outside mask and the
    longitude wrap (a small call's fixed cost): its values are bit for bit those of the same points in a call that
    takes the masked paths (one point off the DEM, one NaN, one a turn west), for every sampler."""
    dem = DEM.from_file(srtm_path, geoid=geoid, nodata="nan")
    rng = np.random.default_rng(3)
    lon, lat = rng.uniform(5.0, 6.0, 50), rng.uniform(44.0, 45.0, 50)
    lon[:2], lat[:2] = (5.0 + 0.5 / 1200, 6.0 - 0.5 / 1200), (45.0 - 0.5 / 1200, 44.0 + 0.5 / 1200)  # edge cells
    lon_m, lat_m = np.r_[lon, 7.5, np.nan, 5.5 - 360.0], np.r_[lat, 44.5, 44.5, 44.5]
    for fn in (dem.sample, dem.sample_with_gradient, dem.newton_sampler(), dem.newton_sampler(gradient=False)):
        small, masked = np.array(fn(lon, lat)), np.array(fn(lon_m, lat_m))
        assert np.isfinite(small).all() and np.isnan(np.atleast_2d(masked)[0, 50:52]).all()   # heights NaN
        np.testing.assert_array_equal(small, masked[..., :50])
        assert np.isfinite(masked[..., 52]).all()            # found a turn east (wrapped, its own rounding)
