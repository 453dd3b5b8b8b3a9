"""Jilin-1 group simulator (METHODS §8, §10): overlapping yaw-steered CCDs, MS bands, interior/exterior truth,
per-orbit attitude errors and the long observation table of GCPs and tie points."""
from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from gdal_gf4cal.rpc_fit import fit_rpc_from_model
from gdal_gf4cal.simulate import SENSORS, SimulationError, make_scene
from gdal_gf4cal.simulate.geodesy import geodetic_to_ecef
from gdal_gf4cal.simulate.jl1 import (ARCSEC, BANDS, MS_BANDS, MS_FACTOR, OBSERVATION_COLUMNS, _seam_vector,
                                      block_observations, build_jl1, image_name, overlap_width_px)

SIZE = (1024, 512)


@pytest.fixture(scope="module")
def crop():
    return make_scene("jl1", seed=5, size=SIZE)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """A scene written through the CLI (small crop, validation orbit)."""
    from gdal_gf4cal.cli import main
    out = tmp_path_factory.mktemp("jl1") / "scene"
    assert main(["simulate", "--sensor", "jl1", "--out", str(out), "--seed", "2", "--size", "768", "256",
                 "--n-gcps", "8", "--gcp-noise", "0.2", "--orbit-seed", "7", "--n-ties", "30",
                 "--tie-noise", "0.1"]) == 0
    return out


def _pairs(images_by_name):
    for band in BANDS:
        for k in range(1, 4):
            yield band, images_by_name[image_name(k, band)], images_by_name[image_name(k + 1, band)]


def _overlaps_pan_px(images, h):
    by = {im.name: im for im in images}
    out = []
    for band, left, right in _pairs(by):
        f = 1 if band == "pan" else MS_FACTOR
        w = overlap_width_px(left, right, h) * f
        out.append((band, left.name, float(np.min(w)), float(np.max(w))))
    return out


