"""Line-of-sight x DEM intersection on the real SRTM tile with a real Pleiades RPC, against GDAL (METHODS §1-§2)."""
from __future__ import annotations

import numpy as np
import pytest
from osgeo import gdal

from rasters import write_tif

from gdal_gf4cal import DEM, RPCModel, localization

gdal.UseExceptions()


@pytest.fixture(scope="module")
def ventoux(ventoux_rpc_path):
    return RPCModel.from_file(ventoux_rpc_path)


def _points(rpc, n, seed=0):
    w, h = rpc.image_size
    rng = np.random.default_rng(seed)
    return rng.uniform(0, w, n), rng.uniform(0, h, n)


@pytest.mark.parametrize("dem_name", ["N44E005.hgt", "N44E005_UTM.tif"])
def test_localize_dem_is_exact_on_the_dem(ventoux, data_dir, dem_name):
    dem = DEM.from_file(data_dir / "dem" / dem_name, nodata="nan")
    s, l = _points(ventoux, 3000)
    lon, lat, h, stats = ventoux.localize_dem(s, l, dem, full_output=True)
    ok = np.isfinite(h)
    assert stats.n_failed == np.count_nonzero(~ok) and stats.n_failed < 0.02 * s.size   # rays into SRTM voids only
    s2, l2 = ventoux.project(lon[ok], lat[ok], h[ok])
    assert np.max(np.hypot(s2 - s[ok], l2 - l[ok])) <= 1e-6            # re-projection error
    assert np.max(np.abs(dem.height(lon[ok], lat[ok]) - h[ok])) <= 1e-3  # height equals the DEM there


@pytest.mark.parametrize("dem_name", ["N44E005.hgt", "N44E005_UTM.tif"])
def test_localize_dem_agrees_with_gdal_rpc_dem(ventoux, data_dir, dem_name):
    dem_path = str(data_dir / "dem" / dem_name)
    w, h = ventoux.image_size
    ds = gdal.GetDriverByName("MEM").Create("", w, h)
    ds.SetMetadata(ventoux.to_gdal_metadata(), "RPC")
    tr = gdal.Transformer(ds, None, ["METHOD=RPC", f"RPC_DEM={dem_path}", "RPC_PIXEL_ERROR_THRESHOLD=1e-6",
                                     "RPC_DEM_APPLY_VDATUM_SHIFT=FALSE"])
    s, l = _points(ventoux, 2000, seed=1)
    out, ok = tr.TransformPoints(0, np.column_stack([s, l, np.zeros(s.size)]))
    out, ok = np.asarray(out), np.asarray(ok, dtype=bool)
    assert ok.mean() > 0.95
    lon, lat, hh = ventoux.localize_dem(s[ok], l[ok], DEM.from_file(dem_path, nodata="nan"))
    # Difference of the two ground points expressed in image pixels (through the RPC's Jacobian).
    J = ventoux.project_jacobian(lon, lat, hh)[:, :, :2]
    d_px = np.hypot(*np.einsum("nij,nj->ni", J, np.column_stack([out[ok, 0] - lon, out[ok, 1] - lat])).T)
    assert np.mean(d_px <= 1e-3) >= 0.99      # NaN (our void points) count as disagreement


def test_shareloc_reference_point_with_geoid(ventoux, srtm_path):
    """CNES shareloc's direct localisation of the Ventoux image centre on SRTM + EGM96 (independent tool).

    Shareloc localises with DIMAP's separate *direct* polynomial; we invert the inverse model, as GDAL does. The
    two models differ by millimetres (3e-8 deg here), hence the tolerance of 5e-8 deg (about 4 mm, 0.01 px).
    """
    dem = DEM.from_file(srtm_path, geoid="egm96")
    lon, lat, h = ventoux.localize_dem(5000.5, 5000.5, dem)
    assert lon == pytest.approx(5.193406151946084, abs=5e-8)
    assert lat == pytest.approx(44.20805807814395, abs=5e-8)
    assert h == pytest.approx(503.51202179, abs=1e-3)


class _CountingTransformer:
    """PROJ's geoid transformer of a DEM, counting the points it is asked for (the real transform answers)."""

    def __init__(self, transformer):
        self.transformer, self.points = transformer, 0

    def transform(self, x, y, z):
        self.points += np.size(x)
        return self.transformer.transform(x, y, z)


