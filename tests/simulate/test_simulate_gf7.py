"""Tests of the Gaofen-7 pan-MS simulator (METHODS §9, §10): the true misregistration field against the injected
truth (sub-CCD jumps at the MS edges only, differential jitter, "before" magnitudes), shared cameras, RPC fits,
determinism, cover, rendering and files."""
from __future__ import annotations

import json

import numpy as np
import pytest
from osgeo import gdal

from gdal_gf4cal.rpc_fit import fit_rpc_from_model
from gdal_gf4cal.simulate import SimulationError, make_scene
from gdal_gf4cal.simulate.gf7 import (MS_FULL, cover_class, make_gf7_scene, misregistration_stats,
                                      true_misregistration, write_gf7_scene, write_misregistration_truth)

EDGES = (2560, 5120)          # MS sub-CCD edges of the full array


@pytest.fixture(scope="module")
def full():
    return make_gf7_scene(seed=1)


@pytest.fixture(scope="module")
def full_nojitter():
    return make_gf7_scene(seed=1, jitter=False)


def _profile_along_sample(scene, line, step=1.0):
    s = np.arange(0.5, MS_FULL[0], step)
    return s, true_misregistration(scene, s, np.full(s.shape, line))


def _design(s, l, W, H, pieces=True):
    u, v = (s - W / 2) / (W / 2), (l - H / 2) / (H / 2)
    cols = [np.ones_like(u), u, v]
    if pieces:
        k = np.clip(np.searchsorted(EDGES, s, side="right"), 0, 2)
        for j, (a, b) in enumerate(zip((0,) + EDGES, EDGES + (W,))):
            uk = (s - 0.5 * (a + b)) / (0.5 * (b - a))
            cols += [(k == j) * uk ** p for p in range(5)]
    return np.column_stack(cols)


def _fit_rms(scene, pieces, n=64):
    W, H = scene.image("ms").size
    s, l = (a.ravel() for a in np.meshgrid((np.arange(n) + 0.5) * W / n, (np.arange(n) + 0.5) * H / n))
    A = _design(s, l, W, H, pieces)
    out = []
    for d in true_misregistration(scene, s, l):
        r = d - A @ np.linalg.lstsq(A, d, rcond=None)[0]
        out.append(float(np.sqrt(np.mean(r ** 2))))
    return out


def test_registry_and_look_time(full):
    ms, pan = full.image("ms"), full.image("pan")
    assert ms.size == (7680, 7680) and pan.size == (30720, 30720)
    assert abs(ms.errors["look_time_s"] - 0.117) < 1e-6
    # Yaw steering: the pan and MS reference detectors see the same ground line (cross-track gap < 1 mm).
    assert abs(ms.errors["pan_ms_cross_track_gap_m"]) < 1e-3
    assert make_scene("gf7", seed=1, size=(64, 64)).image("ms").errors["camera_seed"] == 4
    with pytest.raises(SimulationError):
        make_gf7_scene(seed=1, size=(64, 64), clouds=1.2)


def _steps(scene, line):
    s, (ds, dl) = _profile_along_sample(scene, line)
    return s[:-1] + 0.5, np.hypot(np.diff(ds), np.diff(dl))      # position of each step, its size


def test_jumps_only_at_ms_sub_ccd_edges(full, full_nojitter):
    for scene in (full, full_nojitter):
        for line in (1000.5, 6000.5):
            x, step = _steps(scene, line)
            near = np.min(np.abs(x[:, None] - np.array(EDGES)[None, :]), axis=1) <= 1.5
            # The sub-CCD jumps (camera_seed 4: 0.08-0.8 px) at both MS edges, the pan's own jump within the same
            # pixel or the next (the misregistration there is < 1 px) ...
            for e in EDGES:
                assert step[np.abs(x - e) <= 1.5].max() > 0.05
            # ... and smooth everywhere else (only the terrain's ~0.003 px per pixel): no other discontinuity.
            assert step[~near].max() < 5e-3, x[~near][np.argmax(step[~near])]


