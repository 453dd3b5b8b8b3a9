"""The one sensor-model contract (issue 10, Build items 1-3; METHODS §1, §2).

Every sensor model of the engine (a real RPC, CompensatedRPC, RecalibratedSensor, the simulator's frame and
push-broom models) is run through ``project``, ``project_jacobian``, ``localize`` and ``localize_dem`` with a
scalar, a 1-D and a 2-D input (the ``scalar_and_array`` fixture of conftest.py): shapes are kept, scalars give
Python floats, round trips close, ``full_output`` gives one :class:`LocalizationStats`. Plus: no attribute
forwarding in composed models, and the public DEM API (``DEM.sample``, ``DEM.sample_with_gradient``,
``DEM.from_user_input``).
"""
from __future__ import annotations

import numpy as np
import pytest

from gdal_gf4cal.compensation import apply_compensation
from gdal_gf4cal.dem import DEM
from gdal_gf4cal.errors import DEMError, Gf4calError
from gdal_gf4cal.rpc_io import write_rpc_vrt
from gdal_gf4cal.sensor import LocalizationStats, SensorModel


def _image_points(size, n=6, seed=11):
    """n image points well inside the image (GDAL convention) and heights, fixed seed."""
    rng = np.random.default_rng(seed)
    W, H = size
    return rng.uniform(0.1 * W, 0.9 * W, n), rng.uniform(0.1 * H, 0.9 * H, n)


def _heights(model, n=6, seed=12):
    lo, hi = model.height_range
    return np.random.default_rng(seed).uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), n)


def _check_kind(value, like):
    """A Python float for a scalar input, else an ndarray of the input's shape."""
    if np.ndim(like) == 0:
        assert type(value) is float, type(value)
    else:
        assert isinstance(value, np.ndarray) and value.shape == np.shape(like)


def test_every_model_is_a_sensor_model(sensor_model):
    name, model, _, _ = sensor_model
    assert isinstance(model, SensorModel), name
    lo, hi = model.height_range
    assert lo <= hi


def test_localize_then_project_round_trip(sensor_model, scalar_and_array):
    name, model, _, size = sensor_model
    s0, l0 = _image_points(size)
    s, l, h = scalar_and_array(s0), scalar_and_array(l0), scalar_and_array(_heights(model))
    lon, lat = model.localize(s, l, h)
    _check_kind(lon, s)
    _check_kind(lat, s)
    s2, l2 = model.project(lon, lat, h)
    _check_kind(s2, s)
    _check_kind(l2, s)
    assert np.max(np.hypot(np.subtract(s2, s), np.subtract(l2, l))) <= 1e-6, name


def test_localize_full_output_is_localization_stats(sensor_model, scalar_and_array):
    name, model, _, size = sensor_model
    s0, l0 = _image_points(size)
    s, l, h = scalar_and_array(s0), scalar_and_array(l0), scalar_and_array(_heights(model))
    lon, lat, stats = model.localize(s, l, h, full_output=True)
    _check_kind(lon, s)
    assert isinstance(stats, LocalizationStats)
    assert stats.n_points == np.size(s) and stats.n_failed == 0 and stats.n_converged == np.size(s)
    assert stats.max_residual_px <= 1e-6, name


def test_pixel_conventions_differ_by_half_a_pixel(sensor_model, scalar_and_array):
    name, model, _, size = sensor_model
    s0, l0 = _image_points(size)
    s, l, h = scalar_and_array(s0), scalar_and_array(l0), scalar_and_array(_heights(model))
    lon, lat = model.localize(s, l, h)
    sr, lr = model.project(lon, lat, h, pixel_convention="rpc")
    _check_kind(sr, s)
    np.testing.assert_allclose(sr, np.subtract(s, 0.5), atol=1e-6)
    np.testing.assert_allclose(lr, np.subtract(l, 0.5), atol=1e-6)
    lon_r, lat_r = model.localize(np.subtract(s, 0.5), np.subtract(l, 0.5), h, pixel_convention="rpc")
    np.testing.assert_allclose(lon_r, lon, atol=1e-11)
    np.testing.assert_allclose(lat_r, lat, atol=1e-11)
    with pytest.raises(ValueError):
        model.project(lon, lat, h, pixel_convention="centre")


