"""Look-angle calibration from the RPC alone (METHODS §5, seed 000) against known truth.

The geometry is the real one: a camera in geostationary orbit (105.6°E) looking at Tibet (88.5°E, 32.5°N) through
the simulator's rigorous frame model, a 10240 x 10240 detector array, an RPC fitted from the *current* camera, GCPs
measured with the *true* camera (yaw of ~10 px at the edge, radial distortion of ~4 px, offsets, scale) plus noise.
"""
from __future__ import annotations

import numpy as np
import pytest

from gcpsim import gcps_from_truth
from gf4frame import HEIGHTS, K, W, dense_check, frame_model, make_cameras
from gdal_gf4cal.camera import LookAngleModel
from gdal_gf4cal.errors import CancelledError, DegenerateGeometryError, GCPError
from gdal_gf4cal.lookangle import (LookAngleConditionWarning, RecalibratedSensor, _Frame, calibrate_lookangle,
                                   compare_lookangle, layout_condition, lookangle_monomials, recalibrate_rpc)
from gdal_gf4cal.rpc_fit import fit_rpc_from_model


def make_gcps(true_model, n, sigma, seed, layout=None, blunder_fraction=0.0):
    """GCPs: ground points of uniformly spread true image points, measured with Gaussian noise (+ 10-50 px
    blunders): the shared simulator of conftest."""
    return gcps_from_truth(true_model, n, size=(W, W), heights=HEIGHTS, sigma_px=sigma, seed=seed, layout=layout,
                           blunder_fraction=blunder_fraction, blunder_px=(10, 50))


@pytest.fixture(scope="module")
def scene():
    cur, true = make_cameras()
    m_cur, m_true = frame_model(cur), frame_model(true)
    rpc, rep = fit_rpc_from_model(m_cur, height_range=HEIGHTS)
    assert rep.check.max_px < 0.01
    return {"current": cur, "true": true, "m_cur": m_cur, "m_true": m_true, "rpc": rpc}


# ------------------------------------------------------------------------------------------------ basis
def test_normalised_basis_converts_exactly():
    frame = _Frame(W / 2, W / 2, W / 2, W / 2)
    rng = np.random.default_rng(1)
    alpha_x, alpha_y = rng.normal(size=10) * 1e-3, rng.normal(size=10) * 1e-3
    cam = LookAngleModel(size=(W, W), x=frame.to_raw @ alpha_x, y=frame.to_raw @ alpha_y)
    s, l = rng.uniform(0, W, 200), rng.uniform(0, W, 200)
    tx, ty = cam.tan_angles(s, l)
    m = lookangle_monomials(*frame.uv(s, l))
    np.testing.assert_allclose(tx, m @ alpha_x, rtol=0, atol=1e-14)
    np.testing.assert_allclose(ty, m @ alpha_y, rtol=0, atol=1e-14)
    np.testing.assert_allclose(frame.to_norm @ frame.to_raw, np.eye(10), atol=1e-9)