def test_without_yaw_steering_the_pan_edges_add_discontinuities():
    scene = make_gf7_scene(seed=1, jitter=False, yaw_steering=False)
    x, step = _steps(scene, 3000.5)
    big = x[step > 0.02]
    # The two MS edges + the two pan edges ~19 MS px away (the Earth turns in 0.117 s): four discontinuities.
    far = [b for b in big if min(abs(b - e) for e in EDGES) > 1.5]
    assert len(far) == 2 and all(10 < min(abs(b - e) for e in EDGES) < 30 for b in far)
    assert all(np.any(np.abs(big - e) <= 1.5) for e in EDGES)


def test_before_magnitudes_and_stepwise_like_the_paper(full, full_nojitter):
    st = misregistration_stats(full)
    # METHODS §9 "before": ~0.60 / 0.30 px (column / row), P < 1 %.
    assert 0.5 < st["rms_sample_px"] < 0.85 and 0.2 < st["rms_line_px"] < 0.45
    assert st["p_le_0.25"] < 0.02
    lin_s, lin_l = _fit_rms(full, pieces=False)
    assert lin_s < 0.15 and 0.1 < lin_l < 0.25                   # linear leaves the sub-CCD structure
    pw_s, pw_l = _fit_rms(full, pieces=True)
    assert 0.025 < pw_s < 0.07 and 0.025 < pw_l < 0.07           # what is left: the differential jitter
    no_s, no_l = _fit_rms(full_nojitter, pieces=True)
    assert no_s < 0.005 and no_l < 0.015                         # no jitter: linear + piecewise is (nearly) all


def test_jitter_term_present_or_absent(full, full_nojitter):
    ms = full.image("ms")
    assert full_nojitter.image("ms").true.attitude.jitter == [] and len(ms.true.attitude.jitter) == 6
    amps = ms.errors["jitter_differential_px"]
    assert len(amps) == 6 and max(amps) < 0.1
    col = 1300.5
    l = np.arange(0.5, MS_FULL[1], 1.0)
    dj = [a - b for a, b in zip(true_misregistration(full, np.full(l.shape, col), l),
                                true_misregistration(full_nojitter, np.full(l.shape, col), l))]
    # The jitter term: a sum of sines along the line of the given differential amplitudes, nothing across.
    for d, axis in zip(dj, ("roll", "pitch")):
        comp = [a for a, j in zip(amps, ms.true.attitude.jitter) if j[0] == axis]
        assert np.abs(d).max() <= 1.05 * sum(comp)
        assert 0.6 * np.sqrt(np.sum(np.square(comp)) / 2) < np.sqrt(np.mean((d - d.mean()) ** 2)) < \
            1.6 * np.sqrt(np.sum(np.square(comp)) / 2)
    # Its spectrum peaks at the simulated frequencies (cycles per MS line = f * line period).
    period = ms.info["line_period_s"]
    freqs = np.fft.rfftfreq(l.size)
    sim_f = [j[2] * period for j in ms.true.attitude.jitter]
    for d in dj:
        spec = np.abs(np.fft.rfft((d - d.mean()) * np.hanning(l.size)))
        peak = freqs[np.argmax(spec[1:]) + 1]
        assert min(abs(peak - f) for f in sim_f) < 2.0 / l.size
    # Without jitter, the field along a line is smooth (a cubic in l up to the terrain's ~0.005 px RMS).
    for with_j, scene in ((True, full), (False, full_nojitter)):
        for d in true_misregistration(scene, np.full(l.shape, col), l):
            rms = np.sqrt(np.mean((d - np.polyval(np.polyfit(l, d, 3), l)) ** 2))
            assert (rms > 0.015) if with_j else (rms < 0.006)


def test_scenes_sharing_the_camera_share_the_piecewise_truth(full):
    other = make_gf7_scene(seed=2, center=(113.6, 22.9))
    foreign = make_gf7_scene(seed=1, camera_seed=5, size=(256, 256))
    for name in ("pan", "ms"):
        a, b = full.image(name).true.camera, other.image(name).true.camera
        assert np.array_equal(a.coef_x, b.coef_x) and np.array_equal(a.coef_y, b.coef_y)
        assert not np.allclose(a.coef_x, foreign.image(name).true.camera.coef_x)
    # Different exterior (orbit, attitude, linear truth), same jumps: the difference of the two fields has none.
    assert full.image("ms").errors["linear_truth"] != other.image("ms").errors["linear_truth"]
    s = np.array([e + o for e in EDGES for o in (-2.5, 2.5)])   # the MS and the pan jump between them
    l = np.full(s.shape, 3840.5)
    d1, d2 = true_misregistration(full, s, l), true_misregistration(other, s, l)
    for a, b in zip(d1, d2):
        ja, jb = a[1::2] - a[::2], b[1::2] - b[::2]
        assert np.all(np.abs(ja) > 0.0) and np.max(np.abs(ja - jb)) < 0.01