def test_project_jacobian_shape_and_values(sensor_model, scalar_and_array):
    name, model, _, size = sensor_model
    s0, l0 = _image_points(size)
    h0 = _heights(model)
    lon0, lat0 = model.localize(s0, l0, h0)
    lon, lat, h = scalar_and_array(lon0), scalar_and_array(lat0), scalar_and_array(h0)
    J = model.project_jacobian(lon, lat, h)
    assert isinstance(J, np.ndarray) and J.shape == np.shape(lon) + (2, 3)
    np.testing.assert_array_equal(model.project_jacobian(lon, lat, h, pixel_convention="rpc"), J)
    # Against central differences of project (steps ~1 m on the ground and 1 m in height).
    steps = (1e-5, 1e-5, 1.0)
    for k, step in enumerate(steps):
        d = [0.0, 0.0, 0.0]
        d[k] = step
        sp, lp = model.project(np.add(lon, d[0]), np.add(lat, d[1]), np.add(h, d[2]))
        sm, lm = model.project(np.subtract(lon, d[0]), np.subtract(lat, d[1]), np.subtract(h, d[2]))
        scale = np.max(np.abs(J[..., :, k])) + 1e-12
        np.testing.assert_allclose(J[..., 0, k], np.subtract(sp, sm) / (2 * step), rtol=1e-4, atol=1e-4 * scale)
        np.testing.assert_allclose(J[..., 1, k], np.subtract(lp, lm) / (2 * step), rtol=1e-4, atol=1e-4 * scale)


def test_localize_dem_lands_on_the_dem(sensor_model, scalar_and_array):
    name, model, dem, size = sensor_model
    s0, l0 = _image_points(size)
    s, l = scalar_and_array(s0), scalar_and_array(l0)
    lon, lat, h, stats = model.localize_dem(s, l, dem, full_output=True)
    for v in (lon, lat, h):
        _check_kind(v, s)
    assert isinstance(stats, LocalizationStats)
    assert stats.n_points == np.size(s) and stats.n_failed == 0, name
    assert stats.max_residual_px <= 1e-6 and stats.max_residual_m <= 1e-3, (name, stats)
    s2, l2 = model.project(lon, lat, h)
    assert np.max(np.hypot(np.subtract(s2, s), np.subtract(l2, l))) <= 1e-6
    assert np.max(np.abs(np.subtract(dem.sample(lon, lat), h))) <= 1e-3
    # The same without full_output, and with a constant height (a number is a DEM).
    lon_b, lat_b, h_b = model.localize_dem(s, l, dem)
    np.testing.assert_array_equal(h_b, h)
    hc = float(np.mean(model.height_range))
    lon_c, lat_c, h_c = model.localize_dem(s, l, hc)
    _check_kind(h_c, s)
    np.testing.assert_array_equal(h_c, np.full(np.shape(s), hc) if np.ndim(s) else hc)
    lon_l, lat_l = model.localize(s, l, hc)
    np.testing.assert_allclose(lon_c, lon_l, atol=1e-12)


# ---------------------------------------------------------------------------------------------- no forwarding
def test_composed_models_have_no_writers(sensor_model, tmp_path):
    name, model, _, _ = sensor_model
    if name not in ("compensated_rpc", "recalibrated_sensor"):
        pytest.skip("only composed models")
    for attr in ("write_rpb", "write_rpc_txt", "to_gdal_metadata", "samp_off", "line_scale", "height_off",
                 "image_size", "replace", "with_image_affine"):
        assert not hasattr(model, attr), attr
    assert model.rpc is not None and tuple(model.height_range) == tuple(model.rpc.height_range)
    image = tmp_path / "image.tif"
    from rasters import write_tif
    write_tif(image, np.zeros((8, 8), np.uint8), rpc=model.rpc)
    with pytest.raises(Gf4calError, match="apply_compensation"):
        write_rpc_vrt(image, model, tmp_path / "out.vrt")
    assert not (tmp_path / "out.vrt").exists()


def test_apply_compensation_is_the_way_to_a_file(sensor_model, tmp_path):
    name, model, _, size = sensor_model
    if name != "compensated_rpc":
        pytest.skip("CompensatedRPC only")
    applied = apply_compensation(model.rpc, model.result, image_size=size)
    # Affine has a rotation/shear term: it does not fold into offsets/scales, the RPC is refitted and the refit's
    # check error (independent grid) is reported; it bounds the error of the written RPC at any image point.
    assert not applied.exact and 0.0 < applied.refit_max_px < 0.01
    s, l = _image_points(size)
    h = _heights(model)
    lon, lat = model.localize(s, l, h)
    s2, l2 = applied.rpc.project(lon, lat, h)
    assert np.max(np.hypot(s2 - s, l2 - l)) <= 2 * applied.refit_max_px
    image = tmp_path / "image.tif"
    from rasters import write_tif
    write_tif(image, np.zeros((8, 8), np.uint8), rpc=model.rpc)
    assert write_rpc_vrt(image, applied.rpc, tmp_path / "out.vrt").exists()


