"""Multi-image forward intersection (METHODS §7) on a real Pleiades stereo pair."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from gdal_gf4cal import DegenerateGeometryError, RPCModel
from gdal_gf4cal.cli import main
from gdal_gf4cal.compensation import CompensatedRPC, CompensationResult, fit_compensation
from gdal_gf4cal.intersection import ground_errors_m, intersect, intersection_accuracy

DATA = Path(__file__).parents[1] / "data" / "compensation"
LEFT = DATA / "RPC_P1BP--2017092838284574CP.XML"
RIGHT = DATA / "RPC_P1BP--2017092838319324CP.XML"


@pytest.fixture(scope="module")
def pair():
    return RPCModel.from_file(LEFT), RPCModel.from_file(RIGHT)


def ground_points(rpc, n, rng):
    w, h = rpc.image_size
    s, l = rng.uniform(0.1 * w, 0.9 * w, n), rng.uniform(0.1 * h, 0.9 * h, n)
    hh = rng.uniform(50, 800, n)
    lon, lat = rpc.localize(s, l, hh)
    return lon, lat, hh


def test_matches_independent_otb_triangulation(pair):
    """shareloc's reference tie point, triangulated by OTB (tests/data/compensation/PROVENANCE.txt)."""
    pts = np.array([[[10121.0657280 + 0.5, 10235.9310147 + 0.5]], [[10472.6832936 + 0.5, 10018.9917330 + 0.5]]])
    res = intersect(pair, pts)
    e, n, u = ground_errors_m(res.lon, res.lat, res.h, 7.116048414457637, 43.68329032442379, 106.06528306)
    # The two measurements disagree by ~1 px (0.5 m); OTB meets the rays in object space, we minimise image
    # residuals: both agree within the measurement noise.
    assert np.hypot(e, n)[0] < 0.5 and abs(u[0]) < 1.0
    assert res.n_images[0] == 2 and np.isfinite(res.sigma0[0])


def test_noise_free_is_exact_and_noisy_errors_follow_covariance(pair):
    rng = np.random.default_rng(0)
    lon, lat, h = ground_points(pair[0], 300, rng)
    pts = np.stack([np.column_stack(m.project(lon, lat, h)) for m in pair])
    res = intersect(pair, pts)
    e, n, u = ground_errors_m(res.lon, res.lat, res.h, lon, lat, h)
    assert np.max(np.abs(np.concatenate([e, n, u]))) < 1e-4
    sigma = 0.5
    noisy = pts + rng.normal(0, sigma, pts.shape)
    res = intersect(pair, noisy, sigma_px=sigma)
    err = np.stack(ground_errors_m(res.lon, res.lat, res.h, lon, lat, h), axis=-1)
    # Mahalanobis distances with the predicted covariance: chi-square with 3 degrees of freedom.
    d2 = np.einsum("ni,nij,nj->n", err, np.linalg.inv(res.cov_enu_m2), err)
    assert 2.6 < d2.mean() < 3.4
    acc = intersection_accuracy(res, lon, lat, h)
    assert acc["n"] == 300
    assert acc["height_rms_m"] == pytest.approx(np.sqrt(np.mean(res.sigma_height_m ** 2)), rel=0.15)
    assert acc["planar_rms_m"] == pytest.approx(np.sqrt(np.mean(res.sigma_planar_m ** 2)), rel=0.15)
    assert acc["height_rms_m"] > acc["planar_rms_m"]     # base-to-height < 1: height is the weak axis


def test_unobserved_points_and_single_image(pair):
    rng = np.random.default_rng(1)
    lon, lat, h = ground_points(pair[0], 4, rng)
    pts = np.stack([np.column_stack(m.project(lon, lat, h)) for m in pair])
    pts[1, 2] = np.nan
    res = intersect(pair, pts)
    assert np.isnan(res.lon[2]) and np.isfinite(res.lon[[0, 1, 3]]).all()
    assert list(res.n_images) == [2, 2, 1, 2]
    with pytest.raises(DegenerateGeometryError):
        intersect(pair[:1], pts[:1])


def test_compensated_models_remove_bias(pair):
    """Both RPCs biased by a few pixels; compensation with GCPs brings intersection errors to the noise level."""
    rng = np.random.default_rng(2)
    bias = [(5.0, -3.0), (-4.0, 6.0)]
    truth = []
    for m, (bs, bl) in zip(pair, bias):
        fr = (m.samp_off + 0.5, m.samp_scale, m.line_off + 0.5, m.line_scale)
        truth.append(CompensatedRPC(m, CompensationResult.from_coefficients("translation", fr, [bs], [bl])))
    lon, lat, h = ground_points(pair[0], 60, rng)
    meas = np.stack([np.column_stack(t.project(lon, lat, h)) for t in truth]) + rng.normal(0, 0.3, (2, 60, 2))
    ctrl, chk = slice(0, 10), slice(10, 60)
    raw = intersection_accuracy(intersect(pair, meas[:, chk]), lon[chk], lat[chk], h[chk])
    comp = []
    for k, m in enumerate(pair):
        g = pd.DataFrame({"lon": lon[ctrl], "lat": lat[ctrl], "h": h[ctrl], "sample": meas[k, ctrl, 0],
                          "line": meas[k, ctrl, 1]})
        comp.append(CompensatedRPC(m, fit_compensation(m, g, "translation")))
    fixed = intersection_accuracy(intersect(comp, meas[:, chk]), lon[chk], lat[chk], h[chk])
    assert raw["planar_rms_m"] > 2.0
    assert fixed["planar_rms_m"] < 0.15 * raw["planar_rms_m"]
    assert fixed["height_rms_m"] < 0.5 * raw["height_rms_m"] + 0.5


