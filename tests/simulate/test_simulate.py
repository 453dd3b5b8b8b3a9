"""Tests of the rigorous simulator (METHODS §10): geometry, round trips, the GF4 test bed, RPC fits, files, CLI."""
from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from gdal_gf4cal.rpc import RPCModel
from gdal_gf4cal.rpc_fit import fit_rpc_from_model
from gdal_gf4cal.simulate import (SENSORS, SimulationError, make_scene, shift_coefficients, simulate_gcps,
                                  write_scene)
from gdal_gf4cal.simulate.geodesy import ecef_to_geodetic, geodetic_to_ecef
from gdal_gf4cal.stats import internal_accuracy


@pytest.fixture(scope="module")
def gf4_full():
    return make_scene("gf4", seed=0)


@pytest.fixture(scope="module", params=["zy3", "hj1", "jl1", "gf7"])
def pushbroom_full(request):
    return make_scene(request.param, seed=1)


def test_geodetic_round_trip_is_exact():
    rng = np.random.default_rng(0)
    lon, lat = rng.uniform(-180, 180, 1000), rng.uniform(-89.9, 89.9, 1000)
    h = rng.uniform(-500, 4e7, 1000)          # from below the sea to beyond geostationary altitude
    lo, la, hh = ecef_to_geodetic(geodetic_to_ecef(lon, lat, h))
    assert np.max(np.abs(lo - lon)) < 1e-11
    assert np.max(np.abs(la - lat)) < 1e-11
    assert np.max(np.abs(hh - h)) < 1e-6


def test_polynomial_shift_is_exact():
    rng = np.random.default_rng(3)
    c = rng.normal(size=10) * np.array([1, 1e-3, 1e-3, 1e-6, 1e-6, 1e-6, 1e-9, 1e-9, 1e-9, 1e-9])
    from gdal_gf4cal.camera import lookangle_terms
    s, l = rng.uniform(0, 500, 50), rng.uniform(0, 500, 50)
    shifted = shift_coefficients(c, 123.0, -45.5)
    assert np.allclose(shifted @ lookangle_terms(s, l), c @ lookangle_terms(s + 123.0, l - 45.5), rtol=1e-12,
                       atol=1e-12)


def _round_trip(model, n=500, seed=0):
    W, H = model.size
    rng = np.random.default_rng(seed)
    s, l = rng.uniform(0, W, n), rng.uniform(0, H, n)
    h = rng.uniform(*model.height_range, n)
    lon, lat = model.localize(s, l, h)
    s2, l2 = model.project(lon, lat, h)
    return np.max(np.hypot(s2 - s, l2 - l))


def test_gf4_round_trip_and_gsd(gf4_full):
    im = gf4_full.image("")
    assert im.size == (10240, 10240)
    for model in (im.current, im.true):
        assert _round_trip(model) <= 1e-6
    # 50 m at the sub-satellite point, ~55-66 m over Tibet (METHODS §10).
    gx, gy = im.info["gsd_center_m"]
    assert 50 < gx < 70 and 58 < gy < 70


def test_pushbroom_round_trip(pushbroom_full):
    for im in pushbroom_full.images:
        for model in (im.current, im.true):
            assert _round_trip(model, n=300) <= 1e-6, (pushbroom_full.sensor, im.name)


def test_localize_dem_lands_on_the_dem_and_round_trips(gf4_full):
    im = gf4_full.image("")
    rng = np.random.default_rng(2)
    s, l = rng.uniform(0, 10240, 300), rng.uniform(0, 10240, 300)
    lon, lat, h = im.true.localize_dem(s, l, gf4_full.dem)
    assert np.all(np.isfinite(h))
    assert np.max(np.abs(gf4_full.dem.height(lon, lat) - h)) < 1e-3
    s2, l2 = im.true.project(lon, lat, h)
    assert np.max(np.hypot(s2 - s, l2 - l)) <= 1e-6
    lo, hi = gf4_full.truth["dem"]["height_range_m"]
    assert lo == pytest.approx(3500, abs=1) and hi == pytest.approx(6500, abs=1)


