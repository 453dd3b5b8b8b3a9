"""``gf4cal experiment gf7`` (seed 004, METHODS §9): the paper's Tables 2-3, the jitter step and the cloudy scene
behave as the paper says, on simulated GF7 scenes with known truth."""
from __future__ import annotations

import json

import pytest

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def rep(tmp_path_factory):
    from gdal_gf4cal.workflows import run_experiment
    out = tmp_path_factory.mktemp("gf7")
    r = run_experiment("gf7", out / "exp", verbose=False)
    assert json.loads((out / "exp" / "report.json").read_text())["table2"]
    return r


def test_table2_stepwise(rep):
    for rows in rep["table2"].values():
        assert rows["before"]["p_le_0.25"] < 0.01 and rows["before"]["rms_sample_px"] > 0.4
        assert rows["linear"]["p_le_0.25"] < 0.85 and rows["linear"]["rms_sample_px"] < 0.2
        assert rows["piecewise"]["p_le_0.25"] > 0.97
        assert rows["piecewise"]["rms_sample_px"] < 0.5 * rows["linear"]["rms_sample_px"]


def test_jitter_step_lowers_rms_with_the_simulated_frequencies(rep):
    for r in rep["jitter"].values():
        for ax in ("sample", "line"):
            assert r["jitter"][f"rms_{ax}_px"] < 0.8 * r["piecewise"][f"rms_{ax}_px"]
        sim = sorted(c["frequency_hz"] for c in r["simulated"] if c["axis"] == "sample")
        got = sorted(c["frequency_hz"] for c in r["components"]["sample"])
        assert len(got) == len(sim) and max(abs(a - b) for a, b in zip(got, sim)) < 0.05


def test_table3_reuse_within_10_percent_of_solve(rep):
    for r in rep["table3"].values():
        for ax in ("sample", "line"):
            assert r["reuse"][f"rms_{ax}_px"] <= 1.1 * r["solve"][f"rms_{ax}_px"]
        assert r["reuse"]["p_le_0.25"] >= 0.98


def test_cloudy_scene_better_without_cloudy_cells(rep):
    c = rep["cloudy"]
    assert 0.15 < c["cloudy_share"] < 0.5
    assert c["clear_cells"]["p_le_0.25"] > 0.9 > c["all_cells"]["p_le_0.25"]