@pytest.mark.parametrize("tol_m", [1e-4, 1e-5])
def test_generic_path_on_a_geoid_dem_iterates_without_proj(ventoux, srtm_path, tol_m):
    """The generic path (any model; the RPC with fast_path=False here) on SRTM + EGM96: its height checks are the
    Newton sampler's (the geoid's lattice), |DEM.sample - h| <= tol_m all the same; PROJ's geoid transform sees no
    point: not at every height iteration (it holds the GIL), nor for the march's undulation per ray (the lattice's)."""
    dem = DEM.from_file(srtm_path, geoid="egm96", nodata="nan")
    assert dem.newton_sampler() is not None                  # the lattice, built (PROJ at its nodes) before counting
    s, l = _points(ventoux, 1500, seed=5)
    spy = dem._geoid = _CountingTransformer(dem._geoid)
    lon, lat, h = localization.localize_dem(ventoux, s, l, dem, fast_path=False, tol_m=tol_m)
    assert spy.points == 0
    ok = np.isfinite(h)
    assert ok.mean() > 0.98
    assert np.max(np.abs(dem.sample(lon[ok], lat[ok]) - h[ok])) <= tol_m
    s2, l2 = ventoux.project(lon[ok], lat[ok], h[ok])
    assert np.max(np.hypot(s2 - s[ok], l2 - l[ok])) <= 1e-6


@pytest.mark.parametrize("n", [1, 16, 2000])
def test_fast_path_on_a_geoid_dem_makes_no_proj_call(ventoux, srtm_path, n):
    """The RPC fast path on SRTM + EGM96, a small call as a large one: its start height, Newton steps and checks all
    on the Newton sampler (the start height was DEM.sample's, a PROJ call: a small call's fixed cost); the results
    within tol_m of DEM.sample (PROJ) and exact in the image."""
    dem = DEM.from_file(srtm_path, geoid="egm96", nodata="nan")
    assert dem.newton_sampler() is not None                  # the lattice, built (PROJ at its nodes) before counting
    s, l = _points(ventoux, n, seed=6)
    spy = dem._geoid = _CountingTransformer(dem._geoid)
    lon, lat, h = ventoux.localize_dem(s, l, dem)
    assert spy.points == 0 and np.isfinite(h).all()
    assert np.max(np.abs(dem.sample(lon, lat) - h)) <= 1e-4
    s2, l2 = ventoux.project(lon, lat, h)
    assert np.max(np.hypot(s2 - s, l2 - l)) <= 1e-6


def test_steep_oblique_terrain_uses_bracketing(tmp_path, monkeypatch):
    """A cliff seen obliquely makes the plain height iteration oscillate; bracketing must still find the surface."""
    # Oblique synthetic RPC: image sample depends strongly on height (about 1 px per metre).
    zeros = np.zeros(20)
    samp_num, line_num, den = zeros.copy(), zeros.copy(), zeros.copy()
    den[0] = 1.0
    samp_num[1] = 1.0
    samp_num[3] = 0.9        # d sample / dH comparable to d sample / dL: ~40 deg off-nadir
    line_num[2] = -1.0
    rpc = RPCModel(line_off=500, samp_off=500, lat_off=45.0, long_off=7.0, height_off=500.0, line_scale=500,
                   samp_scale=500, lat_scale=0.005, long_scale=0.005, height_scale=500.0, line_num=line_num,
                   line_den=den, samp_num=samp_num, samp_den=den)
    # Terrain: a steep ramp along longitude (slope ~2.5) so that |slope * tan(view)| > 1.
    x = np.linspace(6.99, 7.01, 401)
    heights = np.clip((x - 6.995) * 1.0e5 * 1.5, 0, 1000)
    arr = np.tile(heights, (401, 1)).astype(np.float32)
    path = write_tif(tmp_path / "cliff.tif", arr, gt=(6.99 - 0.00005 / 2, 0.00005, 0, 45.01, 0, -0.00005), epsg=4326)
    dem = DEM.from_file(path)
    import gdal_gf4cal.localization as localization
    bracketed = []
    original = localization._bracket_and_refine
    monkeypatch.setattr(localization, "_bracket_and_refine",
                        lambda loc, terrain, todo, *a: bracketed.append(todo.size) or original(loc, terrain, todo, *a))
    s = np.linspace(100, 900, 400)
    l = np.full_like(s, 500.0)
    # The generic height iteration oscillates here: most points really go through stage 2 (bracketing).
    *_, stats = localization.localize_dem(rpc, s, l, dem, full_output=True, fast_path=False)
    assert stats.n_failed == 0 and bracketed and bracketed[0] > 100
    # The RPC fast path sees that these rays may cross the cliff more than once (slope x tan(view) > 1) and
    # finds their first crossing from the top with the same march, on its cubic rays, without the fallback.
    bracketed.clear()
    marched = []
    march = localization._march
    monkeypatch.setattr(localization, "_march", lambda ray, dem: marched.append(ray.C.shape[1]) or march(ray, dem))
    lon, lat, h, stats = rpc.localize_dem(s, l, dem, full_output=True)
    assert stats.n_failed == 0
    assert marched == [s.size] and not bracketed
    s2, l2 = rpc.project(lon, lat, h)
    assert np.max(np.hypot(s2 - s, l2 - l)) <= 1e-6
    assert np.max(np.abs(dem.height(lon, lat) - h)) <= 1e-3


