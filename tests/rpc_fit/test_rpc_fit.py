"""Tests of gdal_gf4cal.rpc_fit (METHODS §3): terrain-independent RPC fitting.

Truth comes from (a) two small rigorous sensor models written here from first principles (WGS84 through pyproj,
ray / ellipsoidal-height intersection, Earth rotation), (b) an RPC refitted from itself, (c) the real Sentinel-1
physical-model grids of rpcfit (tests/data/rpcfit_s1) and (d) GDAL's own RPC transformer for the pixel convention.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from osgeo import gdal
from pyproj import Transformer

from gdal_gf4cal.errors import CancelledError, DegenerateGeometryError, GCPError, Gf4calError
from gdal_gf4cal.rpc import RPCModel
from gdal_gf4cal.rpc_fit import FitErrors, FitReport, fit_rpc, fit_rpc_from_model, refit_numerators

gdal.UseExceptions()

# ------------------------------------------------------------------------------------- rigorous test sensors
_TO_ECEF = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
_TO_GEO = Transformer.from_crs("EPSG:4978", "EPSG:4979", always_xy=True)
A_WGS84, B_WGS84 = 6378137.0, 6356752.314245179
OMEGA_E = 7.2921150e-5


def _ecef(lon, lat, h):
    lon, lat, h = np.broadcast_arrays(*(np.asarray(a, float) for a in (lon, lat, h)))
    return np.stack(_TO_ECEF.transform(lon, lat, h), axis=-1)


def _geodetic(xyz):
    return tuple(np.asarray(v) for v in _TO_GEO.transform(xyz[..., 0], xyz[..., 1], xyz[..., 2]))


def _intersect_height(C, u, h):
    """(lon, lat) of the point of the ray ``C + t u`` (ECEF, unit ``u``) at ellipsoidal height ``h``."""
    a, b = A_WGS84 + h, B_WGS84 + h
    q = np.stack([1 / a ** 2, 1 / a ** 2, 1 / b ** 2], -1)
    qa, qb, qc = np.sum(q * u * u, -1), 2 * np.sum(q * u * C, -1), np.sum(q * C * C, -1) - 1
    t = (-qb - np.sqrt(qb * qb - 4 * qa * qc)) / (2 * qa)     # near root on the (a+h, b+h) ellipsoid
    for _ in range(4):                                          # then Newton on the true geodetic height
        lon, lat, hh = _geodetic(C + t[..., None] * u)
        lo, la = np.radians(lon), np.radians(lat)
        up = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], -1)
        t = t - (hh - h) / np.sum(u * up, -1)
    lon, lat, _ = _geodetic(C + t[..., None] * u)
    return lon, lat


class FrameCamera:
    """Geostationary area-array camera (GF4-like: 10240^2, 50 m) with yaw and radial distortion (~3.5 px at the
    edge). ``localize`` and ``project`` are exact inverses (GDAL pixel convention)."""

    def __init__(self, size=(10240, 10240), sat_lon=105.6, target=(90.0, 31.0, 4500.0), gsd=50.0, k1=3.4e-4,
                 yaw_deg=0.05):
        self.size = size
        r = 42164e3
        self.C = np.array([r * np.cos(np.radians(sat_lon)), r * np.sin(np.radians(sat_lon)), 0.0])
        z = _ecef(*target) - self.C
        dist = np.linalg.norm(z)
        z = z / dist
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)                      # samples grow eastwards, lines southwards
        y = np.cross(z, x)
        c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
        self.R = np.array([c * x + s * y, -s * x + c * y, z])
        self.f = dist / gsd
        self.k1 = k1
        self.half = np.array(size, float) / 2

    def localize(self, sample, line, h):
        sample, line, h = np.broadcast_arrays(*(np.asarray(a, float) for a in (sample, line, h)))
        u, v = sample - self.half[0], line - self.half[1]
        k = 1 + self.k1 * (u * u + v * v) / self.half[0] ** 2
        d = np.stack([u * k, v * k, np.full(u.shape, self.f)], -1) @ self.R
        return _intersect_height(self.C, d / np.linalg.norm(d, axis=-1, keepdims=True), h)

    def project(self, lon, lat, h):
        c = (_ecef(lon, lat, h) - self.C) @ self.R.T
        up, vp = self.f * c[..., 0] / c[..., 2], self.f * c[..., 1] / c[..., 2]
        u, v = up, vp
        for _ in range(30):                        # invert the radial distortion (fixed point, contracting)
            k = 1 + self.k1 * (u * u + v * v) / self.half[0] ** 2
            u, v = up / k, vp / k
        return u + self.half[0], v + self.half[1]


class PushBroom:
    """LEO push-broom, HJ-1-like (650 km, 12000 px, 30 m, rolled 15 deg): circular orbit, Earth rotation, attitude
    drift in roll/pitch/yaw, cubic cross-track distortion of ``distortion_px`` at the swath edges. Only
    ``localize`` (the library must not need ``project``)."""

    def __init__(self, size=(12000, 12000), altitude=650e3, gsd=30.0, roll_deg=15.0, distortion_px=20.0,
                 lon0=100.0, lat0=35.0, drift=(2e-6, -3e-6, 5e-6)):
        self.size = size
        self.r = A_WGS84 + altitude
        self.n = np.sqrt(3.986004418e14 / self.r ** 3)
        inc = np.radians(97.9)
        u0 = np.arcsin(np.sin(np.radians(lat0)) / np.sin(inc))
        raan = np.radians(lon0) - np.arctan2(np.cos(inc) * np.sin(u0), np.cos(u0))
        self.p = np.array([np.cos(raan), np.sin(raan), 0.0])
        self.q = np.array([-np.sin(raan) * np.cos(inc), np.cos(raan) * np.cos(inc), np.sin(inc)])
        self.dt = gsd / (self.n * A_WGS84)
        self.u0 = u0 - self.n * self.dt * size[1] / 2
        self.pix = gsd / altitude
        self.roll = np.radians(roll_deg)
        self.dist = distortion_px
        self.drift = np.array(drift)

    @staticmethod
    def _rotate(axis, ang, v):
        c, s = np.cos(ang)[..., None], np.sin(ang)[..., None]
        k = np.zeros(3)
        k[axis] = 1.0
        return v * c + np.cross(k, v) * s + k * np.sum(k * v, -1, keepdims=True) * (1 - c)

    def localize(self, sample, line, h):
        sample, line, h = np.broadcast_arrays(*(np.asarray(a, float) for a in (sample, line, h)))
        t = line * self.dt
        u = (self.u0 + self.n * t)[..., None]
        pos = self.r * (np.cos(u) * self.p + np.sin(u) * self.q)
        vel = self.r * self.n * (-np.sin(u) * self.p + np.cos(u) * self.q)
        zo = -pos / self.r
        yo = -np.cross(pos, vel)
        yo /= np.linalg.norm(yo, axis=-1, keepdims=True)
        xo = np.cross(yo, zo)
        half = self.size[0] / 2
        xi = (sample - half) / half
        tan_cross = ((sample - half) + self.dist * xi ** 3) * self.pix
        d = np.stack([np.zeros_like(tan_cross), tan_cross, np.ones_like(tan_cross)], -1)
        d = self._rotate(0, self.roll + self.drift[0] * t, d)
        d = self._rotate(1, self.drift[1] * t, d)
        d = self._rotate(2, self.drift[2] * t, d)
        ray = d[..., :1] * xo + d[..., 1:2] * yo + d[..., 2:] * zo
        ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
        c, s = np.cos(-OMEGA_E * t), np.sin(-OMEGA_E * t)      # ECI -> ECEF (equal at t = 0)

        def rz(v):
            return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1], v[..., 2]], -1)
        return _intersect_height(rz(pos), rz(ray), h)


def _smooth_rpc(seed=3, size=(6000, 4000)):
    """A vendor-like RPC (small denominators) used as a model with known truth."""
    rng = np.random.default_rng(seed)

    def num(main):
        c = rng.normal(0, 2e-3, 20)
        c[:4] = main
        return c

    def den():
        c = rng.normal(0, 5e-4, 20)
        c[0] = 1.0
        return c
    W, H = size
    return RPCModel(line_off=H / 2 - 0.5, samp_off=W / 2 - 0.5, lat_off=35.2, long_off=101.3, height_off=1500.0,
                    line_scale=H / 2, samp_scale=W / 2, lat_scale=0.12, long_scale=0.15, height_scale=1500.0,
                    line_num=num([0.01, 0.05, -1.02, 0.02]), line_den=den(),
                    samp_num=num([-0.02, 0.98, 0.04, -0.03]), samp_den=den())


@pytest.fixture(scope="module")
def s1(data_dir):
    d = data_dir / "rpcfit_s1"
    return {k: np.load(d / f"s1_{k}.npy") for k in ("train3d", "train2d", "test3d", "test2d")}


# ------------------------------------------------------------------------------------- real data: Sentinel-1
def test_s1_grids_equal_or_better_than_rpcfit(s1):
    """Fit on train, errors on the independent (offset, partly extrapolated) test grid. rpcfit measured here:
    test RMSE 1.1e-4 px per axis and max 7.8e-4 px (2 significant digits, so < 1.15e-4 and < 7.85e-4)."""
    (lon, lat, h), (x, y) = s1["train3d"].T, s1["train2d"].T
    rpc, rep = fit_rpc(lon, lat, h, x, y, check=(*s1["test3d"].T, *s1["test2d"].T))
    assert rep.n_points == 4000 and rep.check.n_points == 4000
    assert rep.check.rms_sample_px < 1.15e-4 and rep.check.rms_line_px < 1.15e-4
    assert rep.check.max_sample_px < 7.85e-4 and rep.check.max_line_px < 7.85e-4
    assert rep.fit.rms_sample_px < 1.1e-4 and rep.fit.rms_line_px < 1.1e-4
    # The report is what the returned RPC does, independently recomputed.
    ps, pl = rpc.project(*s1["test3d"].T)
    np.testing.assert_allclose(np.sqrt(np.mean((pl - s1["test2d"][:, 1]) ** 2)), rep.check.rms_line_px, rtol=1e-9)
    # Vendors' normalisation: centre / half range of the data (raw convention = GDAL - 0.5).
    assert rpc.samp_off == pytest.approx((x.min() + x.max()) / 2 - 0.5)
    assert rpc.line_scale == pytest.approx((y.max() - y.min()) / 2)
    assert rpc.height_off == pytest.approx((h.min() + h.max()) / 2)
    assert rep.regularization[0] <= 1e-12 and max(rep.iterations) <= 20


def test_s1_least_squares_optimum_is_regularisation_independent(s1):
    """The tiny default Tikhonov term must not bias the fit: the unregularised QR solve lands on the same RPC
    (to 2 % of the error floor)."""
    args = (*s1["train3d"].T, *s1["train2d"].T)
    _, auto = fit_rpc(*args, check=(*s1["test3d"].T, *s1["test2d"].T))
    _, plain = fit_rpc(*args, check=(*s1["test3d"].T, *s1["test2d"].T), regularization=0.0)
    assert plain.regularization == (0.0, 0.0)
    assert auto.check.rms_px == pytest.approx(plain.check.rms_px, rel=0.02)
    # A heavy regularisation is honoured and visibly biases the fit (so the parameter is really used).
    _, heavy = fit_rpc(*args, regularization=1e-8)
    assert heavy.regularization == (1e-8, 1e-8) and heavy.fit.rms_px > 3 * auto.fit.rms_px


# ------------------------------------------------------------------------------------- rigorous sensors
def test_frame_camera_full_size_meets_methods_targets():
    cam = FrameCamera()
    rpc, rep = fit_rpc_from_model(cam, height_range=(3000.0, 6000.0))
    assert rep.check.max_px <= 0.01 and rep.check.rms_px <= 0.002
    assert rep.n_points == 21 * 21 * 7 and rep.check.n_points == 20 * 20 * 6
    assert rep.model_roundtrip_max_px < 1e-6
    # Vendor normalisation: image centre / half size (raw convention), heights covering the layers (+10 %).
    assert (rpc.samp_off, rpc.samp_scale, rpc.line_off, rpc.line_scale) == (5119.5, 5120.0, 5119.5, 5120.0)
    assert rpc.height_range == pytest.approx((2700.0, 6300.0))
    # Independent truth: random points at random heights, through the camera's own project().
    rng = np.random.default_rng(7)
    s, l, hh = rng.uniform(0, 10240, 500), rng.uniform(0, 10240, 500), rng.uniform(3000, 6000, 500)
    lon, lat = cam.localize(s, l, hh)
    ps, pl = rpc.project(lon, lat, hh)
    assert np.max(np.hypot(ps - s, pl - l)) <= 0.01


def test_pushbroom_meets_methods_targets_without_project():
    pb = PushBroom()
    assert not hasattr(pb, "project")
    rpc, rep = fit_rpc_from_model(pb, height_range=(0.0, 2000.0), grid=(25, 20), n_layers=6)
    assert rep.check.max_px <= 0.01 and rep.check.rms_px <= 0.002
    assert rep.model_roundtrip_max_px is None
    assert rep.n_points == 25 * 20 * 6
    assert (rpc.samp_off, rpc.samp_scale) == (5999.5, 6000.0)


def test_refit_of_an_rpc_reproduces_it():
    """An RPC is exactly representable: refitting it from itself must give the same mapping."""
    truth = _smooth_rpc()
    rpc, rep = fit_rpc_from_model(truth, size=(6000, 4000), height_range=truth.height_range)
    assert rep.check.max_px < 1e-5
    rng = np.random.default_rng(11)
    lon = rng.uniform(101.18, 101.42, 1000)
    lat = rng.uniform(35.1, 35.3, 1000)
    h = rng.uniform(0, 3000, 1000)
    ts, tl = truth.project(lon, lat, h)
    ps, pl = rpc.project(lon, lat, h)
    assert np.max(np.abs(ps - ts)) < 1e-5 and np.max(np.abs(pl - tl)) < 1e-5


def test_window_keeps_model_coordinates():
    cam = FrameCamera()
    rpc, rep = fit_rpc_from_model(cam, window=(1000, 2000, 512, 256), height_range=(4000.0, 5000.0))
    assert rpc.samp_off == 1000 + 256 - 0.5 and rpc.samp_scale == 256
    assert rpc.line_off == 2000 + 128 - 0.5 and rpc.line_scale == 128
    assert rep.check.max_px < 1e-3
    lon, lat = cam.localize(1100.25, 2100.75, 4321.0)
    s, l = rpc.project(lon, lat, 4321.0)
    assert s == pytest.approx(1100.25, abs=1e-3) and l == pytest.approx(2100.75, abs=1e-3)


def test_pixel_convention_agrees_with_gdal_rpc_transformer():
    """GDAL's RPC transformer, fed the fitted RPC, returns the model's (sample, line) in GDAL convention."""
    cam = FrameCamera(size=(2000, 1500))
    rpc, _ = fit_rpc_from_model(cam, height_range=(3000.0, 6000.0))
    ds = gdal.GetDriverByName("MEM").Create("", 2000, 1500, 1)
    ds.SetMetadata(rpc.to_gdal_metadata(), "RPC")
    tr = gdal.Transformer(ds, None, ["METHOD=RPC"])
    s = np.array([0.5, 1000.25, 1999.5, 0.0])
    l = np.array([0.5, 700.75, 1499.5, 1500.0])
    h = np.array([3000.0, 4500.0, 6000.0, 3500.0])
    lon, lat = cam.localize(s, l, h)
    pts, ok = tr.TransformPoints(1, list(zip(lon, lat, h)))
    assert all(ok)
    np.testing.assert_allclose(np.array(pts)[:, :2], np.column_stack([s, l]), atol=1e-3)
    # Raw-convention input gives the same RPC.
    S, L = np.meshgrid(np.linspace(0, 2000, 20), np.linspace(0, 1500, 20))
    grid = [np.concatenate([a.ravel()] * 6) for a in (S, L)]
    hs = np.repeat(np.linspace(3000, 6000, 6), S.size)
    glon, glat = cam.localize(grid[0], grid[1], hs)
    a, _ = fit_rpc(glon, glat, hs, grid[0], grid[1])
    b, _ = fit_rpc(glon, glat, hs, grid[0] - 0.5, grid[1] - 0.5, pixel_convention="rpc")
    assert a.samp_off == b.samp_off and a.line_off == b.line_off
    np.testing.assert_allclose(a.samp_num, b.samp_num, rtol=1e-9, atol=1e-15)


def test_antimeridian_scene():
    base = _smooth_rpc()
    truth = base.replace(long_off=179.95)
    S, L, Hh = (v.ravel() for v in np.meshgrid(np.linspace(0, 6000, 20), np.linspace(0, 4000, 20),
                                               np.linspace(0, 3000, 6)))
    lon, lat = truth.localize(S, L, Hh)
    lon = (lon + 180.0) % 360.0 - 180.0            # as a GCP file would give them: both signs
    assert lon.min() < -179 and lon.max() > 179
    rpc, rep = fit_rpc(lon, lat, Hh, S, L)
    assert rep.fit.max_px < 1e-5
    assert abs(rpc.long_off) > 179.8 and rpc.long_scale < 0.5


# ------------------------------------------------------------------------------------- degenerate input
def _grid_points(n=20, n_layers=6):
    truth = _smooth_rpc()
    S, L, Hh = (v.ravel() for v in np.meshgrid(np.linspace(0, 6000, n), np.linspace(0, 4000, n),
                                               np.linspace(0, 3000, n_layers)))
    lon, lat = truth.localize(S, L, Hh)
    return truth, lon, lat, Hh, S, L


def test_single_height_fallback_keeps_h_terms_zero():
    truth, lon, lat, h, s, l = _grid_points(n=20, n_layers=1)
    assert np.all(h == h[0])
    rpc, rep = fit_rpc(lon, lat, h, s, l)
    assert any("single height" in n for n in rep.notes)
    h_terms = [3, 5, 6, 9, 10, 13, 16, 17, 18, 19]
    for c in (rpc.samp_num, rpc.samp_den, rpc.line_num, rpc.line_den):
        assert np.all(c[h_terms] == 0.0)
    assert rpc.height_off == h[0] and rpc.height_scale == 1.0
    # Accurate at that height, between the fit points.
    clon, clat = truth.localize(np.array([123.4, 3000.0, 5800.0]), np.array([77.0, 2000.0, 3900.0]), h[0])
    ps, pl = rpc.project(clon, clat, h[0])
    np.testing.assert_allclose(ps, [123.4, 3000.0, 5800.0], atol=0.01)
    # ... and through the model path with a zero-width height range.
    rpc2, rep2 = fit_rpc_from_model(truth, size=(6000, 4000), height_range=(500.0, 500.0))
    assert rep2.check.max_px < 0.01 and rpc2.height_off == 500.0 and rep2.n_points == 21 * 21


@pytest.mark.parametrize("case", ["few", "nan", "line", "same_sample"])
def test_degenerate_correspondences_raise(case):
    _, lon, lat, h, s, l = _grid_points()
    if case == "few":
        lon, lat, h, s, l = (a[:38] for a in (lon, lat, h, s, l))
    elif case == "nan":
        lat = lat.copy()
        lat[5] = np.nan
    elif case == "line":
        lat = 35.2 + 0.5 * (lon - 101.3)                # every ground point on one straight line
    elif case == "same_sample":
        s = np.full_like(s, 10.0)
    with pytest.raises(DegenerateGeometryError) as exc:
        fit_rpc(lon, lat, h, s, l)
    assert isinstance(exc.value, Gf4calError) and "\n" not in str(exc.value)


def test_bad_arguments_raise_clear_errors():
    _, lon, lat, h, s, l = _grid_points()
    with pytest.raises(GCPError, match="equal length"):
        fit_rpc(lon, lat[:-1], h, s, l)
    with pytest.raises(ValueError, match="regularization"):
        fit_rpc(lon, lat, h, s, l, regularization="lcurve")
    with pytest.raises(DegenerateGeometryError, match="check"):
        fit_rpc(lon, lat, h, s, l, check=(lon, lat, h, s * np.nan, l))
    truth = _smooth_rpc()
    with pytest.raises(DegenerateGeometryError, match="20x20"):
        fit_rpc_from_model(truth, size=(100, 100), height_range=(0, 10), grid=(10, 30))
    with pytest.raises(DegenerateGeometryError, match="6"):
        fit_rpc_from_model(truth, size=(100, 100), height_range=(0, 10), n_layers=3)
    with pytest.raises(ValueError, match="height_range"):
        fit_rpc_from_model(truth, size=(100, 100), height_range=(10, 0))
    with pytest.raises(ValueError, match="size"):
        fit_rpc_from_model(object(), height_range=(0, 10))


def test_points_the_model_cannot_localise_are_dropped_and_reported():
    truth = _smooth_rpc()

    class Holey:
        size = (6000, 4000)
        height_range = (0.0, 3000.0)

        def localize(self, sample, line, h):
            lon, lat = truth.localize(sample, line, h)
            bad = (np.asarray(sample) < 300) & (np.asarray(line) < 300)   # e.g. space seen in a corner
            return np.where(bad, np.nan, lon), np.where(bad, np.nan, lat)

    rpc, rep = fit_rpc_from_model(Holey())
    assert any("dropped" in n for n in rep.notes)
    # grid nodes at sample 0 and lines 0, 200 fall in the hole: 2 per layer
    assert rep.n_points == 21 * 21 * 7 - 2 * 7 and rep.check.max_px < 1e-4


# ------------------------------------------------------------------------------------- progress, report
def test_progress_and_cancellation():
    truth = _smooth_rpc()
    seen = []
    fit_rpc_from_model(truth, size=(6000, 4000), height_range=(0, 3000), progress=lambda f, m: seen.append(f))
    assert seen[-1] == 1.0 and all(0.0 <= f <= 1.0 for f in seen) and seen == sorted(seen)

    def cancel(f, m):
        if f > 0.3:
            raise CancelledError("cancelled by the user")
    with pytest.raises(CancelledError):
        fit_rpc_from_model(truth, size=(6000, 4000), height_range=(0, 3000), progress=cancel)


def test_report_values_and_dict():
    e = FitErrors.from_residuals(np.array([3.0, 0.0, -1.0]), np.array([4.0, 0.0, 0.0]))
    assert e.max_px == 5.0 and e.max_sample_px == 3.0 and e.max_line_px == 4.0
    assert e.rms_px == pytest.approx(np.sqrt(26 / 3)) and e.rms_sample_px == pytest.approx(np.sqrt(10 / 3))
    truth = _smooth_rpc()
    rpc, rep = fit_rpc_from_model(truth, size=(6000, 4000), height_range=(0, 3000))
    assert isinstance(rep, FitReport)
    assert rep.rms_px == rep.check.rms_px and rep.max_px == rep.check.max_px
    d = json.loads(json.dumps(rep.to_dict()))
    assert d["check"]["max_px"] == rep.check.max_px and d["iterations"]["line"] == rep.iterations[1]
    assert set(d) >= {"fit", "check", "n_points", "iterations", "regularization", "elapsed_s", "notes"}
    _, rep2 = fit_rpc(*_grid_points()[1:])
    assert rep2.check is None and rep2.max_px == rep2.fit.max_px


def test_refit_numerators_recovers_a_numerator_change_and_keeps_the_rest(data_dir):
    """A real Pleiades RPC whose numerators are changed by a known amount (a ~1 px field over the image): the
    refit on a ground grid at 7 heights recovers the changed model to 1e-6 px, and the denominators, offsets and
    scales are those of the RPC it started from."""
    rpc = RPCModel.from_file(str(data_dir / "rpc" / "RPC_PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.XML"))
    rng = np.random.default_rng(7)
    changed = rpc.replace(samp_num=rpc.samp_num + rng.normal(0, 2e-5, 20),
                          line_num=rpc.line_num + rng.normal(0, 2e-5, 20))
    W, H = rpc.image_size
    s, l = np.meshgrid(np.linspace(0, W, 31), np.linspace(0, H, 31))
    lon, lat, h = [], [], []
    for hv in np.linspace(*rpc.height_range, 7):
        x, y = changed.localize(s, l, np.full(s.shape, hv))
        lon.append(x.ravel()), lat.append(y.ravel()), h.append(np.full(s.size, hv))
    lon, lat, h = (np.concatenate(v) for v in (lon, lat, h))
    S, L = changed.project(lon, lat, h)
    before = np.hypot(*(np.subtract(rpc.project(lon, lat, h), (S, L))))
    assert before.max() > 0.5                                      # the change is a real one
    got = refit_numerators(rpc, lon, lat, h, S, L)
    err = np.hypot(*(np.subtract(got.project(lon, lat, h), (S, L))))
    assert err.max() < 1e-6
    assert np.array_equal(got.samp_den, rpc.samp_den) and np.array_equal(got.line_den, rpc.line_den)
    assert (got.samp_off, got.line_scale, got.long_off, got.height_scale) == \
        (rpc.samp_off, rpc.line_scale, rpc.long_off, rpc.height_scale)
