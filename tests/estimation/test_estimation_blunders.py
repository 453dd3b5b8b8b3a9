"""Blunder breakdown through ``gf4cal refine`` (issue 10 "Must show"): simulated GCP sets with known truth.

The truth is the real WV3 RPC of ``tests/data/compensation/md_dg.RPB`` with a known affine image-space error; GCPs
are drawn from it (seeded, 0.5 px noise), blunders of 20-100 px in random directions (or one coherent 12 px
offset) are put on control points. Every blunder must be flagged and the check-point RMS after compensation must
stay within 1.5x of the same set without blunders.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from gcpsim import gcps_from_truth
from gdal_gf4cal import RPCModel
from gdal_gf4cal.cli import main
from gdal_gf4cal.compensation import CompensatedRPC, CompensationResult

RPB = Path(__file__).parents[1] / "data" / "compensation" / "md_dg.RPB"
NOISE_PX = 0.5
N_CHECK = 20


@pytest.fixture(scope="module")
def truth():
    rpc = RPCModel.from_file(RPB)
    frame = (rpc.samp_off + 0.5, rpc.samp_scale, rpc.line_off + 0.5, rpc.line_scale)
    # affine error: shift (7, -5) px, scale/shear of a few px at the image edges
    corr = CompensationResult.from_coefficients("affine", frame, [7.0, 3.0, -1.5], [-5.0, 1.0, 2.5])
    return rpc, CompensatedRPC(rpc, corr)


def _gcps(truth, n_control: int, seed: int) -> pd.DataFrame:
    rpc, true_model = truth
    h0 = float(rpc.height_off)
    table, _ = gcps_from_truth(true_model, n_control + N_CHECK, size=rpc.image_size, heights=(h0 - 50, h0 + 50),
                               sigma_px=NOISE_PX, seed=seed, n_control=n_control, with_sigma=False)
    table["id"] = [f"G{i:02d}" for i in range(len(table))]
    return table


def _refine(tab: pd.DataFrame, tmp_path: Path, name: str, capsys=None) -> dict:
    csv = tmp_path / f"{name}.csv"
    tab.to_csv(csv, index=False)
    rep = tmp_path / f"{name}.json"
    code = main(["refine", str(RPB), "--gcps", str(csv), "--model", "affine", "--out", str(tmp_path / f"{name}.RPB"),
                 "--report", str(rep)])
    assert code == 0
    return json.loads(rep.read_text())


def _check_rms(rep: dict) -> float:
    a = rep["check"]["after"]
    return float(np.hypot(a["sample"]["rms"], a["line"]["rms"]))


@pytest.mark.parametrize("n_control, n_blunders, seed", [(7, 2, 1), (10, 3, 2), (40, 12, 3)])
def test_random_blunders_are_all_flagged(truth, tmp_path, n_control, n_blunders, seed):
    clean = _gcps(truth, n_control, seed)
    rep0 = _refine(clean, tmp_path, "clean")
    rng = np.random.default_rng(100 + seed)
    bad = rng.choice(n_control, n_blunders, replace=False)
    size = rng.uniform(20, 100, n_blunders)
    ang = rng.uniform(0, 2 * np.pi, n_blunders)
    tab = clean.copy()
    tab.loc[bad, "sample"] += size * np.cos(ang)
    tab.loc[bad, "line"] += size * np.sin(ang)
    rep = _refine(tab, tmp_path, "blunders")
    flagged = {o["id"] for o in rep["outliers"]}
    assert {f"G{i:02d}" for i in bad} <= flagged
    assert len(flagged) <= n_blunders + 1                   # at most one good point lost
    assert _check_rms(rep) <= 1.5 * _check_rms(rep0)
    assert _check_rms(rep0) < 2.0 * NOISE_PX                 # noise-only result is itself sound
    assert rep["warnings"] == []


@pytest.mark.parametrize("n_control, n_blunders, seed", [(20, 6, 4), (30, 12, 5)])
def test_coherent_blunders_are_all_flagged(truth, tmp_path, n_control, n_blunders, seed):
    """30-40 % of the control points off by the SAME 12 px (issue 11): a second, consistent model."""
    clean = _gcps(truth, n_control, seed)
    rep0 = _refine(clean, tmp_path, "clean")
    bad = np.random.default_rng(200 + seed).choice(n_control, n_blunders, replace=False)
    tab = clean.copy()
    tab.loc[bad, "sample"] += 12.0 / np.sqrt(2)
    tab.loc[bad, "line"] -= 12.0 / np.sqrt(2)
    rep = _refine(tab, tmp_path, "coherent")
    flagged = {o["id"] for o in rep["outliers"]}
    assert {f"G{i:02d}" for i in bad} <= flagged
    assert _check_rms(rep) <= 1.5 * _check_rms(rep0)


def test_check_point_blunder_flagged_and_worse_checks_warned(truth, tmp_path, capsys):
    tab = _gcps(truth, 10, 6)
    # A check point blunder is flagged by the same test ...
    tab.loc[12, "sample"] += 40.0
    rep = _refine(tab, tmp_path, "check_blunder")
    assert "G12" in {o["id"] for o in rep["outliers"] if o["role"] == "check"}
    # ... and check points that fit worse after than before give a warning in the report and on the CLI.
    worse = _gcps(truth, 10, 7)
    rpc, _ = truth
    s, l = rpc.project(worse["lon"].to_numpy(), worse["lat"].to_numpy(), worse["h"].to_numpy())
    chk = (worse["role"] == "check").to_numpy()
    # check points measured where the uncorrected RPC puts them (a different error than the control points')
    worse.loc[chk, "sample"], worse.loc[chk, "line"] = s[chk], l[chk]
    capsys.readouterr()
    rep = _refine(worse, tmp_path, "worse")
    assert rep["warnings"] and "20 of the 20 check points are flagged" in rep["warnings"][0]
    assert "gf4cal: warning: 20 of the 20 check points are flagged" in capsys.readouterr().err
    # check points only slightly off (not flagged) but worse after than before: the rms warning
    mild = _gcps(truth, 10, 8)
    from gdal_gf4cal.compensation import fit_compensation
    res = fit_compensation(rpc, mild, "affine")
    tab = res.gcps.copy()
    for axis in ("sample", "line"):                                   # after worse than before by construction
        tab[f"res_{axis}_after"] = tab[f"res_{axis}_before"].abs() + 1.0
    from gdal_gf4cal.compensation import check_point_warnings
    assert any("fit worse after compensation" in w for w in check_point_warnings(tab))


def test_compensation_result_is_an_estimate(truth):
    from gdal_gf4cal.compensation import fit_compensation
    rpc, _ = truth
    tab = _gcps(truth, 12, 9)
    tab.loc[[2, 5], "sample"] += 40.0
    res = fit_compensation(rpc, tab, "affine")
    est = res.estimate
    assert est.names == res.parameter_names and est.block("line").tolist() == res.coef_line.tolist()
    assert est.outlier.sum() == 2 and est.outlier[[2, 5]].all()
    assert set(est.outlier_level[[2, 5]]) <= {"start", "snooping"}
    # redundancy numbers of the 10 points in the estimate add up to the degrees of freedom (2 x (10 - 3))
    assert est.dof == 14 and est.redundancy.sum() == pytest.approx(14.0, abs=1e-9)
    assert np.all(est.weights.reshape(-1, 2)[[2, 5]] == 0)
