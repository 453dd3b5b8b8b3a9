"""``gf4cal experiment hj1``: basic model vs detector polynomials on a simulated HJ-1A CCD scene (seed 002)."""
from __future__ import annotations

import json

import numpy as np

from gdal_gf4cal.cli import main
from gdal_gf4cal.experiments import hj1


def test_hj1_detector_polynomial_reaches_the_floor(tmp_path, capsys):
    assert main(["experiment", "hj1", "--out", str(tmp_path), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "order3" in out and "cross-track" in out
    rep = json.loads((tmp_path / "report.json").read_text())
    for name in ("basic", "order3", "order6"):
        for role in ("control", "check"):
            for axis in ("cross_track", "along_track"):
                assert set(rep["models"][name][role][axis]) >= {"rms", "max"}
    assert rep["n_control"] == 41 and rep["n_check"] == 119
    m = rep["models"]
    ct = {k: m[k]["check"]["cross_track"]["rms"] for k in ("basic", "order3", "order6", "floor")}
    # The basic model leaves a large systematic cross-track error ...
    assert ct["basic"] > 1.2 * ct["order3"]
    assert m["basic"]["check"]["cross_track"]["max"] > 1.5 * m["order3"]["check"]["cross_track"]["max"]
    # ... that grows toward the swath edges, while the cubic's residuals are flat across the swath.
    prof = rep["profile"]["cross_track_rms_px"]
    basic, cubic = np.array(prof["basic"]), np.array(prof["order3"])
    assert max(basic[0], basic[-1]) > 1.25 * np.mean(basic[2:4])
    assert max(cubic[0], cubic[-1]) < 1.15 * np.mean(cubic[2:4])
    # Order 3 reaches the floor (noise + attitude oscillation, no function of the detector position) ...
    assert ct["order3"] <= 1.1 * ct["floor"]
    # ... and order 6 is no better.
    assert ct["order6"] >= 0.95 * ct["order3"]
    # Along-track is untouched by the cross-track polynomial.
    assert m["order3"]["check"]["along_track"] == m["basic"]["check"]["along_track"]
    assert (tmp_path / "hj1_cross_track_residuals.png").stat().st_size > 10000


def test_hj1_other_seed_same_conclusions(tmp_path):
    rep = hj1.run(tmp_path, seed=1, write_files=False, verbose=False)
    ct = {k: rep["models"][k]["check"]["cross_track"]["rms"] for k in ("basic", "order3", "order6", "floor")}
    assert ct["basic"] > 1.2 * ct["order3"] and ct["order3"] <= 1.1 * ct["floor"] and ct["order6"] >= 0.95 * ct["order3"]
