"""``gf4cal experiment jl1``: block calibration of a simulated Jilin-1 group and its validation (seed 003, Tables 3-6)
on a small crop with 2 orbits and 1 scene with 5 GCPs (the full run: 10 orbits, 5 scenes)."""
from __future__ import annotations

import numpy as np
import pytest

from gdal_gf4cal.workflows import run_experiment

pytestmark = pytest.mark.slow


def test_tables(tmp_path, capsys):
    rep = run_experiment("jl1", tmp_path / "exp", n_orbits=2, n_scenes=1, size=(256, 128))
    out = capsys.readouterr().out
    assert "Table 3" in out and "Table 6" in out
    t3 = rep["table3_calibration"]
    assert len(t3) == 20
    for n, v in t3.items():                                     # calibration accuracy against the truth
        scale = 0.25 if "_" not in n else 1.0                   # pan px -> MS px
        assert v["truth_rms_px_after"] * scale <= 0.1 < v["truth_rms_px_before"], n
    assert np.sqrt(np.mean([v["after_ms_px"] ** 2 for v in rep["table4_band_to_band"].values()])) <= 0.1
    t5 = rep["table5_orbits"]                                   # no control: what the orbits' errors imply
    assert abs(t5["ce90_m"] - t5["implied_ce90_m"]) <= 0.1 * t5["implied_ce90_m"]
    assert all(o["band_to_band_mean_px"] <= 0.1 for o in t5["orbits"])
    assert all(s["check_planar_rms_m"] <= 2.0 and s["n_check"] >= 10 for s in rep["table6_scenes"])