def test_gf4_exterior_identical_and_lookangle_identity(gf4_full):
    """METHODS §5: V_true(s, l) = V_current(s', l') exactly for every ground point."""
    im = gf4_full.image("")
    assert np.array_equal(im.current.position, im.true.position)
    assert np.array_equal(im.current.rotation, im.true.rotation)
    rng = np.random.default_rng(5)
    lon, lat, h = im.true.localize_dem(rng.uniform(0, 10240, 400), rng.uniform(0, 10240, 400), gf4_full.dem)
    s, l = im.true.project(lon, lat, h)
    sv, lv = im.virtual_image_point(lon, lat, h)
    vt = np.array(im.true.camera.tan_angles(s, l))
    vc = np.array(im.current.camera.tan_angles(sv, lv))
    ifov = im.errors["ifov_rad"]
    assert np.max(np.abs(vt - vc)) / ifov < 1e-6
    # look_angles is the same quantity computed without the camera inversion
    la = np.array(im.current.look_angles(lon, lat, h))
    assert np.max(np.abs(la - vc)) / ifov < 1e-6
    # the rigorous baseline: the current model with the true camera is the true model
    s3, l3 = im.current.with_camera(im.true.camera).project(lon, lat, h)
    assert np.max(np.hypot(s3 - s, l3 - l)) < 1e-6


def test_gf4_reproduces_the_papers_starting_point(gf4_full):
    """Seed 000 Table 3: ~10 px RMS against the RPC, mostly rotation; ~1.5-1.9 px after rotation+translation;
    3-4 px at the edges."""
    rpc, rep = fit_rpc_from_model(gf4_full.image("").current)
    assert rep.check.max_px <= 0.01 and rep.check.rms_px <= 0.002
    g = simulate_gcps(gf4_full, n_gcps=200, gcp_noise_px=0.6)[""]
    ps, pl = rpc.project(g.lon.to_numpy(), g.lat.to_numpy(), g.h.to_numpy())
    ds, dl = g["sample"].to_numpy() - ps, g["line"].to_numpy() - pl
    rms_s, rms_l = np.sqrt(np.mean(ds ** 2)), np.sqrt(np.mean(dl ** 2))
    assert 8.5 < rms_s < 11.5 and 8.5 < rms_l < 11.5
    ia = internal_accuracy(g["sample"].to_numpy(), g["line"].to_numpy(), ps, pl)
    assert abs(ia["theta_rad"]) > 2.5e-3                         # the rotation dominates
    assert 1.4 <= ia["sample"]["rms"] <= 2.0 and 1.4 <= ia["line"]["rms"] <= 2.0
    # noise-free distortion at the edges of the array (after the same rotation + translation removal)
    im = gf4_full.image("")
    e = np.linspace(0, 10240, 41)
    s = np.concatenate([e, e, np.zeros(41), np.full(41, 10240.0)])
    l = np.concatenate([np.zeros(41), np.full(41, 10240.0), e, e])
    lon, lat, h = im.true.localize_dem(s, l, gf4_full.dem)
    ps, pl = rpc.project(lon, lat, h)
    from gdal_gf4cal.stats import remove_low_order
    rs, rl = remove_low_order(s, l, ps, pl)
    radial = np.hypot(rs, rl)
    assert 2.5 <= np.median(radial) and np.max(radial) <= 5.0


def test_gf4_edge_statistics_per_seed():
    """The starting point holds for other seeds too (not tuned on one draw)."""
    for seed in (3, 4):
        sc = make_scene("gf4", seed=seed, size=(10240, 10240))
        rpc, _ = fit_rpc_from_model(sc.images[0].current)
        g = simulate_gcps(sc, n_gcps=150)[""]
        ps, pl = rpc.project(g.lon.to_numpy(), g.lat.to_numpy(), g.h.to_numpy())
        ia = internal_accuracy(g["sample"].to_numpy(), g["line"].to_numpy(), ps, pl)
        assert 1.2 <= ia["sample"]["rms"] <= 2.1 and 1.2 <= ia["line"]["rms"] <= 2.1


def test_rpc_fit_accuracy_full_size_every_sensor(pushbroom_full):
    for im in pushbroom_full.images:
        _, rep = fit_rpc_from_model(im.current)
        assert rep.check.max_px <= 0.01, (pushbroom_full.sensor, im.name)
        assert rep.check.rms_px <= 0.002, (pushbroom_full.sensor, im.name)


def test_pushbroom_truth_differs_as_designed(pushbroom_full):
    sc = pushbroom_full
    g = simulate_gcps(sc, n_gcps=150, gcp_noise_px=0.0)
    for im in sc.images:
        t = g[im.name]
        assert len(t) > 50
        cs, cl = im.current.project(t.lon.to_numpy(), t.lat.to_numpy(), t.h.to_numpy())
        d = np.hypot(t["sample"].to_numpy() - cs, t["line"].to_numpy() - cl)
        if sc.sensor == "hj1":
            _check_hj1_truth(im, t, cs, cl)
        else:
            assert 0.05 < np.sqrt(np.mean(d ** 2)) < 40


