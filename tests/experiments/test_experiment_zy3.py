"""``gf4cal experiment zy3``: bias compensation and stereo accuracy of a simulated ZY-3 triplet (seed 001)."""
from __future__ import annotations

import json

import numpy as np

from gdal_gf4cal.cli import main
from gdal_gf4cal.experiments.zy3 import spread_order


def test_zy3_table(tmp_path, capsys):
    assert main(["experiment", "zy3", "--out", str(tmp_path), "--quiet"]) == 0
    assert "nadir+fwd+bwd" in capsys.readouterr().out
    rep = json.loads((tmp_path / "report.json").read_text())
    t = rep["table"]
    combos = ["nadir+fwd", "nadir+bwd", "fwd+bwd", "nadir+fwd+bwd"]
    assert set(t) == {"translation", "shift-drift", "affine"} and rep["n_field"] == 24
    for model in t:
        assert set(t[model]) == {str(n) for n in range(0, 13)}
        for n in range(0, 13):
            row = t[model][str(n)]
            if "skipped" in row:
                continue
            for c in combos:
                assert row[c]["n_check"] == 24 - n
                assert row[c]["planar_rms_m"] > 0 and row[c]["height_rms_m"] > 0
    # Each model declares its minimum: shift-drift needs 2 GCPs, affine 3.
    assert "skipped" in t["shift-drift"]["1"] and "skipped" in t["affine"]["2"] and "skipped" not in t["affine"]["3"]
    no, one = t["translation"]["0"], t["translation"]["1"]
    # One GCP with the translation model removes most of the (mostly shift) error, above all in height.
    assert one["nadir+fwd+bwd"]["planar_rms_m"] < no["nadir+fwd+bwd"]["planar_rms_m"]
    assert one["nadir+fwd+bwd"]["height_rms_m"] < 0.5 * no["nadir+fwd+bwd"]["height_rms_m"]
    # With 12 GCPs the affine model is at the noise level of the intersection (predicted precision).
    for c in combos:
        r = t["affine"]["12"][c]
        assert r["planar_rms_m"] < 2.0 * r["predicted_planar_m"] and r["height_rms_m"] < 2.0 * r["predicted_height_m"]
    # More GCPs help: averaged over the combinations, 12 control points beat 3.
    mean = lambda row: np.mean([row[c]["planar_rms_m"] ** 2 + row[c]["height_rms_m"] ** 2 for c in combos])  # noqa
    assert mean(t["affine"]["12"]) < mean(t["affine"]["3"])
    # Geometry: forward+backward (largest intersection angle) is the most precise pair in height; the triplet is
    # the most precise in planimetry.
    pred_h = {c: no[c]["predicted_height_m"] for c in combos}
    assert pred_h["fwd+bwd"] < min(pred_h["nadir+fwd"], pred_h["nadir+bwd"])
    pred_p = {c: no[c]["predicted_planar_m"] for c in combos}
    assert pred_p["nadir+fwd+bwd"] == min(pred_p.values())
    # And so it is, once the bias is compensated.
    a = t["affine"]["12"]
    assert a["fwd+bwd"]["height_rms_m"] < min(a["nadir+fwd"]["height_rms_m"], a["nadir+bwd"]["height_rms_m"])


def test_spread_order_is_well_spread():
    g = np.arange(5.0)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    order = spread_order(x, y)
    assert sorted(order) == list(range(25)) and (x[order[0]], y[order[0]]) == (2.0, 2.0)
    corners = {(x[i], y[i]) for i in order[1:5]}
    assert corners == {(0.0, 0.0), (4.0, 0.0), (0.0, 4.0), (4.0, 4.0)}
