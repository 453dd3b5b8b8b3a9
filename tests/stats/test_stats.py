"""Accuracy statistics (METHODS §6) against hand-computed values."""
from __future__ import annotations

import numpy as np
import pytest

from gdal_gf4cal.stats import axis_stats, ce90, internal_accuracy, planar_stats, share_within


def test_axis_stats_definitions():
    r = np.array([1.0, -2.0, 3.0, 6.0])
    s = axis_stats(r)
    assert s["mean"] == 2.0
    assert s["rms"] == pytest.approx(np.sqrt((1 + 4 + 9 + 36) / 4))
    assert s["std"] == pytest.approx(np.sqrt(((1 - 2) ** 2 + 16 + 1 + 16) / 4))
    assert s["max"] == 6.0 and s["n"] == 4
    # rms² = mean² + std² (the relation behind seed 000's Table 3: 9.90² = 2.52² + 9.57²)
    assert s["rms"] ** 2 == pytest.approx(s["mean"] ** 2 + s["std"] ** 2)
    assert axis_stats([np.nan])["n"] == 0


def test_ce90_and_share():
    dx = np.r_[np.zeros(9), 10.0]
    assert ce90(dx, np.zeros(10)) == pytest.approx(1.0)       # 90th percentile with linear interpolation
    assert share_within(dx, np.zeros(10), 0.25) == 0.9
    assert planar_stats([3.0], [4.0])["rms"] == 5.0


def test_internal_accuracy_removes_rotation_and_translation():
    rng = np.random.default_rng(0)
    s, l = rng.uniform(0, 10000, (2, 200))
    theta = 2e-3
    c, sn = np.cos(theta), np.sin(theta)
    noise = rng.normal(0, 0.5, (2, 200))
    sm = c * (s - 5000) - sn * (l - 5000) + 5000 + 4.0 + noise[0]
    lm = sn * (s - 5000) + c * (l - 5000) + 5000 - 7.0 + noise[1]
    out = internal_accuracy(sm, lm, s, l)
    assert out["theta_rad"] == pytest.approx(theta, abs=2e-5)
    assert out["sample"]["rms"] == pytest.approx(0.5, rel=0.15)
    assert out["line"]["rms"] == pytest.approx(0.5, rel=0.15)
    assert abs(out["sample"]["mean"]) < 1e-9


def test_accuracy_report_splits_axes_and_reports_ce90_in_metres():
    from gdal_gf4cal.stats import accuracy_report
    rep = accuracy_report([3.0, -3.0, np.nan], [4.0, 4.0, 1.0], ground_m_per_px=50.0)
    assert rep["n"] == 2 and rep["line"]["mean"] == 4.0 and rep["sample"]["std"] == 3.0
    assert rep["planar"]["max"] == 5.0 and rep["ce90_m"] == 250.0


def test_accuracy_by_role_is_the_one_report_shape():
    import pandas as pd
    from gdal_gf4cal.stats import accuracy_by_role
    tab = pd.DataFrame({"role": ["control"] * 3 + ["check"] * 2, "outlier": [False, False, True, False, False],
                        "res_sample_before": [3.0, 4.0, 50.0, 1.0, -1.0], "res_line_before": [4.0, 3.0, 0.0, 0.0, 0.0],
                        "res_sample_after": [0.0, 0.0, 45.0, 3.0, -3.0], "res_line_after": [0.0, 0.0, 0.0, 4.0, 4.0]})
    rep = accuracy_by_role(tab, ground_m_per_px=2.0)
    assert rep["control"]["n_outliers"] == 1 and rep["control"]["before"]["n"] == 2
    assert rep["control"]["before"]["planar"]["rms"] == pytest.approx(5.0)
    assert rep["check"]["after"]["planar"]["rms"] == pytest.approx(5.0)
    assert rep["check"]["after"]["ce90_m"] == pytest.approx(10.0)
    assert rep["check"]["after"]["sample"] == {"mean": 0.0, "rms": 3.0, "std": 3.0, "max": 3.0}
    assert rep["control"]["after"]["line"]["max"] == 0.0


class _Grid:
    """A sensor of 10,000 px per degree on both axes at the equator (line down = south): 1 px = 11.132 m."""

    height_range = (0.0, 100.0)

    def project(self, lon, lat, h):
        return np.asarray(lon, float) * 1e4, -np.asarray(lat, float) * 1e4