def _check_hj1_truth(im, t, cs, cl):
    """HJ-1 (seed 002, METHODS §10): beyond a straight CCD the cross-track error is a cubic of the detector position
    reaching ~50-75 px at both swath edges; what is not cubic (attitude oscillation) is a fraction of a pixel."""
    W, H = im.size
    ds = t["sample"].to_numpy() - cs
    u, v = (cs - W / 2) / (W / 2), (cl - H / 2) / (H / 2)
    beyond_line = ds - np.column_stack([np.ones_like(u), u, v]) @ np.linalg.lstsq(
        np.column_stack([np.ones_like(u), u, v]), ds, rcond=None)[0]
    for side in (u < -0.85, u > 0.85):
        assert np.sum(side) >= 3 and np.min(np.abs(beyond_line[side])) > 20
        assert np.max(np.abs(beyond_line[side])) < 85
    assert 20 < np.sqrt(np.mean(beyond_line ** 2)) < 35
    # the same signs at both edges, the other at the centre (symmetric shape)
    assert np.sign(np.median(beyond_line[u < -0.85])) == np.sign(np.median(beyond_line[u > 0.85])) \
        == -np.sign(np.median(beyond_line[np.abs(u) < 0.2]))
    A = np.column_stack([u ** k for k in range(4)] + [v])
    cubic_left = ds - A @ np.linalg.lstsq(A, ds, rcond=None)[0]
    assert np.sqrt(np.mean(cubic_left ** 2)) < 0.5
    edge = im.errors["cross_track_edge_beyond_line_px"]
    assert 45 <= min(abs(e) for e in edge) and max(abs(e) for e in edge) <= 80


def test_hj1_distorted_rpc_fit_full_size():
    """METHODS §3 target for the HJ-1 camera with its distortion (the model a corrected RPC represents), at full
    size, for several draws and the corners of the design range: the u³ part of the distortion is what costs the
    RPC (70 px of u³ alone: 0.0104 px max, 0.0030 px RMS), so it is kept <= 22 px."""
    from gdal_gf4cal.simulate.sensors import HJ1_EVEN_PX, HJ1_ODD_PX, _linear_camera, _poly_px
    for seed in (0, 1, 2):
        im = make_scene("hj1", seed=seed).image("")
        assert im.size == (12000, 12000)
        for model in (im.current, im.current.with_camera(im.true.camera)):
            _, rep = fit_rpc_from_model(model)
            assert rep.check.max_px <= 0.01 and rep.check.rms_px <= 0.002, seed
        assert abs(im.errors["odd_px"]) <= HJ1_ODD_PX[1]
        assert HJ1_EVEN_PX[0] <= abs(im.errors["even_px"]) <= HJ1_EVEN_PX[1]
    # the corners of the design range (largest u³ and u² terms, both signs)
    ifov = im.info["ifov_rad"]
    for c2 in (-HJ1_EVEN_PX[1], HJ1_EVEN_PX[1]):
        for c3 in (-HJ1_ODD_PX[1], HJ1_ODD_PX[1]):
            d = (-c2 / 3, -0.6 * c3, c2, c3)
            cam = _linear_camera(im.size, ifov, 0.0, 0.0, "corner", _poly_px([-c for c in d]))
            _, rep = fit_rpc_from_model(im.current.with_camera(cam))
            assert rep.check.max_px <= 0.01 and rep.check.rms_px <= 0.002, (c2, c3)


