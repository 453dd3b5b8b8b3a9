"""Block calibration engine (METHODS §8) on a synthetic group: four linear RPC CCD images side by side (overlap 40 px)
over a constant-height DEM, measurements made by a known block correction (the model itself) plus noise."""
import numpy as np
import pandas as pd
import pytest

from gdal_gf4cal.block import (BlockCorrectedRPC, BlockError, ImageCorrection, adjust_block, calibrated_model,
                               calibration_dict, derive_layout, prediction_std)
from gdal_gf4cal.dem import DEM
from gdal_gf4cal.rpc import RPCModel

W, H, OVERLAP, GSD_DEG = 400, 200, 40, 1e-5
DEM0 = DEM.constant(100.0)


def ccd_rpc(k, lon0=120.0, lat0=40.0):
    """A linear RPC: sample along +lon, line along -lat; CCD k shifted by W - OVERLAP px across track."""
    num_s, num_l, den = np.zeros(20), np.zeros(20), np.zeros(20)
    num_s[1], num_l[2], den[0] = 1.0, -1.0, 1.0
    num_s[3] = 0.01                                             # a little height dependence (off-nadir)
    return RPCModel(line_off=H / 2 - 0.5, samp_off=W / 2 - 0.5, lat_off=lat0, long_off=lon0 + k * (W - OVERLAP) * GSD_DEG,
                    height_off=0.0, line_scale=H / 2, samp_scale=W / 2, lat_scale=H / 2 * GSD_DEG,
                    long_scale=W / 2 * GSD_DEG, height_scale=500.0, line_num=num_l, line_den=den,
                    samp_num=num_s, samp_den=den)


def group(n_ties_per_pair=60, n_gcps=25, seed=0, blunders=0.0):
    rng = np.random.default_rng(seed)
    names = [f"c{k}" for k in range(1, 5)]
    models = {n: ccd_rpc(k) for k, n in enumerate(names)}
    layout = derive_layout(models, names, sizes={n: (W, H) for n in names})
    ext = np.array([2.0, -1.5, 0.4, -0.3, 0.5])
    truth = {}
    for n in names:
        inter = rng.normal(0, [1.5, 0.8, 0.6, 0.9, 1.5, 0.8, 0.6, 0.4])
        if n == layout.reference_ccd:
            inter[[0, 4, 5]] = 0.0
        truth[n] = BlockCorrectedRPC(models[n], ImageCorrection(layout.images[n], layout.time_scale, ext, inter))
    rows = []
    for n in names:
        s, l = rng.uniform(0, W, n_gcps), rng.uniform(0, H, n_gcps)
        lon, lat, h = models[n].localize_dem(s, l, DEM0)
        ms, ml = truth[n].project(lon, lat, h)
        rows.append(pd.DataFrame({"point_id": [f"G{n}{i}" for i in range(n_gcps)], "image_id": n, "kind": "gcp",
                                  "sample": ms + rng.normal(0, 0.2, n_gcps), "line": ml + rng.normal(0, 0.2, n_gcps),
                                  "sigma": 0.2, "role": "control", "lon": lon, "lat": lat, "h": h}))
    for j, (a, b) in enumerate(zip(names[:-1], names[1:])):
        s, l = rng.uniform(W - OVERLAP + 3, W - 3, n_ties_per_pair), rng.uniform(0, H, n_ties_per_pair)
        lon, lat, h = truth[a].localize_dem(s, l, DEM0)
        sb, lb = truth[b].project(lon, lat, h)
        pid = [f"T{j}_{i}" for i in range(n_ties_per_pair)]
        for im, ss, ll in ((a, s, l), (b, sb, lb)):
            rows.append(pd.DataFrame({"point_id": pid, "image_id": im, "kind": "tie",
                                      "sample": ss + rng.normal(0, 0.1, ss.size),
                                      "line": ll + rng.normal(0, 0.1, ss.size), "sigma": 0.1}))
    obs = pd.concat(rows, ignore_index=True)
    bad = np.zeros(len(obs), bool)
    if blunders:
        tie_b = np.flatnonzero((obs["kind"] == "tie").to_numpy() & obs["image_id"].isin(names[1:]).to_numpy())
        pick = rng.choice(tie_b, int(blunders * tie_b.size), replace=False)
        ang = rng.uniform(0, 2 * np.pi, pick.size)
        mag = rng.uniform(5, 50, pick.size)
        obs.loc[pick, "sample"] += mag * np.cos(ang)
        obs.loc[pick, "line"] += mag * np.sin(ang)
        bad[pick] = True
    return models, truth, layout, obs, bad


def max_error(est, models, truth):
    """Largest error against the truth over a grid of every image, over the largest propagated 1-sigma there."""
    err, std = 0.0, 0.0
    for n in models:
        S, L = (a.ravel() for a in np.meshgrid(np.linspace(0, W, 9), np.linspace(0, H, 5)))
        lon, lat, h = truth[n].localize_dem(S, L, DEM0)
        ps, pl = BlockCorrectedRPC(models[n], est.correction(n)).project(lon, lat, h)
        err = max(err, float(np.max(np.hypot(ps - S, pl - L))))
        std = max(std, float(np.max(np.hypot(*prediction_std(est, n, S, L)))))
    return err, err / std


def test_layout_from_rpcs():
    models = {f"c{k}": ccd_rpc(k - 1) for k in range(1, 5)}
    lay = derive_layout(models, list(models), sizes={n: (W, H) for n in models})
    assert lay.reference_ccd == "c2"
    x = [lay.images[n].x0_px for n in models]
    np.testing.assert_allclose(np.diff(x), W - OVERLAP, atol=0.5)
    assert all(abs(lay.images[n].ratio - 1.0) < 1e-6 for n in models)


