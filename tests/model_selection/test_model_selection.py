"""``--model auto`` (METHODS §4, §6): translation for a shift plus noise, affine for an affine error, and why."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from gdal_gf4cal import RPCModel
from gdal_gf4cal.cli import main
from gdal_gf4cal.model_selection import select_model

DATA = Path(__file__).parents[1] / "data" / "compensation"


def _gcps(kind: str, n: int, seed: int) -> tuple:
    """``n`` control GCPs on a 2000 x 2000 px part of the real WV3 RPC, image error ``kind`` + 0.3 px noise."""
    rpc = RPCModel.from_file(DATA / "md_dg.RPB")
    rng = np.random.default_rng(seed)
    s0, l0 = rpc.samp_off - 1000, rpc.line_off - 1000
    s, l = s0 + rng.uniform(0, 2000, n), l0 + rng.uniform(0, 2000, n)
    h = rng.uniform(80, 230, n)
    lon, lat = rpc.localize(s, l, h)
    ds, dl = np.full(n, 4.0), np.full(n, -3.0)                 # the shift
    if kind == "affine":                                       # plus 6 px of scale/rotation across the part
        u, v = (s - rpc.samp_off) / 1000.0, (l - rpc.line_off) / 1000.0
        ds += 3.0 * u + 2.0 * v
        dl += -2.0 * u + 3.0 * v
    noise = rng.normal(0.0, 0.3, (2, n))
    tab = pd.DataFrame({"id": [f"P{i}" for i in range(n)], "lon": lon, "lat": lat, "h": h,
                        "sample": s + ds + noise[0], "line": l + dl + noise[1], "role": "control"})
    return rpc, tab


@pytest.mark.parametrize("n", [5, 8, 10])
def test_auto_picks_translation_for_a_shift(n):
    rpc, tab = _gcps("shift", n, seed=n)
    sel = select_model(rpc, tab)
    assert sel.chosen == "translation", sel.reason
    assert sel.reason.startswith("translation:") and "leave-one-out" in sel.reason
    t = sel.candidates["translation"]
    assert t["scored"] and 0.2 < t["loo_rms_px"] < 0.8          # the 0.3 px noise per axis, radial, loo-inflated
    assert list(sel.candidates)[:2] == ["translation", "shift-drift"]


@pytest.mark.parametrize("n", [6, 8, 10])
def test_auto_picks_affine_for_an_affine_error(n):
    rpc, tab = _gcps("affine", n, seed=n)
    sel = select_model(rpc, tab)
    assert sel.chosen == "affine", sel.reason
    a, t = sel.candidates["affine"], sel.candidates["translation"]
    assert a["loo_rms_px"] < 0.8 * t["loo_rms_px"] and a["p_value"] < 0.01
    assert a["loo_rms_px"] < 1.0 and t["loo_rms_px"] > 2.0
    assert "affine:" in sel.reason and "F-test" in sel.reason


def test_refine_cli_model_auto_reports_the_choice(tmp_path, capsys):
    rpc, tab = _gcps("affine", 9, seed=1)
    tab.to_csv(tmp_path / "gcps.csv", index=False)
    rpc.write_rpb(tmp_path / "in.RPB")
    rc = main(["refine", str(tmp_path / "in.RPB"), "--gcps", str(tmp_path / "gcps.csv"), "--out",
               str(tmp_path / "out.RPB"), "--report", str(tmp_path / "report.json")])
    assert rc == 0
    out = capsys.readouterr().out
    assert "model auto -> affine:" in out
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["model_selection"]["chosen"] == "affine" and rep["model"]["name"] == "affine"
    assert set(rep["model_selection"]["candidates"]) == {"translation", "shift-drift", "affine", "poly2"}