@pytest.fixture(scope="module")
def edge_crop():
    # A small crop centred on the first MS sub-CCD edge (pan 1024^2, MS 256^2), cloudy and watery.
    return make_gf7_scene(seed=3, size=(1024, 1024), crop_center_ms_px=2560, clouds=0.2, water=0.1)


def test_rpc_fits_within_methods_3(edge_crop):
    for name in ("pan", "ms"):
        _, rep = fit_rpc_from_model(edge_crop.image(name).current)
        assert rep.check.max_px <= 0.01 and rep.check.rms_px <= 0.002


def test_deterministic(edge_crop):
    again = make_gf7_scene(seed=3, size=(1024, 1024), crop_center_ms_px=2560, clouds=0.2, water=0.1)
    assert json.dumps(again.truth, sort_keys=True, default=str) == json.dumps(edge_crop.truth, sort_keys=True,
                                                                              default=str)
    s, l = np.array([10.5, 127.5, 128.5, 250.5]), np.array([5.5, 100.5, 100.5, 200.5])
    for a, b in zip(true_misregistration(again, s, l), true_misregistration(edge_crop, s, l)):
        assert np.array_equal(a, b)


def test_cover_shares(edge_crop):
    W, H = edge_crop.image("ms").size
    s, l = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    lon, lat, _ = edge_crop.image("ms").true.localize_dem(s, l, edge_crop.dem)
    c = cover_class(edge_crop, lon, lat)
    assert abs((c == 1).mean() - 0.2) < 0.05 and abs((c == 2).mean() - 0.1) < 0.05


def test_truth_file_matches_the_function(edge_crop, tmp_path):
    path = write_misregistration_truth(edge_crop, tmp_path / "truth.tif", step=4, tile=128)
    ds = gdal.Open(str(path))
    assert (ds.RasterXSize, ds.RasterYSize, ds.RasterCount) == (256, 256, 2)
    assert ds.GetRasterBand(1).DataType == gdal.GDT_Float32
    grid = ds.ReadAsArray()
    assert edge_crop.image("ms").true.camera.edges_in_image() == [128.0]
    rng = np.random.default_rng(0)
    i, j = rng.integers(0, 256, 400), rng.integers(0, 256, 400)
    i = np.concatenate([i, [50, 50, 200, 200]])
    j = np.concatenate([j, [126, 129, 126, 129]])                # both sides of the edge
    exact = true_misregistration(edge_crop, j + 0.5, i + 0.5)
    edge = np.abs(j - 127.5) < 1                                 # the pixels next to the edge (pan jump)
    for band in range(2):
        err = np.abs(grid[band][i, j] - exact[band])
        assert np.max(err[~edge]) < 2e-3 and np.max(err[edge]) < 0.15
    jump = np.hypot(grid[0][:, 128] - grid[0][:, 127], grid[1][:, 128] - grid[1][:, 127])
    smooth = np.hypot(grid[0][:, 127] - grid[0][:, 126], grid[1][:, 127] - grid[1][:, 126])
    assert jump.min() > 0.1 and smooth.max() < 5e-3


def _bilinear(img, s, l):
    from scipy.ndimage import map_coordinates
    return map_coordinates(img.astype(float), [l - 0.5, s - 0.5], order=1, mode="nearest")