def test_names_sizes_and_registry(crop):
    names = [im.name for im in crop.images]
    assert tuple(names) == SENSORS["jl1"].images
    assert names[:4] == ["ccd1", "ccd2", "ccd3", "ccd4"] and "ccd3_nir" in names and len(names) == 20
    for im in crop.images:
        band = im.info["band"]
        f = 1 if band == "pan" else MS_FACTOR
        assert im.size == (SIZE[0] // f, SIZE[1] // f)
        assert im.gsd_m == pytest.approx(0.75 * f)
        gx, gy = im.info["gsd_center_m"]
        assert abs(gx - 0.75 * f) < 0.02 * f and abs(gy - 0.75 * f) < 0.02 * f


@pytest.mark.parametrize("center", [(125.3, 43.9), (10.0, 0.0), (-60.0, -45.0), (20.0, 70.0), (30.0, -78.0),
                                    (100.0, 80.0), (-120.0, -80.0)])
def test_adjacent_ccds_overlap_at_every_latitude(center):
    h = 400.0
    images = build_jl1(np.random.default_rng(1), center, (1024, 256), h)
    for band, name, lo, hi in _overlaps_pan_px(images, h):
        assert 150 <= lo and hi <= 400, (center, band, name, lo, hi)


def test_full_size_keeps_overlaps_and_stagger():
    h = 400.0
    images = build_jl1(np.random.default_rng(3), (-70.0, -35.0), None, h)
    by = {im.name: im for im in images}
    assert by["ccd1"].size == (8192, 8192) and by["ccd1_red"].size == (2048, 2048)
    for band, name, lo, hi in _overlaps_pan_px(images, h):
        assert 150 <= lo and hi <= 400, (band, name, lo, hi)
    # adjacent CCDs see the same ground ~0.6 s apart (staggered rows), the bands of a CCD within 0.2 s
    t = {n: im.info["t_center_s"] for n, im in by.items()}
    for k in range(1, 4):
        assert 0.5 < abs(t[f"ccd{k}"] - t[f"ccd{k + 1}"]) < 0.7
        assert 0.05 < abs(t[f"ccd{k}_blue"] - t[f"ccd{k}"]) < 0.2


def test_centre_beyond_the_orbit_is_refused():
    with pytest.raises(SimulationError, match="lat"):
        make_scene("jl1", seed=0, size=(256, 64), center=(0.0, 83.0))
    with pytest.raises(SimulationError, match="orbit_seed"):
        make_scene("zy3", seed=0, size=(64, 64), options={"orbit_seed": 1})


def test_seams_are_2_to_5_px_and_recorded(crop):
    h = float(np.mean(crop.images[0].true.height_range))
    by = {im.name: im for im in crop.images}
    recorded = crop.truth["block"]["seams_px"]
    assert len(recorded) == 15
    for band, left, right in _pairs(by):
        S = _seam_vector(left, right, h)
        assert 2.0 <= np.hypot(*S) <= 5.0, (band, left.name, S)
        assert np.allclose(S, recorded[f"{left.name}|{right.name}"], atol=0.1)


def test_interior_truth_is_the_recorded_cubic(crop):
    """true camera at s == current camera at s - I_s(u) across track; along track tan_y differs by -ifov I_l(u)."""
    for im in crop.images:
        W = im.size[0]
        s = np.linspace(0, W, 33)
        u = (s - W / 2) / (W / 2)
        i_s = np.polyval(im.errors["interior_sample_px_poly"][::-1], u)
        i_l = np.polyval(im.errors["interior_line_px_poly"][::-1], u)
        ifov = im.info["ifov_rad"]
        tx_t, ty_t = im.true.camera.tan_angles(s, 0 * s)
        tx_c, ty_c = im.current.camera.tan_angles(s - i_s, 0 * s)
        assert np.max(np.abs(tx_t - tx_c)) / ifov < 1e-6
        assert np.max(np.abs((ty_t - im.current.camera.tan_angles(s, 0 * s)[1]) / ifov + i_l)) < 1e-6
        fp = im.errors["focal_plane"]
        assert fp["X_px_poly"][1] == W / 2 and fp["Y_px"] == pytest.approx(im.info["view_tan_y"] / ifov)


def test_exterior_is_shared_and_has_the_papers_terms(crop):
    block = crop.truth["block"]
    ext = block["exterior"]
    assert set(ext) >= {"roll_rad", "roll_drift_rad_s", "pitch_rad", "pitch_drift_rad_s", "yaw_rad"}
    assert 2 * ARCSEC <= abs(ext["roll_rad"]) <= 6 * ARCSEC and 20 * ARCSEC <= abs(ext["yaw_rad"]) <= 60 * ARCSEC
    att = {id(im.true.attitude) for im in crop.images}
    assert len(att) == 1                                   # one exterior for every CCD and band of the group
    a = crop.images[0].true.attitude
    assert a.roll[1] == ext["roll_drift_rad_s"] and a.yaw[0] == pytest.approx(block["yaw_steering_rad"] +
                                                                                 ext["yaw_rad"])
    assert block["orbit_attitude_error"]["orbit_seed"] is None


def test_per_orbit_attitude_error_moves_the_ground_as_designed():
    """3.6 arcsec per axis on top of the group's exterior; the ground of the centre pixel moves by alt x angle."""
    size, h = (256, 64), 300.0
    base = {im.name: im for im in build_jl1(np.random.default_rng(4), (125.3, 43.9), size, h)}["ccd2"]
    shifts, predicted = [], []
    for orbit_seed in range(3):
        ims = build_jl1(np.random.default_rng(4), (125.3, 43.9), size, h, orbit_seed=orbit_seed)
        im = {i.name: i for i in ims}["ccd2"]
        err = im.info["group"]["orbit_attitude_error"]
        assert err["orbit_seed"] == orbit_seed and err["sigma_arcsec"] == 3.6
        # interior unchanged: the orbit error is exterior only
        assert im.errors["interior_sample_px_poly"] == base.errors["interior_sample_px_poly"]
        W, H = im.size
        P0 = geodetic_to_ecef(*base.true.localize(W / 2, H / 2, h), h)
        P1 = geodetic_to_ecef(*im.true.localize(W / 2, H / 2, h), h)
        shifts.append(np.linalg.norm(P1 - P0))
        predicted.append(535e3 * np.hypot(err["roll_rad"], err["pitch_rad"]))
    assert np.allclose(shifts, predicted, rtol=0.05, atol=0.3)
    # the population: CE90 = 2.146 sigma of a circular normal with sigma = 535 km x 3.6" (METHODS §8: ~20 m)
    assert 2.146 * 535e3 * 3.6 * ARCSEC == pytest.approx(20.0, abs=0.1)


def test_deterministic_for_a_seed(crop):
    again = make_scene("jl1", seed=5, size=SIZE)
    assert json.dumps(again.truth["block"], sort_keys=True, default=str) == \
        json.dumps(crop.truth["block"], sort_keys=True, default=str)
    for a, b in zip(again.images, crop.images):
        assert a.errors == b.errors
    o1 = block_observations(crop, n_gcps=5, n_overlap_ties=10, n_band_ties=10)
    o2 = block_observations(again, n_gcps=5, n_overlap_ties=10, n_band_ties=10)
    pd.testing.assert_frame_equal(o1, o2)
    other = make_scene("jl1", seed=6, size=SIZE)
    assert other.images[0].errors != crop.images[0].errors


def test_rpc_fit_of_every_ccd_and_band_crop(written):
    truth = json.loads((written / "truth.json").read_text())
    assert len(truth["images"]) == 20
    for name, rec in truth["images"].items():
        assert rec["rpc_fit"]["check"]["max_px"] <= 0.01 and rec["rpc_fit"]["check"]["rms_px"] <= 0.002, name
        assert (written / name / "scene.RPB").exists()


def test_rpc_fit_full_size_pan_and_ms():
    images = {im.name: im for im in build_jl1(np.random.default_rng(8), (125.3, 43.9), None, 400.0)}
    for name in ("ccd1", "ccd4_nir"):
        model = images[name].current
        model.height_range = (0.0, 900.0)
        _, rep = fit_rpc_from_model(model)
        assert rep.check.max_px <= 0.01 and rep.check.rms_px <= 0.002, name


def test_observation_table_written_with_truth(written):
    obs = pd.read_csv(written / "observations.csv", dtype={"point_id": str})
    assert list(obs.columns) == OBSERVATION_COLUMNS
    truth = json.loads((written / "truth.json").read_text())
    assert truth["files"]["observations"] == "observations.csv"
    assert truth["block"]["orbit_attitude_error"]["orbit_seed"] == 7
    assert truth["observations"]["tie_noise_px"] == 0.1 and truth["observations"]["n_rows"] == len(obs)
    assert set(obs["kind"]) == {"gcp", "tie"} and set(obs["role"]) <= {"control", "check"}
    assert set(obs["image_id"]) == set(truth["images"])
    # GCP rows are the per-image gcps.csv rows
    g = obs[(obs.kind == "gcp") & (obs.image_id == "ccd2_red")]
    per_image = pd.read_csv(written / "ccd2_red" / "gcps.csv", dtype={"id": str})
    assert sorted(g.point_id) == sorted(per_image.id)
    ties = obs[obs.kind == "tie"]
    assert ties[["lon", "lat", "h"]].isna().all().all()
    # tie noise: 0.1 px per axis
    d = np.concatenate([ties["sample"] - ties["truth_sample"], ties["line"] - ties["truth_line"]])
    assert 0.09 < np.std(d) < 0.11 and abs(np.mean(d)) < 0.01
    # every tie point links >= 2 images; overlap ties link adjacent CCDs of one band, band ties one CCD's bands
    for pid, grp in ties.groupby("point_id"):
        assert len(grp) >= 2 and grp.image_id.is_unique
        ccd = grp.image_id.str.extract(r"ccd(\d)")[0].astype(int)
        if pid.startswith("T"):
            assert len(grp) == 2 and abs(ccd.iloc[0] - ccd.iloc[1]) == 1
            assert len({n.partition("_")[2] for n in grp.image_id}) == 1
        else:
            assert ccd.nunique() == 1 and any(n.endswith("_blue") for n in grp.image_id)
    n_overlap = ties[ties.point_id.str.startswith("T")].point_id.nunique()
    assert n_overlap == 15 * 30                                          # 3 overlaps x 5 bands x 30


def test_tie_truth_is_consistent_through_the_true_models(written):
    """Localise a tie's truth position in one image on the DEM (true model) and project it into the others."""
    from gdal_gf4cal.simulate import make_scene as _ms
    from gdal_gf4cal.dem import DEM
    truth = json.loads((written / "truth.json").read_text())
    sc = _ms("jl1", seed=truth["seed"], size=truth["size"], options={"orbit_seed": 7})
    dem = DEM.from_file(str(written / "dem.tif"))
    by = {im.name: im for im in sc.images}
    obs = pd.read_csv(written / "observations.csv", dtype={"point_id": str})
    ties = obs[obs.kind == "tie"]
    first = ties.groupby("point_id").head(1)
    rest = ties[~ties.index.isin(first.index)].merge(first[["point_id", "image_id", "truth_sample", "truth_line"]],
                                                     on="point_id", suffixes=("", "_0"))
    worst = 0.0
    for (name0, name1), grp in rest.groupby(["image_id_0", "image_id"]):
        m0 = by[name0].true
        lon, lat, h = m0.localize_dem(grp.truth_sample_0.to_numpy(), grp.truth_line_0.to_numpy(), dem)
        s, l = by[name1].true.project(lon, lat, h)
        worst = max(worst, float(np.max(np.hypot(s - grp.truth_sample, l - grp.truth_line))))
        # the recorded true ground point projects to the recorded truth position
        s2, l2 = by[name1].true.project(grp.truth_lon.to_numpy(), grp.truth_lat.to_numpy(), grp.truth_h.to_numpy())
        assert np.max(np.hypot(s2 - grp.truth_sample, l2 - grp.truth_line)) < 1e-4
    assert worst < 2e-3


def test_band_ties_cover_every_ms_band(written):
    obs = pd.read_csv(written / "observations.csv", dtype={"point_id": str})
    band_ties = obs[obs.point_id.str.startswith("B")]
    for k in range(1, 5):
        for b in ("pan",) + MS_BANDS:
            assert (band_ties.image_id == image_name(k, b)).sum() >= 15, (k, b)


def test_truth_is_inside_the_rpc_space_model(crop):
    """METHODS §8: true - current = exterior (constant + linear in time) + cubic interior in u, per image: that
    model leaves < 0.01 px of the several-px truth, so a block adjustment can reach it."""
    sizes = []
    for im in crop.images:
        W, H = im.size
        s, l = (a.ravel() for a in np.meshgrid(np.linspace(0, W, 21), np.linspace(0, H, 21)))
        lon, lat, h = im.current.localize_dem(s, l, crop.dem)
        ts, tl = im.true.project(lon, lat, h)
        u, v = (s - W / 2) / (W / 2), (l - H / 2) / (H / 2)
        A = np.column_stack([u ** 0, u, u ** 2, u ** 3, v])
        for d in (ts - s, tl - l):
            sizes.append(np.sqrt(np.mean(d ** 2)))
            left = d - A @ np.linalg.lstsq(A, d, rcond=None)[0]
            assert np.sqrt(np.mean(left ** 2)) < 0.01, im.name
    assert max(sizes) > 3.0


def test_tie_blunders_are_marked(crop):
    clean = block_observations(crop, n_gcps=5, n_overlap_ties=20, n_band_ties=20, tie_noise_px=0.0)
    obs = block_observations(crop, n_gcps=5, n_overlap_ties=20, n_band_ties=20, tie_noise_px=0.0,
                             tie_outlier_fraction=0.05)
    ties = obs[obs.kind == "tie"]
    n_points = ties.point_id.nunique()
    bad = ties[ties.truth_outlier]
    assert len(bad) == round(0.05 * n_points) and bad.point_id.is_unique
    off = np.hypot(bad["sample"] - bad.truth_sample, bad["line"] - bad.truth_line)
    assert off.min() >= 5.0 and off.max() <= 50.0
    good = ties[~ties.truth_outlier]
    assert np.allclose(good["sample"], good.truth_sample) and np.allclose(good["line"], good.truth_line)
    assert len(clean) == len(obs) and not clean.truth_outlier.any()


def test_tiny_crop_whose_true_ms_projection_leaves_the_crop():
    """Seed 43 at 128 x 64 (MS 32 x 16): some seam points' true projections left the crop (NaN), the seam vector
    became NaN and the scene failed ("camera coefficients 'x' must be 10 finite numbers"). Now it builds and its
    seams are 2-5 px where the seam is measurable."""
    sc = make_scene("jl1", seed=43, size=(128, 64))
    by = {im.name: im for im in sc.images}
    h = float(np.mean(sc.images[0].true.height_range))
    for band, left, right in _pairs(by):
        S = _seam_vector(left, right, h)
        assert np.all(np.isfinite(S)) and np.hypot(*S) <= 5.0 + 1e-6, (band, left.name, S)