def test_compare_lookangle_measures_a_known_shift_in_pixels():
    cur, _ = make_cameras()
    # b looks where a looks one detector further along s and half a detector back along l.
    from gdal_gf4cal.simulate.cameras import shift_coefficients
    b = LookAngleModel(size=cur.size, x=shift_coefficients(cur.x, 1.0, -0.5), y=shift_coefficients(cur.y, 1.0, -0.5))
    d = compare_lookangle(cur, b, grid_px=50)
    assert d["n"] == (W // 50 + 1) ** 2
    assert d["sample"]["mean"] == pytest.approx(-1.0, abs=2e-3)
    assert d["line"]["mean"] == pytest.approx(0.5, abs=2e-3)
    assert d["sample"]["max"] == pytest.approx(1.0, abs=5e-3)
    same = compare_lookangle(cur, cur)
    assert same["sample"]["max"] == 0.0 and same["line"]["max"] == 0.0


# ------------------------------------------------------------------------------------------------ calibration
def test_noise_free_recovers_the_true_camera(scene):
    gcps, _ = make_gcps(scene["m_true"], 60, 0.0, seed=2)
    res = calibrate_lookangle(scene["m_cur"], gcps, scene["current"])        # rigorous virtual points
    d = compare_lookangle(res.camera, scene["true"])
    assert max(d["sample"]["max"], d["line"]["max"]) < 1e-6
    assert res.iterations <= 3 and res.converged
    assert np.abs(res.residuals_after).max() < 1e-6
    before = compare_lookangle(scene["current"], scene["true"])
    assert before["sample"]["max"] > 10        # there was a real error to remove
    assert res.correction_px[0] > 10 and res.correction_px[-1] < 1e-3
    assert res.corrections.shape == (res.iterations, 20)


def test_rpc_based_equals_rigorous_and_reaches_the_noise_floor(scene):
    n, sigma = 300, 0.2
    gcps, _ = make_gcps(scene["m_true"], n, sigma, seed=3)
    res = calibrate_lookangle(scene["rpc"], gcps, scene["current"])
    rig = calibrate_lookangle(scene["m_cur"], gcps, scene["current"])
    # Paper Table 2: RPC-based vs rigorous calibration, <= 0.01 px max over a 50 px grid.
    d = compare_lookangle(res.camera, rig.camera, grid_px=50)
    assert max(d["sample"]["max"], d["line"]["max"]) <= 0.01
    assert res.iterations <= 5
    # Calibrated-scene residuals ~ the GCP noise (paper Table 3), sigma0 ~ 1 with correct sigmas.
    after = res.control_stats["after"]
    assert after["sample"]["rms"] <= 1.15 * sigma and after["line"]["rms"] <= 1.15 * sigma
    assert res.control_stats["before"]["sample"]["rms"] > 3.0
    assert 0.85 < res.sigma0 < 1.15
    # Recalibrated RPC against the true model on a dense check grid: only propagated noise remains.
    new_rpc, rep = recalibrate_rpc(scene["rpc"], scene["current"], res.camera)
    assert rep.check.max_px < 0.01
    lon, lat, h, S, L = dense_check(scene["m_true"])
    ps, pl = new_rpc.project(lon, lat, h)
    floor = sigma * np.sqrt(10.0 / n)
    rms_s, rms_l = np.sqrt(np.mean((ps - S) ** 2)), np.sqrt(np.mean((pl - L) ** 2))
    assert rms_s <= 1.5 * floor and rms_l <= 1.5 * floor
    assert np.hypot(rms_s, rms_l) <= 0.1
    ps0, pl0 = scene["rpc"].project(lon, lat, h)
    assert np.sqrt(np.mean((ps0 - S) ** 2)) > 3.0       # the old RPC was off by pixels


def test_residuals_after_are_the_reprojection_through_the_recalibrated_model(scene):
    gcps, _ = make_gcps(scene["m_true"], 80, 0.5, seed=4)
    res = calibrate_lookangle(scene["rpc"], gcps, scene["current"])
    # Re-project the ground points through the rigorous model with the new camera: same residuals (to the RPC fit).
    ps, pl = scene["m_cur"].with_camera(res.camera).project(gcps.lon, gcps.lat, gcps.h)
    np.testing.assert_allclose(res.gcps["res_sample_after"], gcps["sample"] - ps, atol=2e-3)
    np.testing.assert_allclose(res.gcps["res_line_after"], gcps["line"] - pl, atol=2e-3)
    sv, lv = scene["rpc"].project(gcps.lon, gcps.lat, gcps.h)
    np.testing.assert_allclose(res.gcps["res_sample_before"], gcps["sample"] - sv, atol=1e-9)


def test_blunders_are_flagged_and_the_accuracy_holds(scene):
    n, sigma = 300, 0.2
    gcps, blunder = make_gcps(scene["m_true"], n, sigma, seed=5, blunder_fraction=0.05)
    res = calibrate_lookangle(scene["rpc"], gcps, scene["current"])
    flagged = res.outliers
    assert np.all(flagged[blunder])                         # every blunder found
    assert np.count_nonzero(flagged & ~blunder) <= 2        # and almost no good point lost
    assert np.all(res.gcps.loc[blunder, "norm_residual"] > 4)
    assert np.all(res.gcps.loc[blunder, "weight"] == 0)
    assert res.iterations <= 5
    after = res.control_stats["after"]
    assert after["sample"]["rms"] <= 1.15 * sigma and after["line"]["rms"] <= 1.15 * sigma
    clean = calibrate_lookangle(scene["rpc"], gcps[~blunder], scene["current"])
    d = compare_lookangle(res.camera, clean.camera)
    assert max(d["sample"]["rms"], d["line"]["rms"]) < 0.01
    n_used = n - int(flagged.sum())
    lon, lat, h, S, L = dense_check(scene["m_true"], n=30)
    new_rpc, _ = recalibrate_rpc(scene["rpc"], scene["current"], res.camera)
    ps, pl = new_rpc.project(lon, lat, h)
    floor = sigma * np.sqrt(10.0 / n_used)
    assert np.sqrt(np.mean((ps - S) ** 2)) <= 1.5 * floor and np.sqrt(np.mean((pl - L) ** 2)) <= 1.5 * floor
    # Without the robust step the blunders spoil the camera by tenths of a pixel.
    plain = calibrate_lookangle(scene["rpc"], gcps, scene["current"], robust=False)
    bad = compare_lookangle(plain.camera, clean.camera)
    assert max(bad["sample"]["rms"], bad["line"]["rms"]) > 0.1
    assert not plain.outliers.any()


def test_covariance_matches_the_scatter_of_repeated_calibrations(scene):
    n, sigma, reps = 60, 0.5, 40
    gcps, _ = make_gcps(scene["m_true"], n, sigma, seed=6)
    truth_s, truth_l = gcps["truth_sample"].to_numpy(), gcps["truth_line"].to_numpy()
    rng = np.random.default_rng(7)
    coefs, covs = [], []
    for _ in range(reps):
        g = gcps.copy()
        g["sample"] = truth_s + rng.normal(0, sigma, n)
        g["line"] = truth_l + rng.normal(0, sigma, n)
        res = calibrate_lookangle(scene["m_cur"], g, scene["current"], robust=False)
        coefs.append(np.concatenate([res.camera.x, res.camera.y]))
        covs.append(res.covariance)
    coefs = np.array(coefs)
    # Compare in pixels at the array corner, where the cubic is least constrained: var of tan_x there.
    m = np.concatenate([LookAngleModel(size=(W, W), x=np.eye(10)[i], y=np.zeros(10)).tan_angles(W, W)[:1]
                        for i in range(10)])
    pred_std = np.sqrt(np.mean([m @ c[:10, :10] @ m for c in covs])) / K
    emp_std = np.std(coefs[:, :10] @ m, ddof=1) / K
    assert emp_std == pytest.approx(pred_std, rel=0.3)
    assert pred_std > 0.3        # the corner really is uncertain with 60 GCPs (a meaningful comparison)


def test_weights_replace_the_sigma_column(scene):
    gcps, _ = make_gcps(scene["m_true"], 120, 0.3, seed=15)
    by_sigma = calibrate_lookangle(scene["rpc"], gcps, scene["current"], robust=False)
    w = np.full(len(gcps), 1 / 0.3 ** 2)
    by_weights = calibrate_lookangle(scene["rpc"], gcps.drop(columns=["sigma"]), scene["current"], weights=w,
                                     robust=False)
    np.testing.assert_allclose(by_weights.camera.x, by_sigma.camera.x, rtol=1e-9, atol=1e-15)
    # Down-weighting one axis of half the points changes the estimate, zero weight removes them.
    w2 = np.column_stack([w, w])
    w2[::2] = 0.0
    half = calibrate_lookangle(scene["rpc"], gcps, scene["current"], weights=w2, robust=False)
    only = calibrate_lookangle(scene["rpc"], gcps.iloc[1::2], scene["current"], robust=False)
    np.testing.assert_allclose(half.camera.x, only.camera.x, rtol=1e-9, atol=1e-15)


def test_check_points_are_evaluated_not_used(scene):
    gcps, _ = make_gcps(scene["m_true"], 150, 0.3, seed=8)
    gcps.loc[100:, "role"] = "check"
    res = calibrate_lookangle(scene["rpc"], gcps, scene["current"])
    moved = gcps.copy()
    moved.loc[100:, "sample"] += 25.0                        # wrecking check points changes nothing
    res2 = calibrate_lookangle(scene["rpc"], moved, scene["current"])
    np.testing.assert_array_equal(res.camera.x, res2.camera.x)
    assert res.n_control == 100 and res.check_stats["n"] == 50
    assert res.check_stats["after"]["sample"]["rms"] <= 1.3 * 0.3
    assert not res.gcps.loc[100:, "outlier"].any()


def test_nominal_camera_gives_the_same_recalibrated_rpc(scene):
    """METHODS §5: without the vendor's camera file, a nominal camera yields an equally right RPC."""
    gcps, _ = make_gcps(scene["m_true"], 200, 0.3, seed=9)
    vendor = calibrate_lookangle(scene["rpc"], gcps, scene["current"])
    nominal = LookAngleModel.from_nominal((W, W), focal_length_m=9.0, pixel_size_m=9.0 * 1.1 * K,
                                          principal_point=(5000.0, 5300.0))
    nom = calibrate_lookangle(scene["rpc"], gcps, nominal)
    rpc_v, _ = recalibrate_rpc(scene["rpc"], scene["current"], vendor.camera)
    rpc_n, _ = recalibrate_rpc(scene["rpc"], nominal, nom.camera)
    lon, lat, h, S, L = dense_check(scene["m_true"], n=30)
    sv, lv = rpc_v.project(lon, lat, h)
    sn, ln = rpc_n.project(lon, lat, h)
    assert np.max(np.hypot(sv - sn, lv - ln)) < 0.01
    # ... while the nominal-relative camera itself is not the vendor's camera.
    assert compare_lookangle(nom.camera, vendor.camera)["sample"]["max"] > 100


def test_recalibrate_with_unchanged_camera_reproduces_the_rpc(scene):
    new_rpc, rep = recalibrate_rpc(scene["rpc"], scene["current"], scene["current"], progress=lambda f, m: None)
    lon, lat, h, S, L = dense_check(scene["m_cur"], n=25)
    s0, l0 = scene["rpc"].project(lon, lat, h)
    s1, l1 = new_rpc.project(lon, lat, h)
    assert np.max(np.hypot(s1 - s0, l1 - l0)) < 0.01
    assert rep.check.max_px < 0.01
    sensor = RecalibratedSensor(scene["rpc"], scene["current"], scene["true"])
    s, l = sensor.project(lon[:5], lat[:5], h[:5])
    lo, la = sensor.localize(s, l, h[:5])
    np.testing.assert_allclose(lo, lon[:5], atol=1e-9)
    np.testing.assert_allclose(la, lat[:5], atol=1e-9)


# ------------------------------------------------------------------------------------------------ bad input
def test_fewer_than_ten_control_points_is_a_clear_error(scene):
    gcps, _ = make_gcps(scene["m_true"], 9, 0.3, seed=10)
    with pytest.raises(GCPError, match="at least 10 control GCPs"):
        calibrate_lookangle(scene["rpc"], gcps, scene["current"])


@pytest.mark.parametrize("layout", [
    lambda rng, n: (np.linspace(100, W - 100, n), 0.5 * np.linspace(100, W - 100, n) + 300 + rng.normal(0, 0.5, n)),
    lambda rng, n: (rng.uniform(0, 2500, n), rng.uniform(0, 2500, n)),
], ids=["collinear", "one-corner"])
def test_unconstrained_layouts_are_refused_naming_the_condition_number(scene, layout):
    gcps, _ = make_gcps(scene["m_true"], 100, 0.3, seed=11, layout=layout)
    with pytest.raises(DegenerateGeometryError, match=r"condition number [0-9.e+]+ >"):
        calibrate_lookangle(scene["rpc"], gcps, scene["current"])


def test_half_covered_image_warns_with_the_condition_number(scene):
    gcps, _ = make_gcps(scene["m_true"], 100, 0.3, seed=12,
                        layout=lambda rng, n: (rng.uniform(0, W / 2, n), rng.uniform(0, W, n)))
    with pytest.warns(LookAngleConditionWarning, match="condition number"):
        res = calibrate_lookangle(scene["rpc"], gcps, scene["current"])
    assert res.warnings and res.condition_number > 1e4
    assert layout_condition(np.random.default_rng(0).uniform(0, W, 300),
                            np.random.default_rng(1).uniform(0, W, 300), (W, W)) < 200


def test_missing_columns_and_bad_sigma_are_gcp_errors(scene):
    gcps, _ = make_gcps(scene["m_true"], 30, 0.3, seed=13)
    with pytest.raises(GCPError, match="lacks column"):
        calibrate_lookangle(scene["rpc"], gcps.drop(columns=["h"]), scene["current"])
    bad = gcps.copy()
    bad.loc[3, "sigma"] = 0.0
    with pytest.raises(GCPError, match="sigma"):
        calibrate_lookangle(scene["rpc"], bad, scene["current"])


def test_progress_is_reported_and_cancellation_propagates(scene):
    gcps, _ = make_gcps(scene["m_true"], 50, 0.3, seed=14)
    seen = []
    calibrate_lookangle(scene["rpc"], gcps, scene["current"], progress=lambda f, m: seen.append(f))
    assert seen[0] == 0.0 and seen[-1] == 1.0 and seen == sorted(seen)

    def cancel(f, m):
        if f > 0.1:
            raise CancelledError("stop")
    with pytest.raises(CancelledError):
        calibrate_lookangle(scene["rpc"], gcps, scene["current"], progress=cancel)


def test_apply_calibration_keeps_dotted_product_names(scene, tmp_path):
    """GF4 product names carry dotted coordinates (GF4_PMS_E88.5_N32.5_...): output names keep the whole stem."""
    from gdal_gf4cal.workflows import apply_calibration
    names = ["GF4_PMS_E88.5_N32.5_20210109", "GF4_PMS_E88.9_N27.3_20210109"]
    paths = [scene["rpc"].write_rpb(str(tmp_path / f"{n}.RPB")) for n in names]
    rep = apply_calibration(scene["current"], scene["true"], paths, tmp_path / "out")
    for n in names:
        assert (tmp_path / "out" / f"{n}.RPB").is_file()
    assert len(rep["scenes"]) == 2


def test_weights_of_the_wrong_shape_are_a_gcp_error(scene):
    gcps, _ = make_gcps(scene["m_true"], 30, 0.3, seed=16)
    with pytest.raises(GCPError, match="weights"):
        calibrate_lookangle(scene["rpc"], gcps, scene["current"], weights=np.ones(7))


@pytest.mark.parametrize("n, fraction, seed", [(60, 0.3, 21), (100, 0.4, 22)])
def test_many_blunders_in_a_small_set_are_all_flagged(scene, n, fraction, seed):
    """Issue 10: a Huber start from least squares breaks down with 30-40 % blunders among few GCPs; the
    high-breakdown start (estimation.high_breakdown_start) does not."""
    sigma = 0.3
    gcps, blunder = make_gcps(scene["m_true"], n, sigma, seed=seed, blunder_fraction=fraction)
    res = calibrate_lookangle(scene["rpc"], gcps, scene["current"])
    assert np.all(res.outliers[blunder])
    assert np.count_nonzero(res.outliers & ~blunder) <= 1
    # the camera is the least-squares one of the good points alone
    clean = calibrate_lookangle(scene["rpc"], gcps[~blunder], scene["current"], robust=False)
    d = compare_lookangle(res.camera, clean.camera)
    assert max(d["sample"]["rms"], d["line"]["rms"]) < 0.02
    assert set(res.gcps.loc[res.outliers, "outlier_level"]) <= {"start", "reject"}


def test_check_point_blunders_are_flagged_and_left_out_of_the_check_statistics(scene):
    gcps, _ = make_gcps(scene["m_true"], 150, 0.3, seed=9)
    gcps.loc[100:, "role"] = "check"
    gcps.loc[[110, 120], "line"] += 30.0
    res = calibrate_lookangle(scene["rpc"], gcps, scene["current"])
    assert np.flatnonzero(res.outliers).tolist() == [110, 120]
    assert res.check_stats["n"] == 48 and res.check_stats["n_outliers"] == 2
    assert res.check_stats["after"]["line"]["rms"] <= 1.3 * 0.3


def test_estimate_is_the_one_result_class(scene):
    """Issue 10: LookAngleCalibration.estimate (METHODS §4, §5) agrees with the calibration's own numbers."""
    from gdal_gf4cal.estimation import Estimate
    gcps, _ = make_gcps(scene["m_true"], 150, 0.3, seed=9)
    gcps.loc[100:, "role"] = "check"
    gcps.loc[[110, 120], "line"] += 30.0
    res = calibrate_lookangle(scene["rpc"], gcps, scene["current"])
    est = res.estimate
    assert isinstance(est, Estimate)
    np.testing.assert_array_equal(est.block("x"), res.camera.x)
    np.testing.assert_array_equal(est.block("y"), res.camera.y)
    np.testing.assert_allclose(est.std, res.coefficient_std)
    assert est.sigma0 == res.sigma0 and 0.8 < est.sigma0 < 1.2         # GCP noise 0.3 px, sigma 0.3 px
    assert np.flatnonzero(est.outlier).tolist() == [110, 120]
    # check points carry no weight; the redundancy numbers of the control observations add up to the dof
    assert np.all(est.weights.reshape(-1, 2)[100:] == 0)
    assert est.redundancy.sum() == pytest.approx(est.dof, abs=1e-6)
    assert est.dof == 2 * 100 - 20
    # the one report shape: before/after per role, with planar statistics
    assert res.check_stats["after"]["planar"]["n"] == 48 and res.control_stats["n_outliers"] == 0
