"""``workflows.bundle_adjust`` from files (issue 22): views given as RPC files alone with a tie table, GCPs from the
same table; the written RPCs are the engine's corrected models; outputs refused over existing files and beside the
images (a sidecar GDAL would read as the image's RPC); the pair chooser and the prior option."""
from __future__ import annotations

import os

import numpy as np
import pytest

import ventouxpair as V
from gdal_gf4cal import RPCModel
from gdal_gf4cal.bundle import adjust_views, corrected_models
from gdal_gf4cal.errors import GCPError, Gf4calError, InputOverwriteError
from gdal_gf4cal.rpc_io import write_rpb
from gdal_gf4cal.simulate.views import simulate_views
from gdal_gf4cal.workflows import bundle_adjust
from gdal_gf4cal.workflows.bundle import Views, choose_pairs, parse_prior_sigma


@pytest.fixture(scope="module")
def tri(tmp_path_factory):
    """A simulated tri-stereo (seed 3, 200 ties at 0.2 px, 3 control + 3 check GCPs) written as three .RPB files
    and one observation table."""
    d = tmp_path_factory.mktemp("tri")
    sim = simulate_views("tri-stereo", n_ties=200, n_gcps=3, n_check=3, noise_px=0.2, seed=3)
    paths = []
    for v, m in sim.models.items():
        paths.append(str(d / f"{v}.RPB"))
        write_rpb(m, paths[-1])
    obs = d / "observations.csv"
    sim.observations.drop(columns=["true_sample", "true_line"]).to_csv(obs, index=False)
    return sim, paths, obs, d


def test_rpc_files_alone_with_a_tie_table(tri):
    sim, paths, obs, d = tri
    rep = bundle_adjust(paths, ties=obs, gcps=obs, out=d / "out")
    assert sorted(os.listdir(d / "out")) == ["bwd.RPB", "fwd.RPB", "nadir.RPB", "report.json", "residuals.gpkg",
                                             "ties.png"]
    assert rep["ties"]["n_points"] == 200 and rep["ties"]["n_gcps"] == 6
    assert rep["model_used"] == {"fwd": "affine", "nadir": "affine", "bwd": "affine"}
    assert all(v["image_size"] is None and "vrt" not in v for v in rep["views"].values())
    # the files are the engine's corrected models of the same inputs
    est = adjust_views(sim.observations, sim.models, model="affine", sizes=sim.sizes)
    expected = corrected_models(est, sim.models)
    p = sim.points
    for v in sim.models:
        got = RPCModel.from_file(d / "out" / f"{v}.RPB")
        a = np.c_[got.project(p["lon"].to_numpy(), p["lat"].to_numpy(), p["h"].to_numpy())]
        b = np.c_[expected[v].project(p["lon"].to_numpy(), p["lat"].to_numpy(), p["h"].to_numpy())]
        assert np.max(np.abs(a - b)) < 1e-6
        assert rep["views"][v]["rpc"]["refit_max_px"] < 1e-3
    assert rep["reprojection_px"]["after"]["all"] == pytest.approx(est.reprojection["after"]["all"])
    # against the truth: across track (sample; along-track stereo) each view agrees with the first within 0.1 px
    # at every true point (the along-track part trades against the points' heights)
    err = {}
    for v in sim.models:
        got = RPCModel.from_file(d / "out" / f"{v}.RPB")
        s, _ = got.project(p["lon"].to_numpy(), p["lat"].to_numpy(), p["h"].to_numpy())
        ts, _ = sim.true_image(v, p["lon"].to_numpy(), p["lat"].to_numpy(), p["h"].to_numpy())
        err[v] = ts - s
    assert max(np.max(np.abs(err[v] - err["fwd"])) for v in sim.models) < 0.1
    assert rep["reprojection_px"]["before"]["all"] > 5 * rep["reprojection_px"]["after"]["all"]


def test_existing_outputs_refused_then_replaced(tri):
    sim, paths, obs, d = tri
    out = d / "again"
    bundle_adjust(paths, ties=obs, model="translation", out=out)
    stamp = {f: os.stat(out / f).st_mtime_ns for f in os.listdir(out)}
    with pytest.raises(InputOverwriteError, match="--overwrite"):
        bundle_adjust(paths, ties=obs, model="translation", out=out)
    assert {f: os.stat(out / f).st_mtime_ns for f in os.listdir(out)} == stamp
    rep = bundle_adjust(paths, ties=obs, model="shift-drift", out=out, overwrite=True)
    assert set(rep["model_used"].values()) == {"shift-drift"}


def test_outputs_beside_the_images_are_refused(tmp_path):
    left, right = V.pair(tmp_path)
    before = sorted(os.listdir(tmp_path))
    with pytest.raises(Gf4calError, match="left.RPB"):
        bundle_adjust([left, right], match_ties=True, dem=str(V.SRTM), geoid="egm96", out=tmp_path)
    assert sorted(os.listdir(tmp_path)) == before


def test_choose_pairs_joins_every_view_first():
    keys = ["a", "b", "c", "d"]
    overlaps = [(0.9, "a", "b"), (0.4, "a", "c"), (0.5, "b", "c"), (0.1, "c", "d"), (0.3, "b", "d")]
    assert choose_pairs(overlaps, keys) == [("a", "b"), ("b", "c"), ("b", "d"), ("a", "c"), ("c", "d")]
    assert choose_pairs(overlaps, keys, 4) == [("a", "b"), ("b", "c"), ("b", "d"), ("a", "c")]
    assert choose_pairs(overlaps, keys, 1) == [("a", "b"), ("b", "c"), ("b", "d")]     # never fewer than a tree
    with pytest.raises(GCPError, match="view d overlaps no other view"):
        choose_pairs(overlaps[:3], keys)
    with pytest.raises(GCPError, match=r"2 groups that overlap nowhere on the ground \(a, b \| c, d\)"):
        choose_pairs([(0.9, "a", "b"), (0.2, "c", "d")], keys)


def test_prior_sigma_option():
    views = Views(keys=["left", "right"], paths=["/x/left.tif", "/x/right.tif"], models={}, sizes={})
    assert parse_prior_sigma(None, views) is None
    assert parse_prior_sigma(["4"], views) == 4.0
    assert parse_prior_sigma(["right=100"], views) == {"right": 100.0}
    assert parse_prior_sigma(["2", "right.tif=100"], views) == {"left": 2.0, "right": 100.0}
    with pytest.raises(GCPError, match="'middle', which is not among"):
        parse_prior_sigma(["middle=3"], views)
    with pytest.raises(GCPError, match="positive"):
        parse_prior_sigma(["right=-1"], views)