class _GridWithJacobian(_Grid):
    def project_jacobian(self, lon, lat, h):
        jac = np.zeros(np.shape(lon) + (2, 3))
        jac[..., 0, 0], jac[..., 1, 1] = 1e4, -1e4
        return jac


@pytest.mark.parametrize("model", [_Grid(), _GridWithJacobian()])
def test_accuracy_by_role_takes_residuals_to_the_ground_through_the_model(model):
    """The one accuracy_by_role (compensation re-exports it): ``rpc=`` gives ce90_m through the model's ground
    Jacobian (analytic or central differences). At the equator 1e-4 deg of longitude is 11.132 m (WGS84 a)."""
    import pandas as pd
    from gdal_gf4cal import compensation
    from gdal_gf4cal.stats import accuracy_by_role
    assert compensation.accuracy_by_role is accuracy_by_role
    n = 10
    tab = pd.DataFrame({"role": ["check"] * n, "outlier": [False] * n, "lon": np.linspace(0, 1e-3, n),
                        "lat": np.zeros(n), "h": np.zeros(n), "res_sample_before": np.full(n, 3.0),
                        "res_line_before": np.full(n, -4.0), "res_sample_after": np.full(n, 1.0),
                        "res_line_after": np.zeros(n)})
    rep = accuracy_by_role(tab, model, roles=("check",))["check"]
    m_per_px = 2 * np.pi * 6378137.0 / 360.0 * 1e-4
    assert rep["after"]["ce90_m"] == pytest.approx(m_per_px, rel=1e-6)
    north_m_per_px = 6378137.0 * (1 - 0.00669437999014) * np.pi / 180.0 * 1e-4  # meridian radius a (1 - e^2)
    assert rep["before"]["ce90_m"] == pytest.approx(np.hypot(3 * m_per_px, 4 * north_m_per_px), rel=1e-6)


def test_one_geodesy_helper_gives_the_wgs84_radii():
    """Issue 10: one set of ellipsoid radii (gdal_gf4cal.geodesy), used by compensation and intersection."""
    from gdal_gf4cal import geodesy
    from gdal_gf4cal.simulate import geodesy as sim_geodesy
    rn, rm = geodesy.radii_of_curvature([0.0, 90.0])
    # equator: N = a, M = a (1 - e^2) = b^2 / a; pole: N = M = a^2 / b
    np.testing.assert_allclose(rn, [6378137.0, 6378137.0 ** 2 / 6356752.314245], rtol=1e-12)
    np.testing.assert_allclose(rm, [6356752.314245 ** 2 / 6378137.0, 6378137.0 ** 2 / 6356752.314245], rtol=1e-12)
    mx, my = geodesy.metres_per_degree(0.0, 0.0)
    assert mx == pytest.approx(111319.4908, abs=1e-3) and my == pytest.approx(np.radians(1.0) * 6356752.314245 ** 2 / 6378137.0, abs=1e-4)
    assert sim_geodesy.WGS84_A is geodesy.WGS84_A and sim_geodesy.WGS84_E2 is geodesy.WGS84_E2


def test_grouped_trimmed_mean_matches_a_loop_and_trims_blunders():
    from gdal_gf4cal.stats import grouped_trimmed_mean
    rng = np.random.default_rng(3)
    g = rng.integers(0, 5, 300)
    g[g == 4] = 3  # group 4 empty
    v = np.column_stack([g + 0.1 * rng.standard_normal(300), -g + 0.1 * rng.standard_normal(300)])
    v[:6, 0] += 50.0  # blunders on one axis: the whole observation goes
    r = grouped_trimmed_mean(g, v, 5, k=3.0, sigma=np.full(300, 0.1))
    for k in range(4):
        x = v[g == k]
        med = np.median(x, axis=0)
        mad = np.median(np.abs(x - med), axis=0)
        keep = np.all(np.abs(x - med) <= 3 * 1.4826 * mad + 1e-12, axis=1)
        np.testing.assert_allclose(r.median[k], med)
        assert r.n[k] == keep.sum()
        np.testing.assert_allclose(r.mean[k], x[keep].mean(axis=0))
        se = np.maximum(x[keep].std(axis=0, ddof=1), 0.1) / np.sqrt(keep.sum())
        np.testing.assert_allclose(r.sigma[k], se)
    assert np.all(np.abs(r.mean[:4, 0] - np.arange(4)) < 0.05)
    assert r.n[4] == 0 and np.isnan(r.mean[4]).all() and np.isnan(r.sigma[4]).all()