# ---------------------------------------------------------------------------------------------- DEM API
def test_dem_from_user_input(srtm_path, tmp_path):
    assert DEM.from_user_input(None) is None
    flat = DEM.from_user_input(312.5)
    assert flat.is_constant and flat.sample(5.2, 44.1) == 312.5 and type(flat.sample(5.2, 44.1)) is float
    dem = DEM.from_user_input(srtm_path, geoid="egm96", nodata="nan")
    assert dem.geoid_applied == "egm96" and dem.nodata_policy == "nan"
    assert DEM.from_user_input(dem) is dem
    assert DEM.from_user_input(str(srtm_path), geoid=False).geoid_applied is None
    with pytest.raises(DEMError, match="not found"):
        DEM.from_user_input(tmp_path / "missing.tif")
    with pytest.raises(DEMError, match="height in metres"):
        DEM.from_user_input([1.0, 2.0])
    with pytest.raises(DEMError, match="finite"):
        DEM.from_user_input(float("nan"))


def test_dem_sample_nodata_policy(srtm_path, scalar_and_array):
    dem = DEM.from_user_input(srtm_path, geoid=False)
    lon = scalar_and_array(np.array([5.5, 5.1, 5.9, 5.3, 5.7, 5.05]))
    lat = scalar_and_array(np.array([44.5, 44.2, 44.8, 44.1, 44.9, 44.6]))
    h = dem.sample(lon, lat)
    _check_kind(h, lon)
    np.testing.assert_array_equal(h, dem.height(lon, lat))           # height stays an alias
    # Mont Ventoux summit (1909 m above EGM96 on the map, SRTM3 ~1 900 m within a pixel).
    assert dem.sample(5.2786, 44.1741) == pytest.approx(1900.0, abs=40.0)
    outside = (np.array([5.5, 7.5]), np.array([44.5, 44.5]))
    with pytest.raises(DEMError, match="outside the DEM"):
        dem.sample(*outside)
    assert np.isnan(dem.sample(*outside, nodata="nan")[1])
    assert dem.sample(*outside, nodata=-7.0)[1] == -7.0
    assert dem.nodata_policy == "error"                               # the DEM itself is unchanged


@pytest.mark.parametrize("tiled", [False, True])
def test_dem_sample_with_gradient_matches_finite_differences(srtm_path, tiled):
    dem = DEM.from_user_input(srtm_path, geoid=False, nodata="nan")
    if tiled:
        dem._whole_limit = 0          # force the windowed tile reads of a large DEM on this small tile
        dem._tile = 256
    assert dem.gradient_is_analytic
    rng = np.random.default_rng(5)
    lon = rng.uniform(5.02, 5.98, 2000)
    lat = rng.uniform(44.02, 44.98, 2000)
    z, gx, gy = dem.sample_with_gradient(lon, lat)
    np.testing.assert_allclose(z, dem.sample(lon, lat), rtol=0, atol=1e-7)
    # Inside one cell the bilinear surface is smooth: central differences of 1e-6 deg (~1/800 px).
    e = 1e-6
    fx = (dem.sample(lon + e, lat) - dem.sample(lon - e, lat)) / (2 * e)
    fy = (dem.sample(lon, lat + e) - dem.sample(lon, lat - e)) / (2 * e)
    ok = np.isfinite(fx) & np.isfinite(fy) & np.isfinite(z)
    # Away from the cell edges (pixel centres of SRTM3: lon 5 + k/1200, lat 45 - k/1200), where the slope jumps.
    fx_px, fy_px = ((lon - 5.0) * 1200.0) % 1.0, ((45.0 - lat) * 1200.0) % 1.0
    interior = ok & (np.minimum(fx_px, 1 - fx_px) > 0.01) & (np.minimum(fy_px, 1 - fy_px) > 0.01)
    assert interior.sum() > 1500
    np.testing.assert_allclose(gx[interior], fx[interior], rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(gy[interior], fy[interior], rtol=1e-4, atol=1e-3)
    z_out, gx_out, _ = dem.sample_with_gradient(np.array([7.5]), np.array([44.5]))
    assert np.isnan(z_out[0])
