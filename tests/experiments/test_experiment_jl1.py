"""``gf4cal experiment jl1``: the paper's validation of the Jilin-1 block calibration on simulated truth (seed 003,
issue 12, METHODS §8): Tables 3-6 printed, report.json / tables.txt / calibration.json written under one output
folder, and the issue's numbers (interior <= 0.1 px with tie noise 0.1 px and GCP noise 0.2 px, band-to-band
<= 0.1 px, CE90 of 10 orbits without control within 10 % of what their attitude errors imply, <= 2 m check RMS with
5 GCPs per scene at 0.75 m GSD)."""
from __future__ import annotations

import json

import pytest

from gdal_gf4cal.cli import main
from gdal_gf4cal.experiments import jl1


def _check(rep, *, ce90_tol=0.10):
    s = rep["summary"]
    assert rep["gcp_noise_px"] == 0.2 and rep["tie_noise_px"] == 0.1
    # Table 3: every CCD and band recalibrated to <= 0.1 px RMS per axis against the true model (paper < 0.3 px),
    # from 1.5-15 px before; close to the floor the noise allows
    for name, v in rep["table3"].items():
        assert max(v["before"]["across"], v["before"]["along"]) > 0.5, name
        assert v["after"]["across"] <= 0.1 and v["after"]["along"] <= 0.1, (name, v["after"])
    assert s["interior_max_rms_px"] <= 0.1
    # Table 4: bands register to <= 0.1 px of the MS band (paper < 0.3 px), from ~1-5 px before
    for ccd, row in rep["table4"].items():
        for band, v in row.items():
            assert v["before"] > 0.5 and v["after"] <= 0.1, (ccd, band, v)
    # Table 5: without control, the error is what the orbits' attitude errors imply (within 10 %), ~20 m (paper)
    t5 = rep["table5"]["summary"]
    assert abs(t5["ratio"] - 1.0) <= ce90_tol
    assert 15.0 <= t5["expected_ce90_m"] <= 25.0
    assert t5["band_to_band_max_px"] <= 0.15
    # Table 6: 5 GCPs per scene and >= 10 check points: check planar RMS <= 2 m at 0.75 m GSD (paper < 2 m)
    for sc in rep["table6"]["scenes"]:
        assert sc["n_control"] == 5 and sc["n_check"] >= 10
        assert sc["after"]["planar_rms_m"] <= 2.0
        assert sc["after"]["planar_rms_m"] < sc["before"]["planar_rms_m"]
    assert rep["table6"]["summary"]["gsd_m"] == pytest.approx(0.75)


@pytest.mark.slow
def test_jl1_small_group_through_the_cli(tmp_path, capsys):
    """A small crop of every CCD (256 x 128 pan px), through the CLI: tables printed, files written."""
    assert main(["experiment", "jl1", "--size", "256", "128", "--out", str(tmp_path), "--quiet"]) == 0
    out = capsys.readouterr().out
    for title in ("Table 3.", "Table 4.", "Table 5.", "Table 6.", "CE90 / implied"):
        assert title in out
    rep = json.loads((tmp_path / "report.json").read_text())
    assert (tmp_path / "tables.txt").read_text().strip() == jl1.format_tables(rep).strip()
    assert json.loads((tmp_path / "calibration.json").read_text())["model"] == "block-rpc-cubic"
    assert len(rep["table5"]["orbits"]) == 10 and len(rep["table6"]["scenes"]) == 5
    assert set(rep["table3"]) == {f"ccd{k}" for k in range(1, 5)} | {f"ccd{k}_{b}" for k in range(1, 5)
                                                                      for b in ("blue", "green", "red", "nir")}
    _check(rep)
    # an existing, non-empty folder is refused without --overwrite (one line, exit 2), and kept
    assert main(["experiment", "jl1", "--size", "256", "128", "--out", str(tmp_path), "--quiet"]) == 2
    assert "exist" in capsys.readouterr().err.lower()
    assert (tmp_path / "report.json").exists()


def test_experiment_refuses_an_option_it_does_not_take(tmp_path, capsys):
    assert main(["experiment", "hj1", "--size", "256", "128", "--out", str(tmp_path / "x"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "size" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_jl1_default_group_meets_the_issue_numbers(tmp_path):
    """The default crop (512 x 256 pan px per CCD): the issue's numbers."""
    rep = jl1.run(tmp_path, verbose=False)
    _check(rep)
