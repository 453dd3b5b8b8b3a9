"""Issue 19, block-adjust: every observation checked against its image as ``refine`` checks GCPs (refused: exit 2,
one line, nothing written), and no interior polynomial extrapolated beyond the detector range its observations
cover (METHODS §8). On the seeded simulated Jilin-1 group of tests/blocksim.py, its four blue CCD images
(128 x 64 px each; GCP heights 545-636 m, DEM 150-700 m)."""
import json
import os

import numpy as np
import pandas as pd
import pytest

import blocksim as B
import gdal_gf4cal.block as engine
from gdal_gf4cal.cli import main
from gdal_gf4cal.observations import validate_observations
from gdal_gf4cal.rpc import RPCModel
from gdal_gf4cal.workflows.block import check_observations

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return B.block_scene(str(tmp_path_factory.getbasetemp()))


def _ref_obs(scene):
    """The blue CCDs' observations (ties with >= 2 rays among them)."""
    t = pd.read_csv(os.path.join(scene, "observations.csv"), dtype={"point_id": str})
    t = t[t["image_id"].isin(B.REF)]
    return t[(t["kind"] == "gcp") | (t.groupby("point_id")["image_id"].transform("size") >= 2)].copy()


def _args(scene, obs):
    return [B.image_path(scene, n) for n in B.REF] + ["--dem", os.path.join(scene, "dem.tif"), "--gcps", obs,
                                                       "--ties", obs]


def _fails(args, capsys, out):
    assert main(["block-adjust", *args, "--out", out]) == 2
    err = [ln for ln in capsys.readouterr().err.strip().splitlines() if not ln.startswith("gf4cal: warning:")]
    assert len(err) == 1 and err[0].startswith("gf4cal: ")
    assert not os.path.exists(out)
    return err[0]


def test_ties_5000px_outside_their_image_are_refused(scene, tmp_path, capsys):
    t = _ref_obs(scene)
    rows = t.index[(t["image_id"] == "ccd2_blue") & (t["kind"] == "tie")][:30]
    t.loc[rows, "sample"] += 5000.0
    obs = str(tmp_path / "obs.csv")
    t.to_csv(obs, index=False)
    msg = _fails(_args(scene, obs), capsys, str(tmp_path / "out"))
    assert "ccd2_blue" in msg and "30 of" in msg and "tie points" in msg and "--no-plausibility-check" in msg, msg
    # a few stray measurements just outside are blunders for the robust adjustment (a warning), not a refusal
    t = _ref_obs(scene)
    models = {n: RPCModel.from_file(B.image_path(scene, n)) for n in B.REF}
    sizes = {n: (128, 64) for n in B.REF}
    tab = validate_observations(t, need_height=False)
    tab.loc[tab.index[(tab["image_id"] == "ccd2_blue") & (tab["kind"] == "tie")][:2], "line"] += 60.0
    with pytest.warns(UserWarning, match="2 of .* tie points of ccd2_blue .* left to the robust adjustment"):
        check_observations(tab, models, sizes)


@pytest.mark.parametrize("case, words", [("feet", ("feet",)), ("datum", ("vertical datum", "-35.0 m"))])
def test_gcp_heights_in_feet_or_on_another_datum_are_refused(scene, tmp_path, capsys, case, words):
    t = _ref_obs(scene)
    g = t["kind"] == "gcp"
    t.loc[g, "h"] = t.loc[g, "h"] / 0.3048 if case == "feet" else t.loc[g, "h"] - 35.0
    obs = str(tmp_path / "obs.csv")
    t.to_csv(obs, index=False)
    msg = _fails(_args(scene, obs), capsys, str(tmp_path / "out"))
    assert all(w in msg for w in words) and "--no-plausibility-check" in msg, msg


def test_interior_not_extrapolated_beyond_the_observed_detector_range(scene, tmp_path, capsys, monkeypatch):
    """ccd1_blue observed on its last 28 of 128 columns only (its overlap with ccd2_blue): its interior is held to a
    constant, not a cubic extrapolated over the detector. Seeded: 1.2 px rms over the image against the truth
    (4.9 px before); the unconstrained cubic 15.6 px (35 px at worst), with NumPy overflows on the way."""
    t = _ref_obs(scene)
    t = t[~((t["image_id"] == "ccd1_blue") & (t["sample"] < 100.0))]
    t = t[(t["kind"] == "gcp") | (t.groupby("point_id")["image_id"].transform("size") >= 2)]
    obs = str(tmp_path / "obs.csv")
    t.to_csv(obs, index=False)
    errors = {}
    for label, limit in (("held", engine.MAX_EXTRAPOLATION_VARIANCE), ("free", np.inf)):
        monkeypatch.setattr(engine.coverage, "MAX_EXTRAPOLATION_VARIANCE", limit)   # where it is read
        out = str(tmp_path / label)
        assert main(["block-adjust", *_args(scene, obs), "--out", out]) == 0
        err = capsys.readouterr().err
        e = B.errors_vs_truth(out, scene, names=B.REF)
        errors[label] = {n: B.rms(e[n]["after"]) for n in B.REF}
        errors[label]["before"] = B.rms(e["ccd1_blue"]["before"])
        with open(os.path.join(out, "calibration.json")) as fh:
            inter = json.load(fh)["images"]["ccd1_blue"]["interior"]
        with open(os.path.join(out, "report.json")) as fh:
            rep = json.load(fh)
        if label == "held":
            assert all(inter[k] == 0.0 for k in ("a1", "a2", "a3", "b1", "b2", "b3")), inter
            w = [x for x in rep["warnings"] if x.startswith("ccd1_blue: the observations cover detector columns")]
            assert len(w) == 1 and "degree 0" in w[0] and "of 128 (2" in w[0], rep["warnings"]
            assert "overflow" not in err
            assert all(rep["images"][n]["rpc_fit"]["check"]["max_px"] < 0.01 for n in B.REF), rep["images"]
    held, free = errors["held"], errors["free"]
    assert held["ccd1_blue"] < 2.0 < 4.0 < held["before"], held
    assert free["ccd1_blue"] > 5 * held["ccd1_blue"], (held, free)
    # the other CCDs, fully observed, are as good either way
    assert all(held[n] < 0.15 and free[n] < 0.15 for n in B.REF[1:]), (held, free)


@pytest.mark.parametrize("lo, hi, degree", [(-1.0, 1.0, 3), (-0.875, 0.676, 3), (-0.6, 0.6, 2), (-0.3, 0.3, 1),
                                            (-1.0, 0.0, 1), (0.56, 1.0, 0), (0.96, 1.0, 0)])
def test_supported_degree_by_coverage(lo, hi, degree):
    """The degree a detector coverage supports (leverage over the detector <= 25 x the worst at an observation):
    a cubic from ~70 % centred or 78 % from one edge (the matched-ties test's last CCD), a slope from a third."""
    u = np.random.default_rng(1).uniform(lo, hi, 100)
    assert engine.supported_degree(u) == degree
    assert engine.supported_degree(u[:2], 3) <= 1 and engine.supported_degree(np.full(5, 0.3)) == 0