def test_cli_intersect_wide_and_long_csv(pair, tmp_path, capsys):
    rng = np.random.default_rng(3)
    lon, lat, h = ground_points(pair[0], 5, rng)
    (s1, l1), (s2, l2) = (m.project(lon, lat, h) for m in pair)
    wide = tmp_path / "ties.csv"
    pd.DataFrame({"id": list("abcde"), "sample_1": s1, "line_1": l1, "sample_2": s2, "line_2": l2, "lon": lon,
                  "lat": lat, "h": h}).to_csv(wide, index=False)
    out, rep = tmp_path / "pts.gpkg", tmp_path / "rep.json"
    assert main(["intersect", "--rpc", str(LEFT), str(RIGHT), "--points", str(wide), "--out", str(out),
                 "--report", str(rep)]) == 0
    r = json.loads(rep.read_text())
    assert r["n_intersected"] == 5 and r["accuracy"]["planar_rms_m"] < 1e-3
    import geopandas as gpd
    back = gpd.read_file(out)
    assert np.allclose(back["h"], h, atol=1e-3)
    long = tmp_path / "long.csv"
    rows = [(i, LEFT.name, a, b) for i, a, b in zip("abcde", s1, l1)] + [(i, "2", a, b) for i, a, b in
                                                                        zip("abcde", s2, l2)]
    pd.DataFrame(rows, columns=["id", "image", "sample", "line"]).to_csv(long, index=False)
    capsys.readouterr()
    assert main(["intersect", "--rpc", str(LEFT), str(RIGHT), "--points", str(long)]) == 0
    text = capsys.readouterr().out
    assert "5 of 5 points intersected" in text and text.count("\n") >= 8
    assert main(["intersect", "--rpc", str(LEFT), "--points", str(long)]) == 2
    assert "at least 2" in capsys.readouterr().err


def test_estimate_view_of_a_point(pair):
    """Issue 10: IntersectionResult.estimate(i) is the one result class; covariance and sigma0 unchanged."""
    from gdal_gf4cal.estimation import Estimate
    rng = np.random.default_rng(3)
    lon, lat, h = ground_points(pair[0], 50, rng)
    sigma = 0.5
    pts = np.stack([np.column_stack(m.project(lon, lat, h)) for m in pair]) + rng.normal(0, sigma, (2, 50, 2))
    res = intersect(pair, pts, sigma_px=sigma)
    est = res.estimate(7)
    assert isinstance(est, Estimate) and est.names == ["east_m", "north_m", "up_m"]
    np.testing.assert_array_equal(est.cov, res.cov_enu_m2[7])
    assert est.sigma0 == res.sigma0[7] and est.dof == 1
    np.testing.assert_array_equal(est.residuals, res.residuals[:, 7].ravel())
    np.testing.assert_allclose(est.weights, 1.0 / sigma ** 2)
    # 4 observations, 3 unknowns: the redundancy numbers add up to 1 for every point
    np.testing.assert_allclose(res.redundancy.sum(axis=(0, 2)), 1.0, atol=1e-9)
    # one redundant observation: every normalised residual has the same magnitude, 1 (w-test with dof 1)
    np.testing.assert_allclose(np.abs(est.normalised), 1.0, rtol=1e-6)


def test_without_final_pass_same_points_and_last_step_covariance(pair):
    """``final_pass=False`` (the bundle's start): the same solution, the covariance of each point's last step
    (within ``tol_m`` of the solution, so equal to a few parts per million), residuals not computed."""
    rng = np.random.default_rng(5)
    lon, lat, h = ground_points(pair[0], 200, rng)
    pts = np.stack([np.column_stack(m.project(lon, lat, h)) for m in pair]) + rng.normal(0, 0.5, (2, 200, 2))
    pts[1, 3] = np.nan                                         # one point seen once: not intersected either way
    full = intersect(pair, pts, sigma_px=0.5)
    fast = intersect(pair, pts, sigma_px=0.5, final_pass=False)
    np.testing.assert_array_equal(fast.converged, full.converged)
    assert not fast.converged[3] and np.isnan(fast.cov_enu_m2[3]).all()
    ok = full.converged
    np.testing.assert_array_equal(np.stack([fast.lon, fast.lat, fast.h])[:, ok],
                                  np.stack([full.lon, full.lat, full.h])[:, ok])
    np.testing.assert_allclose(fast.cov_enu_m2[ok], full.cov_enu_m2[ok], rtol=1e-4)
    assert 0.5 < np.median(fast.sigma_height_m[ok]) < 2.0               # ~1 m for 0.5 px on this pair
    assert np.isnan(fast.residuals).all() and np.isnan(fast.sigma0).all()