@pytest.mark.parametrize("real", [False, True])
def test_write_gf7_scene_renders_pan_and_ms_with_the_true_misregistration(tmp_path, real):
    reference = None
    if real:
        reference = _georeferenced_pleiades(tmp_path)
    out = tmp_path / "gf7"
    res = write_gf7_scene(out, seed=3, size=(512, 512), crop_center_ms_px=2560, clouds=0.15, n_gcps=10,
                          tile=128, reference=reference)
    truth = json.loads((out / "truth.json").read_text())
    assert truth["gf7"]["options"]["clouds"] == 0.15 and truth["gf7"]["files"]["misregistration_truth"]
    pan = gdal.Open(str(out / "pan" / "scene.tif")).ReadAsArray().astype(float)
    ms = gdal.Open(str(out / "ms" / "scene.tif")).ReadAsArray().astype(float)
    mask = gdal.Open(str(out / "ms" / "cover_mask.tif")).ReadAsArray()
    assert pan.shape == (512, 512) and ms.shape == (4, 128, 128)
    assert 0.05 < (mask == 1).mean() < 0.3
    for k in range(4):
        # Textured where clear; flat (one value) in the clouds but for their soft rims.
        vals, counts = np.unique(ms[k][mask == 1], return_counts=True)
        assert ms[k][mask == 0].std() > 5 and counts.max() > 0.7 * counts.sum()
    # Through the RPCs (current models) and the DEM, pan pixels land in the MS where the MS shows that ground
    # only after adding the true misregistration: the MS band mean agrees better with the pan there.
    sc = res.scene
    panim, msim = sc.image("pan"), sc.image("ms")
    p = np.meshgrid(np.arange(40, 472, 4) + 2.0, np.arange(40, 472, 4) + 2.0)
    ps, pl = p[0].ravel(), p[1].ravel()
    lon, lat, h = panim.current.localize_dem(ps, pl, sc.dem)
    s2, l2 = msim.current.project(lon, lat, h)
    ds, dl = true_misregistration(sc, s2, l2)        # at the predicted point; ~ at the true one (smooth field)
    from scipy.ndimage import uniform_filter
    pan4 = uniform_filter(pan, 4)                     # the pan at MS resolution around each pan point
    pv = pan4[pl.astype(int), ps.astype(int)]
    msmean = ms.mean(axis=0)
    ok = (mask[np.clip(l2.astype(int), 0, 127), np.clip(s2.astype(int), 0, 127)] == 0)
    e_before = np.abs(_bilinear(msmean, s2, l2) - pv)[ok]
    e_after = np.abs(_bilinear(msmean, s2 + ds, l2 + dl)[ok] - pv[ok])
    assert np.mean(e_after) < 0.8 * np.mean(e_before)


def _georeferenced_pleiades(tmp_path):
    """The real Pleiades crop (tests/data/matching) as a texture: an EPSG:4326 copy spread over the scene."""
    from pathlib import Path
    from gdal_gf4cal.simulate.gf7 import make_gf7_scene as mk
    from gdal_gf4cal.simulate.render import model_bounds
    sc = mk(seed=3, size=(512, 512), crop_center_ms_px=2560)
    b = model_bounds(sc.image("pan").true, margin=0.05)
    src = Path(__file__).parents[1] / "data" / "matching" / "pleiades_ventoux_left.tif"
    dst = str(tmp_path / "ref.tif")
    ds = gdal.Translate(dst, str(src), outputSRS="EPSG:4326", outputBounds=[b[0], b[3], b[2], b[1]])
    ds = None
    return dst


def test_field_at_predicted_points(edge_crop):
    s, l = np.array([20.5, 100.25, 200.75]), np.array([30.5, 128.0, 250.5])
    ds, dl = true_misregistration(edge_crop, s, l)
    ps, pl = true_misregistration(edge_crop, s - ds, l - dl, at="predicted")
    assert np.max(np.abs(ps - ds)) < 1e-6 and np.max(np.abs(pl - dl)) < 1e-6
    # Through the fitted RPCs instead of the current models: the same field to the RPC fit error (METHODS §3).
    rpc_pan, _ = fit_rpc_from_model(edge_crop.image("pan").current)
    rpc_ms, _ = fit_rpc_from_model(edge_crop.image("ms").current)
    rs, rl = true_misregistration(edge_crop, s, l, pan_model=rpc_pan, ms_model=rpc_ms)
    assert np.max(np.abs(rs - ds)) < 0.01 and np.max(np.abs(rl - dl)) < 0.01