def test_crop_keeps_geometry():
    full = make_scene("gf4", seed=2)
    crop = make_scene("gf4", seed=2, size=(1000, 800))
    assert crop.images[0].size == (1000, 800)
    x0, y0 = crop.truth["images"]["scene"]["info"]["crop_offset"]
    assert (x0, y0) == ((10240 - 1000) // 2, (10240 - 800) // 2)
    s, l = np.array([0.5, 999.5, 500.0]), np.array([0.5, 799.5, 400.0])
    for state in ("current", "true"):
        a = getattr(full.images[0], state).localize(s + x0, l + y0, 5000.0)
        b = getattr(crop.images[0], state).localize(s, l, 5000.0)
        assert np.allclose(a, b, atol=1e-10)
    zf, zc = make_scene("zy3", seed=0), make_scene("zy3", seed=0, size=(600, 600))
    im_f, im_c = zf.image("fwd"), zc.image("fwd")
    x0, y0 = zc.truth["images"]["fwd"]["info"]["crop_offset"]
    a = im_f.true.localize(np.array([10.0, 300.0]) + x0, np.array([20.0, 200.0]) + y0, 100.0)
    b = im_c.true.localize(np.array([10.0, 300.0]), np.array([20.0, 200.0]), 100.0)
    assert np.allclose(a, b, atol=1e-10)


def test_bad_parameters_raise_clear_errors():
    with pytest.raises(SimulationError, match="unknown sensor"):
        make_scene("spot")
    with pytest.raises(SimulationError, match="exceeds"):
        make_scene("gf4", size=(20000, 100))
    with pytest.raises(SimulationError, match="too small"):
        make_scene("gf4", size=(4, 4))


def test_write_scene_files(tmp_path):
    res = write_scene("gf4", tmp_path / "gf4", seed=1, size=(640, 512), n_gcps=60, gcp_noise_px=0.5,
                      outlier_fraction=0.1)
    d = tmp_path / "gf4"
    for f in ("scene.tif", "scene.RPB", "dem.tif", "gcps.csv", "gcps.gpkg", "check_grid.csv",
              "camera_current.json", "camera_true.json", "truth.json"):
        assert (d / f).is_file(), f
    from osgeo import gdal
    ds = gdal.Open(str(d / "scene.tif"))
    assert (ds.RasterXSize, ds.RasterYSize) == (640, 512)
    md = ds.GetMetadata("RPC")            # GDAL picks up the scene.RPB sidecar
    assert md and "LINE_OFF" in md
    rpc = RPCModel.from_file(str(d / "scene.tif"))
    grid = pd.read_csv(d / "check_grid.csv")
    assert list(grid.columns) == ["lon", "lat", "h", "sample_current", "line_current", "sample_true", "line_true"]
    ps, pl = rpc.project(grid.lon.to_numpy(), grid.lat.to_numpy(), grid.h.to_numpy())
    assert np.max(np.hypot(ps - grid.sample_current, pl - grid.line_current)) < 0.01
    # GDAL's own RPC transformer agrees on the pixel convention of the written RPC
    tr = gdal.Transformer(ds, None, ["METHOD=RPC", f"RPC_HEIGHT={grid.h[0]}"])
    ok, (x, y, _) = tr.TransformPoint(1, float(grid.lon[0]), float(grid.lat[0]), 0.0)
    assert ok and abs(x - grid.sample_current[0]) < 0.01 and abs(y - grid.line_current[0]) < 0.01
    g = pd.read_csv(d / "gcps.csv")
    for col in ("id", "lon", "lat", "h", "sample", "line", "role", "truth_sample", "truth_line"):
        assert col in g.columns
    assert set(g.role) <= {"control", "check"}
    noise = np.hypot(g["sample"] - g.truth_sample, g["line"] - g.truth_line)
    assert noise[g.truth_outlier].min() >= 4.0 and noise[~g.truth_outlier].max() < 3.0
    # truth positions come from the true model exactly
    ts, tl = res.scene.images[0].true.project(g.lon.to_numpy(), g.lat.to_numpy(), g.h.to_numpy())
    assert np.max(np.hypot(ts - g.truth_sample, tl - g.truth_line)) < 1e-6
    truth = json.loads((d / "truth.json").read_text())
    assert truth["sensor"] == "gf4" and truth["images"]["scene"]["rpc_fit"]["check"]["max_px"] <= 0.01
    from gdal_gf4cal.camera import LookAngleModel
    cam = LookAngleModel.from_json(d / "camera_true.json")
    assert cam.size == (640, 512)
    assert np.allclose(cam.tan_angles(10.0, 20.0), res.scene.images[0].true.camera.tan_angles(10.0, 20.0))
    import geopandas as gpd
    assert len(gpd.read_file(d / "gcps.gpkg")) == len(g)


def test_write_scene_multi_image_layout(tmp_path):
    write_scene("zy3", tmp_path / "zy3", seed=0, size=(400, 400), n_gcps=40)
    for view in ("nadir", "fwd", "bwd"):
        g = pd.read_csv(tmp_path / "zy3" / view / "gcps.csv")
        assert len(g) > 20
        assert (tmp_path / "zy3" / view / "scene.RPB").is_file()
    ids = [set(pd.read_csv(tmp_path / "zy3" / v / "gcps.csv").id) for v in ("nadir", "fwd", "bwd")]
    assert len(ids[0] & ids[1] & ids[2]) > 20        # the same ground points in the three views


def test_write_scene_with_user_dem(tmp_path):
    from gdal_gf4cal.simulate.terrain import write_dem_tif
    h = np.full((50, 50), 120.0, dtype=np.float32)
    dem_path = str(tmp_path / "flat.tif")
    write_dem_tif(dem_path, h, (121.0, 0.03, 0.0, 32.2, 0.0, -0.03))
    res = write_scene("hj1", tmp_path / "hj1", seed=0, size=(300, 300), n_gcps=30, dem=dem_path,
                      center=(121.7, 31.5))
    g = res.images[""].gcps
    assert np.allclose(g.h, 120.0, atol=1e-3)


def test_cli_simulate(tmp_path, capsys):
    from gdal_gf4cal.cli import main
    out = tmp_path / "cli"
    assert main(["simulate", "--sensor", "gf7", "--out", str(out), "--size", "256", "256", "--n-gcps", "30",
                 "--seed", "4"]) == 0
    assert (out / "pan" / "scene.RPB").is_file() and (out / "ms" / "camera_true.json").is_file()
    assert main(["simulate", "--sensor", "gf4", "--out", str(tmp_path / "bad"), "--size", "99999", "10"]) == 2
    err = capsys.readouterr().err
    assert "gf4cal: error:" in err and "Traceback" not in err


@pytest.mark.parametrize("sensor", sorted(SENSORS))
def test_every_sensor_small_crop(sensor, tmp_path):
    sc = make_scene(sensor, seed=3, size=(256, 192))
    for im in sc.images:
        for model in (im.current, im.true):
            assert _round_trip(model, n=100) <= 1e-6
        _, rep = fit_rpc_from_model(im.current)
        assert rep.check.max_px <= 0.01 and rep.check.rms_px <= 0.002


def test_earth_rotation_sign_of_the_platform():
    """Independent physics: the ECEF velocity of the platform is the inertial one minus omega x r (the Earth turns
    eastward under the orbit, so the ground track drifts west)."""
    from gdal_gf4cal.simulate.geodesy import OMEGA_EARTH
    im = make_scene("zy3", seed=0, size=(64, 64)).image("nadir")
    m = im.current
    pos_i, vel_i = m.orbit.inertial(0.0)               # inertial frame = ECEF at t = 0
    dt = 1e-3
    (p0, _), (p1, _) = m.platform(np.array([-dt])), m.platform(np.array([dt]))
    vel_ecef = (p1[0] - p0[0]) / (2 * dt)
    expected = vel_i - np.cross([0.0, 0.0, OMEGA_EARTH], pos_i)
    assert np.max(np.abs(vel_ecef - expected)) < 1e-3          # m/s (omega x r is ~460 m/s)
    assert np.max(np.abs(vel_ecef - vel_i)) > 100


def test_user_dem_above_the_geoid_gives_an_ellipsoidal_height_range(tmp_path, data_dir):
    """A DEM with geoid='egm96' (undulation ~50 m in Provence): the scene's height range is ellipsoidal."""
    from gdal_gf4cal.dem import DEM
    from gdal_gf4cal.simulate.terrain import write_dem_tif
    path = str(tmp_path / "flat_ortho.tif")
    write_dem_tif(path, np.full((60, 60), 100.0, dtype=np.float32), (4.5, 0.03, 0.0, 45.4, 0.0, -0.03))
    dem = DEM.from_file(path, geoid="egm96")
    sc = make_scene("hj1", seed=0, size=(200, 200), dem=dem, center=(5.4, 44.5))
    lo, hi = sc.truth["dem"]["height_range_m"]
    assert 145 < lo <= hi < 155


def test_write_scene_refuses_to_overwrite_its_reference(tmp_path):
    from gdal_gf4cal.simulate.render import write_reference_ortho
    out = tmp_path / "sc"
    out.mkdir()
    ref = out / "scene.tif"
    write_reference_ortho(ref, (87.9, 30.9, 88.1, 31.1), 0.002, seed=1)
    before = ref.read_bytes()
    with pytest.raises(SimulationError, match="input"):
        write_scene("gf4", out, seed=1, size=(64, 64), n_gcps=10, render=True, reference=str(ref))
    assert ref.read_bytes() == before
    from gdal_gf4cal.simulate.terrain import write_dem_tif
    dem = write_dem_tif(str(out / "dem.tif"), np.full((20, 20), 4000.0, dtype=np.float32),
                        (87.0, 0.1, 0.0, 32.0, 0.0, -0.1))
    before = (out / "dem.tif").read_bytes()
    with pytest.raises(SimulationError, match="input"):
        write_scene("gf4", out, seed=1, size=(64, 64), n_gcps=10, dem=dem)
    assert (out / "dem.tif").read_bytes() == before


def test_clouds_without_render_are_refused(tmp_path):
    with pytest.raises(SimulationError, match="--render"):
        write_scene("gf4", tmp_path / "c", seed=1, size=(64, 64), n_gcps=10, paint_clouds=0.2)