def test_constant_height_and_off_dem_points(ventoux, srtm_path):
    lon, lat, h = ventoux.localize_dem(np.array([100.0, 200.0]), np.array([100.0, 300.0]), 400.0)
    assert np.all(h == 400.0)
    lon0, lat0 = ventoux.localize(np.array([100.0, 200.0]), np.array([100.0, 300.0]), 400.0)
    np.testing.assert_array_equal(lon, lon0)
    # A point far outside the image lands outside the SRTM tile: NaN and counted, never a wrong value.
    lon, lat, h, stats = ventoux.localize_dem(np.array([5000.0, 4e6]), np.array([5000.0, 5000.0]),
                                                 DEM.from_file(srtm_path), full_output=True)
    assert np.isfinite(h[0]) and np.isnan(h[1]) and stats.n_failed == 1


def test_localize_dem_across_the_antimeridian_on_a_world_dem(tmp_path):
    """A scene centred on 180 deg: points east of it localise to lon > 180 and must still find the -180..180 DEM."""
    zeros = np.zeros(20)
    samp_num, line_num, den = zeros.copy(), zeros.copy(), zeros.copy()
    den[0] = 1.0
    samp_num[1], samp_num[3] = 1.0, 0.05
    line_num[2] = -1.0
    rpc = RPCModel(line_off=500, samp_off=500, lat_off=-16.0, long_off=179.95, height_off=200.0, line_scale=500,
                   samp_scale=500, lat_scale=0.2, long_scale=0.2, height_scale=500.0, line_num=line_num,
                   line_den=den, samp_num=samp_num, samp_den=den)
    yy, xx = np.mgrid[0:40, 0:3600]          # a band all around the globe, 14..18 S
    arr = (100.0 + 50.0 * np.sin(xx / 7.0) * np.cos(yy / 5.0)).astype(np.float32)
    path = write_tif(tmp_path / "world.tif", arr, gt=(-180.0, 0.1, 0, -14.0, 0, -0.1), epsg=4326)
    dem = DEM.from_file(path)
    s, l = np.meshgrid(np.linspace(10, 990, 15), np.linspace(10, 990, 15))
    lon, lat, h, stats = rpc.localize_dem(s.ravel(), l.ravel(), dem, full_output=True)
    assert stats.n_failed == 0 and np.any(lon > 180.0) and np.any(lon < 180.0)
    s2, l2 = rpc.project(lon, lat, h)
    assert np.max(np.hypot(s2 - s.ravel(), l2 - l.ravel())) <= 1e-6
    assert np.max(np.abs(dem.height(lon, lat) - h)) <= 1e-3


def test_ray_basis_is_the_binomial_expansion_bit_for_bit(ventoux):
    """The fast path's ray basis (Python floats, a table of terms) is bit for bit the binomial expansion of the
    approximate inverse at Hm written out with NumPy scalars, term by term in RPC00B order."""
    import math

    import gdal_gf4cal.localization as localization
    A = ventoux._approximate_inverse
    col = {(ex, ey): k for k, (_, ex, ey) in enumerate(localization._XY_TERMS)}
    for Hm in (-0.37, 0.0, 0.81234567):
        B = np.zeros((8, 10))
        for j, (ex, ey, eh) in enumerate(localization._EXPONENTS):
            for k in range(eh + 1):
                w = math.comb(eh, k) * Hm ** (eh - k)
                B[k, col[(ex, ey)]] += A[0, j] * w
                B[4 + k, col[(ex, ey)]] += A[1, j] * w
        np.testing.assert_array_equal(localization._ray_basis(A, Hm), B)