def test_recovers_the_block_and_reduced_size_is_independent_of_ties():
    models, truth, layout, obs, _ = group()
    est = adjust_block(obs, models, DEM0, layout=layout)
    assert est.stages[0]["converged"] and est.stages[0]["iterations"] <= 10
    assert max_error(est, models, truth)[1] < 3.0
    assert est.block(f"datum:{layout.reference_ccd}").tolist() == [0.0, 0.0, 0.0]
    assert est.stages[0]["reduced_system_size"] == 5 + 8 * 4 - 3
    more = group(n_ties_per_pair=240)[3]
    est2 = adjust_block(more, models, DEM0, layout=layout)
    assert est2.stages[0]["reduced_system_size"] == est.stages[0]["reduced_system_size"]
    assert est2.stages[0]["n_tie_points"] == 4 * est.stages[0]["n_tie_points"]
    # precision floor: the propagated std is of the size of the errors
    fs, fl = prediction_std(est, "c1", np.array([10.0, 200.0]), np.array([100.0, 100.0]))
    assert np.all((fs > 0.005) & (fs < 0.2) & (fl > 0.005) & (fl < 0.2))


def test_alternating_takes_more_iterations():
    models, truth, layout, obs, _ = group(seed=1)
    est = adjust_block(obs, models, DEM0, layout=layout, compare=True)
    alt = est.comparison["stages"][0]
    assert est.comparison["solver"] == "alternating"
    assert est.stages[0]["iterations"] < alt["iterations"]


def test_blunder_ties_are_flagged():
    """5 % wrong ties (5-50 px): all flagged, result within 10 % of the clean run's (same noise)."""
    models, truth, layout, obs, bad = group(seed=2, blunders=0.05)
    est = adjust_block(obs, models, DEM0, layout=layout)
    assert est.outlier[bad].all()
    clean = adjust_block(group(seed=2)[3], models, DEM0, layout=layout)
    assert max_error(est, models, truth)[0] <= 1.1 * max_error(clean, models, truth)[0]


def test_calibration_roundtrip():
    models, truth, layout, obs, _ = group(seed=3)
    est = adjust_block(obs, models, DEM0, layout=layout)
    cal = calibration_dict(est)
    m = calibrated_model(cal, "c3", models["c3"], (W, H))
    lon, lat = np.array([120.0083]), np.array([39.9995])
    a = m.project(lon, lat, 100.0)
    b = BlockCorrectedRPC(models["c3"], est.correction("c3")).project(lon, lat, 100.0)
    np.testing.assert_allclose(a, b, atol=1e-9)
    with pytest.raises(BlockError, match="not in the calibration"):
        calibrated_model(cal, "c9", models["c3"])


def test_bad_inputs():
    models, truth, layout, obs, _ = group(seed=4)
    with pytest.raises(BlockError, match="not among the images"):
        adjust_block(obs.assign(image_id=obs["image_id"].replace("c4", "c9")), models, DEM0, layout=layout)
    few = obs[(obs["kind"] == "tie") | obs["point_id"].str.fullmatch(r"Gc\d[0-2]")]
    with pytest.raises(BlockError, match="control GCP"):
        adjust_block(few, models, DEM0, layout=layout)
    sizes = {n: (W, H) for n in models}
    with pytest.raises(BlockError, match="no overlap between c1 and c3"):
        derive_layout(models, ["c1", "c3", "c2", "c4"], sizes=sizes)
    far = dict(models, c4=ccd_rpc(3, lon0=121.0))
    with pytest.raises(BlockError, match="c4 overlaps none"):
        derive_layout(far, ["c1", "c2", "c3", "c4"], sizes=sizes)


def test_exterior_of_another_scene_from_a_calibration():
    """Another scene of the same group (its own exterior, same interiors): 5 GCPs fix its exterior."""
    models, truth, layout, obs, _ = group(seed=5)
    cal = calibration_dict(adjust_block(obs, models, DEM0, layout=layout))
    other = {}
    rng = np.random.default_rng(9)
    ext = np.array([-3.0, 2.5, 0.1, 0.2, -0.4])
    for n in models:
        c = truth[n].corr
        other[n] = BlockCorrectedRPC(models[n], ImageCorrection(c.layout, c.time_scale, ext, c.interior))
    rows = []
    for i, n in enumerate(list(models)[:2] + list(models)[2:] * 1):
        s, l = rng.uniform(0, W, 2), rng.uniform(0, H, 2)
        lon, lat, h = models[n].localize_dem(s, l, DEM0)
        ms, ml = other[n].project(lon, lat, h)
        rows.append(pd.DataFrame({"point_id": [f"G{i}a", f"G{i}b"], "image_id": n, "kind": "gcp", "sample": ms,
                                  "line": ml, "sigma": 0.2, "role": "control", "lon": lon, "lat": lat, "h": h}))
    few = pd.concat(rows, ignore_index=True)
    est = adjust_block(few, models, DEM0, calibration=cal)
    np.testing.assert_allclose(est.block("exterior")[:2], ext[:2], atol=0.2)   # + the calibration's own error
    assert [s["stage"] for s in est.stages] == ["exterior"]
    with pytest.raises(BlockError, match=">= 3"):
        adjust_block(few.iloc[:2], models, DEM0, calibration=cal)
