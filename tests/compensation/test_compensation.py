"""Bias compensation (METHODS §4): models, robust estimation, exact folding, refitting, writing.

Truth is always known: a real RPC (tests/data/compensation) composed with a chosen image-space error is the true
sensor; GCPs are localised through it and measured with seeded Gaussian noise.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from gcpsim import gcps_from_truth
from gdal_gf4cal import DegenerateGeometryError, GCPError, InputOverwriteError, RPCModel
from gdal_gf4cal.compensation import (CompensatedRPC, CompensationModel, CompensationResult, apply_compensation,
                                      fit_compensation)
from gdal_gf4cal.workflows import write_refined_rpc

DATA = Path(__file__).parents[1] / "data" / "compensation"


@pytest.fixture(scope="module")
def wv3():
    return RPCModel.from_file(DATA / "md_dg.RPB")


@pytest.fixture(scope="module")
def ikonos():
    return RPCModel.from_file(DATA / "rpc_IKONOS.txt")


def frame_of(rpc):
    return (rpc.samp_off + 0.5, rpc.samp_scale, rpc.line_off + 0.5, rpc.line_scale)


# True image-space errors (px) for each model, in the normalised frame u, v of the RPC.
TRUE = {
    "translation": ("translation", None, [4.3], [-2.7]),
    "shift-drift": ("shift-drift", None, [4.3, 1.8], [-2.7, -1.2]),
    "affine": ("affine", None, [4.3, 1.8, -0.9], [-2.7, 0.6, -1.2]),
    "poly2": ("poly2", None, [4.3, 1.8, -0.9, 0.8, -0.6, 0.4], [-2.7, 0.6, -1.2, -0.5, 0.7, 0.3]),
    "detector-poly": ("detector-poly", 3, [4.3, 6.0, -3.0, 5.0], [-2.7]),
}


def true_model(rpc, key):
    name, order, cs, cl = TRUE[key]
    model = CompensationModel.from_name(name, order=order)
    return CompensatedRPC(rpc, CompensationResult.from_coefficients(model, frame_of(rpc), cs, cl))


def simulate_gcps(truth, rpc, n, sigma, rng, n_control):
    """GCPs spread over the image: ground by localising random image points through the truth (conftest)."""
    table, _ = gcps_from_truth(truth, n, size=rpc.image_size, heights=rpc.height_range, sigma_px=sigma, seed=rng,
                               n_control=n_control, with_sigma=False)
    return table


def dense_grid(rpc, truth, n=25):
    w, h = rpc.image_size
    s, l = np.meshgrid(np.linspace(0, w, n), np.linspace(0, h, n))
    hs = [rpc.height_range[0], rpc.height_off, rpc.height_range[1]]
    S = np.concatenate([s.ravel()] * 3)
    L = np.concatenate([l.ravel()] * 3)
    Hh = np.repeat(hs, s.size)
    lon, lat = truth.localize(S, L, Hh)
    return lon, lat, Hh, S, L


# ---------------------------------------------------------------------------------------------- model specs
def test_model_names_minimum_gcps_and_folding():
    expect = {"translation": (1, 2, True), "shift-drift": (2, 4, True), "affine": (3, 6, False),
              "poly2": (6, 12, False)}
    for name, (min_gcps, n_params, foldable) in expect.items():
        m = CompensationModel.from_name(name)
        assert (m.min_gcps, m.n_params, m.foldable) == (min_gcps, n_params, foldable)
    for order in range(1, 7):
        m = CompensationModel.from_name("detector-poly", order=order)
        assert m.min_gcps == order + 1 and m.n_params == order + 2
        assert m.foldable == (order == 1)   # order 1 = shift + scale along the CCD: exact
    combined = CompensationModel.from_name("detector-poly", order=3, along="affine")
    assert combined.terms[1] == ((0, 0), (1, 0), (0, 1))          # along-track terms of the affine model
    assert set(combined.terms[0]) == {(0, 0), (1, 0), (0, 1), (2, 0), (3, 0)}
    with pytest.raises(GCPError, match="unknown compensation model"):
        CompensationModel.from_name("helmert")
    with pytest.raises(GCPError, match="order"):
        CompensationModel.from_name("detector-poly", order=7)
    with pytest.raises(GCPError, match="order"):
        CompensationModel.from_name("detector-poly")
    with pytest.raises(GCPError, match="only to model 'detector-poly'"):
        CompensationModel.from_name("affine", order=3)


def test_too_few_or_degenerate_gcps_are_clear_errors(wv3):
    rng = np.random.default_rng(1)
    truth = true_model(wv3, "affine")
    gcps = simulate_gcps(truth, wv3, 10, 0.3, rng, 10)
    with pytest.raises(GCPError, match="at least 3 control"):
        fit_compensation(wv3, gcps.iloc[:2], "affine")
    with pytest.raises(GCPError, match="at least 6 control"):
        fit_compensation(wv3, gcps.iloc[:5], "poly2")
    # Collinear GCPs: image points on one diagonal -> affine undetermined.
    t = np.linspace(100, 1500, 6)
    lon, lat = truth.localize(t, t * 0.8, np.full(6, 95.0))
    coll = pd.DataFrame({"lon": lon, "lat": lat, "h": 95.0, "sample": t, "line": t * 0.8})
    with pytest.raises(DegenerateGeometryError, match="collinear"):
        fit_compensation(wv3, coll, "affine")
    # ... while the translation model is fine with them.
    fit_compensation(wv3, coll, "translation")
    # All GCPs on one image line: the line drift of shift-drift is undetermined.
    lon, lat = true_model(wv3, "translation").localize(t, np.full(6, 800.0), np.full(6, 95.0))
    row = pd.DataFrame({"lon": lon, "lat": lat, "h": 95.0, "sample": t, "line": 800.0})
    with pytest.raises(DegenerateGeometryError):
        fit_compensation(wv3, row, "shift-drift")
    # Spread over only ~1 px in line: determined in theory, noise amplified > 1000x at the corners.
    lon, lat = true_model(wv3, "translation").localize(t, 800.0 + np.linspace(0, 1, 6), np.full(6, 95.0))
    with pytest.raises(DegenerateGeometryError):
        fit_compensation(wv3, row.assign(lon=lon, lat=lat), "shift-drift")
    with pytest.raises(GCPError, match="no height"):
        fit_compensation(wv3, coll.assign(h=np.nan), "translation")


# ---------------------------------------------------------------------------------------------- accuracy vs truth
def test_translation_with_one_gcp_removes_a_pure_shift(ikonos):
    truth = true_model(ikonos, "translation")
    rng = np.random.default_rng(2)
    gcps = simulate_gcps(truth, ikonos, 1, 0.0, rng, 1)
    res = fit_compensation(ikonos, gcps, "translation")
    assert res.coef_sample == pytest.approx([4.3], abs=1e-6) and res.coef_line == pytest.approx([-2.7], abs=1e-6)
    applied = apply_compensation(ikonos, res)
    assert applied.exact
    lon, lat, h, s, l = dense_grid(ikonos, truth)
    ps, pl = applied.rpc.project(lon, lat, h)
    assert np.max(np.abs(ps - s)) < 1e-6 and np.max(np.abs(pl - l)) < 1e-6
    # The input model is untouched.
    ps0, _ = ikonos.project(lon, lat, h)
    assert np.max(np.abs(ps0 - s)) > 4.0


@pytest.mark.parametrize("key", list(TRUE))
def test_matching_model_reaches_noise_and_noise_floor(wv3, key):
    """Check RMS <= 1.15 sigma; corrected model within 1.5x the noise-propagation floor everywhere."""
    sigma, n_ctrl, n_check, n_rep = 0.5, 40, 400, 60
    truth = true_model(wv3, key)
    name, order, *_ = TRUE[key]
    lon, lat, h, S, L = dense_grid(wv3, truth)
    sp, lp = wv3.project(lon, lat, h)
    rng = np.random.default_rng(10)
    sq_err = np.zeros((2, S.size))
    sq_floor = np.zeros((2, S.size))
    check_rms = []
    for rep in range(n_rep):
        gcps = simulate_gcps(truth, wv3, n_ctrl + n_check, sigma, rng, n_ctrl)
        res = fit_compensation(wv3, gcps, name, order=order)
        acc = res.accuracy()["check"]["after"]
        check_rms.append((acc["sample"]["rms"], acc["line"]["rms"]))
        ds, dl = res.correction(sp, lp)
        sq_err += np.stack([(sp + ds - S) ** 2, (lp + dl - L) ** 2])
        # Floor from the true sigma: sigma * sqrt(a^T N^-1 a) at every grid point, for this GCP layout.
        fs, fl = res.correction_std(sp, lp)
        sq_floor += np.stack([(fs / res.sigma0_px[0] * sigma) ** 2, (fl / res.sigma0_px[1] * sigma) ** 2])
    check_rms = np.array(check_rms)
    assert np.all(check_rms.mean(axis=0) <= 1.15 * sigma), check_rms.mean(axis=0)
    rms_err = np.sqrt(sq_err / n_rep)
    floor_s, floor_l = np.sqrt(sq_floor / n_rep)
    assert np.all(rms_err[0] <= 1.5 * floor_s), np.max(rms_err[0] / floor_s)
    assert np.all(rms_err[1] <= 1.5 * floor_l), np.max(rms_err[1] / floor_l)
    # A wrong (too simple) model is clearly worse than the floor: the test can fail.
    if key in ("poly2", "detector-poly"):
        res_t = fit_compensation(wv3, gcps, "translation", robust=False)
        acc_t = res_t.accuracy()["check"]["after"]
        assert max(acc_t["sample"]["rms"], acc_t["line"]["rms"]) > 1.5 * sigma


@pytest.mark.parametrize("key", ["affine", "poly2", "detector-poly"])
def test_refit_error_and_refined_rpc_against_truth(wv3, key):
    sigma = 0.5
    truth = true_model(wv3, key)
    name, order, *_ = TRUE[key]
    rng = np.random.default_rng(3)
    gcps = simulate_gcps(truth, wv3, 60, sigma, rng, 60)
    res = fit_compensation(wv3, gcps, name, order=order)
    applied = apply_compensation(wv3, res)
    assert not applied.exact
    assert applied.refit_max_px <= 0.01
    lon, lat, h, S, L = dense_grid(wv3, truth)
    ps, pl = applied.rpc.project(lon, lat, h)
    cs, cl = CompensatedRPC(wv3, res).project(lon, lat, h)
    # Independent check of the refit on our own dense grid (3 heights incl. the range ends).
    assert np.max(np.hypot(ps - cs, pl - cl)) <= 0.01
    # Refined RPC vs truth: bounded by a generous simultaneous band of the noise floor (chi2 99.9 %, p params).
    fs, fl = res.correction_std(*wv3.project(lon, lat, h))
    k = np.sqrt(np.quantile(np.random.default_rng(0).chisquare(len(res.coef_sample), 200000), 0.999))
    assert np.all(np.abs(ps - S) <= 1.5 * k * fs + 0.01)
    assert np.all(np.abs(pl - L) <= 1.5 * k * fl + 0.01)


def test_shift_and_scale_fold_exactly(wv3):
    truth = true_model(wv3, "shift-drift")
    res = truth.result
    folded = apply_compensation(wv3, res)
    assert folded.exact and folded.refit_max_px == 0.0
    lon, lat, h, S, L = dense_grid(wv3, truth)
    ps, pl = folded.rpc.project(lon, lat, h)
    assert np.max(np.abs(ps - S)) < 1e-7 and np.max(np.abs(pl - L)) < 1e-7
    # The same correction expressed in another normalisation frame (origin at pixel 0, not at the RPC's offsets)
    # folds to the same RPC: the frame origin and the half pixel are accounted for exactly.
    s0, ss, l0, ls = res.frame
    a0, a1 = res.coef_sample
    b0, b1 = res.coef_line
    other = CompensationResult.from_coefficients("shift-drift", (0.0, 1000.0, 0.0, 500.0),
                                                 [a0 - a1 * s0 / ss, a1 * 1000.0 / ss],
                                                 [b0 - b1 * l0 / ls, b1 * 500.0 / ls])
    assert np.allclose(other.correction(S, L), res.correction(S, L), atol=1e-9)
    refolded = apply_compensation(wv3, other).rpc
    ps2, pl2 = refolded.project(lon, lat, h)
    assert np.max(np.abs(ps2 - S)) < 1e-7 and np.max(np.abs(pl2 - L)) < 1e-7


# ---------------------------------------------------------------------------------------------- blunders
def test_blunders_flagged_and_check_rms_far_below_uncorrected(ikonos):
    """Real IKONOS RPC with a known affine perturbation; GCPs derived from it, with blunders."""
    truth = true_model(ikonos, "affine")
    rng = np.random.default_rng(4)
    gcps = simulate_gcps(truth, ikonos, 150, 0.4, rng, 40)
    blunders = {"g3": (25.0, 0.0), "g11": (0.0, -12.0), "g27": (9.0, 9.0), "g90": (-30.0, 5.0)}
    for gid, (ds, dl) in blunders.items():
        gcps.loc[gcps.id == gid, "sample"] += ds
        gcps.loc[gcps.id == gid, "line"] += dl
    res = fit_compensation(ikonos, gcps, "affine")
    flagged = set(res.outliers["id"])
    assert flagged == set(blunders), flagged
    norm = res.outliers.set_index("id")[["norm_res_sample", "norm_res_line"]].abs().max(axis=1)
    assert (norm > 4.0).all()
    # The estimate is unaffected: coefficients within 4 sigma of the truth.
    true_cs, true_cl = truth.result.coef_sample, truth.result.coef_line
    assert np.all(np.abs(res.coef_sample - true_cs) < 4 * np.sqrt(np.diag(res.cov_sample)))
    assert np.all(np.abs(res.coef_line - true_cl) < 4 * np.sqrt(np.diag(res.cov_line)))
    acc = res.accuracy(ikonos)["check"]
    before = np.hypot(acc["before"]["sample"]["rms"], acc["before"]["line"]["rms"])
    after = np.hypot(acc["after"]["sample"]["rms"], acc["after"]["line"]["rms"])
    assert after < 0.15 * before and after < 0.8
    assert acc["after"]["ce90_m"] < acc["before"]["ce90_m"] / 5
    d = res.to_dict(ikonos)
    assert {o["id"] for o in d["outliers"]} == set(blunders)
    # Plain least squares is dragged by the blunders.
    plain = fit_compensation(ikonos, gcps, "affine", robust=False)
    acc_p = plain.accuracy()["check"]["after"]
    assert np.hypot(acc_p["sample"]["rms"], acc_p["line"]["rms"]) > 1.3 * after


def test_pure_noise_flags_nothing(wv3):
    truth = true_model(wv3, "affine")
    gcps = simulate_gcps(truth, wv3, 200, 0.5, np.random.default_rng(5), 100)
    res = fit_compensation(wv3, gcps, "affine")
    assert not res.gcps["outlier"].any()
    assert res.sigma0_px[0] == pytest.approx(0.5, rel=0.2) and res.sigma0_px[1] == pytest.approx(0.5, rel=0.2)


def test_leave_one_out_matches_explicit_refits(wv3):
    from gdal_gf4cal.gcp_formats import leave_one_out_splits
    truth = true_model(wv3, "affine")
    gcps = simulate_gcps(truth, wv3, 12, 0.5, np.random.default_rng(6), 12)
    res = fit_compensation(wv3, gcps, "affine", robust=False, leave_one_out=True)
    loo = res.gcps.set_index("id")
    for gid, table in leave_one_out_splits(gcps):
        one = fit_compensation(wv3, table, "affine", robust=False).gcps.set_index("id")
        assert one.loc[gid, "role"] == "check"
        assert one.loc[gid, "res_sample_after"] == pytest.approx(loo.loc[gid, "res_sample_loo"], abs=1e-8)
        assert one.loc[gid, "res_line_after"] == pytest.approx(loo.loc[gid, "res_line_loo"], abs=1e-8)


def test_correction_inverse_and_jacobian(wv3):
    truth = true_model(wv3, "poly2")
    res = truth.result
    s = np.array([10.0, 900.0, 1900.0])
    l = np.array([1700.0, 20.0, 800.0])
    ds, dl = res.correction(s, l)
    sp, lp = res.invert_correction(s + ds, l + dl)
    assert np.allclose(sp, s, atol=1e-8) and np.allclose(lp, l, atol=1e-8)
    J = res.correction_jacobian(s, l)
    e = 1e-3
    num_s = (np.array(res.correction(s + e, l)) - np.array(res.correction(s - e, l))) / (2 * e)
    assert np.allclose(J[:, 0, 0], num_s[0], atol=1e-7) and np.allclose(J[:, 1, 0], num_s[1], atol=1e-7)
    # CompensatedRPC Jacobian agrees with finite differences of its projection.
    lon, lat = truth.localize(s, l, np.full(3, 95.0))
    Jc = truth.project_jacobian(lon, lat, 95.0)
    d = 1e-7
    a = np.array(truth.project(lon + d, lat, 95.0))
    b = np.array(truth.project(lon - d, lat, 95.0))
    assert np.allclose(Jc[:, :, 0], ((a - b) / (2 * d)).T, rtol=1e-5)


# ---------------------------------------------------------------------------------------------- writing
def test_written_sidecars_read_back_and_never_overwrite_input(tmp_path, wv3):
    truth = true_model(wv3, "affine")
    gcps = simulate_gcps(truth, wv3, 30, 0.3, np.random.default_rng(7), 30)
    applied = apply_compensation(wv3, fit_compensation(wv3, gcps, "affine"))
    lon, lat, h, S, L = dense_grid(wv3, truth, n=9)
    for name in ("refined.RPB", "refined_RPC.TXT"):
        out = write_refined_rpc(applied.rpc, tmp_path / name, inputs=[str(DATA / "md_dg.RPB")])
        back = RPCModel.from_file(out)
        a, b = back.project(lon, lat, h), applied.rpc.project(lon, lat, h)
        assert np.max(np.abs(np.array(a) - np.array(b))) < 1e-9
        with pytest.raises(InputOverwriteError):
            write_refined_rpc(applied.rpc, out)
    src = tmp_path / "in.RPB"
    src.write_bytes((DATA / "md_dg.RPB").read_bytes())
    before = src.read_bytes()
    with pytest.raises(InputOverwriteError):
        write_refined_rpc(applied.rpc, src, inputs=[str(src)], overwrite=True)
    assert src.read_bytes() == before
    with pytest.raises(GCPError, match="needs an image"):
        write_refined_rpc(applied.rpc, tmp_path / "x.vrt")
    with pytest.raises(GCPError, match=r"\.RPB, _RPC\.TXT or \.vrt"):
        write_refined_rpc(applied.rpc, tmp_path / "x.tif")
    assert not os.path.exists(tmp_path / "x.vrt")


def test_many_blunders_do_not_mask_each_other(ikonos):
    """A quarter of the control points are blunders of 5-30 px: all found, none invented."""
    truth = true_model(ikonos, "poly2")
    rng = np.random.default_rng(8)
    gcps = simulate_gcps(truth, ikonos, 100, 0.5, rng, 60)
    idx = rng.choice(60, 15, replace=False)
    ang, mag = rng.uniform(0, 2 * np.pi, 15), rng.uniform(5, 30, 15)
    gcps.loc[idx, "sample"] += mag * np.cos(ang)
    gcps.loc[idx, "line"] += mag * np.sin(ang)
    res = fit_compensation(ikonos, gcps, "poly2")
    assert set(res.outliers["id"]) == set(gcps["id"][idx])
    acc = res.accuracy()["check"]["after"]
    assert acc["sample"]["rms"] < 0.6 and acc["line"]["rms"] < 0.6


def test_detector_poly_along_the_line_axis(wv3):
    """A CCD along the image lines (ccd_axis='line'): the polynomial goes to the line axis."""
    model = CompensationModel.from_name("detector-poly", order=3, ccd_axis="line")
    assert model.terms == (((0, 0),), ((0, 0), (0, 1), (0, 2), (0, 3)))
    truth = CompensatedRPC(wv3, CompensationResult.from_coefficients(model, frame_of(wv3), [1.5],
                                                                      [-2.0, 3.0, 4.0, -6.0]))
    gcps = simulate_gcps(truth, wv3, 200, 0.3, np.random.default_rng(9), 50)
    res = fit_compensation(wv3, gcps, model)
    assert np.allclose(res.coef_line, [-2.0, 3.0, 4.0, -6.0], atol=0.4)
    acc = res.accuracy()["check"]["after"]
    assert acc["line"]["rms"] < 1.15 * 0.3 and acc["sample"]["rms"] < 1.15 * 0.3


def test_small_control_sets_do_not_flag_good_points(wv3):
    """Pure Gaussian noise, few control points: a 4-sigma blunder test must (almost) never fire.

    The residuals are normalised with a sigma estimated from a few redundant observations, so they are Student-t,
    not normal: a fixed threshold of 4 flagged 1-5 % of good points here.
    """
    rng = np.random.default_rng(11)
    flagged = n_pts = 0
    for key, sizes in (("translation", (4, 6)), ("shift-drift", (4, 6)), ("affine", (6, 8, 10))):
        truth = true_model(wv3, key)
        for n in sizes:
            for _ in range(15):
                gcps = simulate_gcps(truth, wv3, n, 0.5, rng, n)
                res = fit_compensation(wv3, gcps, key)
                flagged += int(res.gcps["outlier"].sum())
                n_pts += n
    assert flagged <= 1, f"{flagged} of {n_pts} good GCPs flagged as blunders"
    # A real blunder in a small set is still found.
    truth = true_model(wv3, "affine")
    gcps = simulate_gcps(truth, wv3, 10, 0.5, np.random.default_rng(12), 10)
    gcps.loc[4, "sample"] += 40.0
    assert list(fit_compensation(wv3, gcps, "affine").outliers["id"]) == ["g4"]


def test_output_table_keeps_the_input_class_columns_and_leaves_the_input_alone(wv3):
    """The output table (built in one go, issue 23): a GeoDataFrame stays one (its CRS and geometry), the input's
    columns keep their order and values, the new columns follow, the caller's table is unchanged."""
    gpd = pytest.importorskip("geopandas")
    truth = true_model(wv3, "affine")
    gcps = simulate_gcps(truth, wv3, 60, 0.5, np.random.default_rng(8), 60).drop(columns=["role"], errors="ignore")
    gcps.index = np.arange(len(gcps))[::-1] * 2                    # an index that is not 0..n-1
    geo = gpd.GeoDataFrame(gcps.copy(), geometry=gpd.points_from_xy(gcps.lon, gcps.lat), crs=4326)
    before = geo.copy()
    for table, cls in ((gcps, pd.DataFrame), (geo, gpd.GeoDataFrame)):
        out = fit_compensation(wv3, table, "affine").gcps
        assert type(out) is cls
        assert list(out.columns[:len(table.columns)]) == list(table.columns)
        assert {"role", "sigma", "res_sample_after", "outlier", "used"} <= set(out.columns)
        np.testing.assert_array_equal(out["sample"].to_numpy(), table["sample"].to_numpy())
        assert (out["role"] == "control").all() and list(out.index) == list(range(len(table)))
    assert out.crs == geo.crs and out.geometry.name == "geometry"
    pd.testing.assert_frame_equal(geo, before)
