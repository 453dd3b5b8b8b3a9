"""Issue 19: plausibility by the RPC's own domain and GCP heights against the DEM (METHODS §4, §6).

A real QuickBird-2 RPC cut to an 850 x 1450 px crop (tests/cropsim.py): field GCPs up to 35 % of the crop's size
outside it are used, with a warning naming them; the same points 3 image sizes away are refused naming the
override; heights in feet or on another vertical datum than the DEM's are refused where the RPC's height range
alone lets them through."""
from __future__ import annotations

import json
import subprocess
import sys
import warnings

import numpy as np
import pytest

import cropsim as C


@pytest.fixture(scope="module")
def crop(tmp_path_factory):
    d = tmp_path_factory.mktemp("crop")
    img, dem = C.write_crop(str(d))
    return d, img, dem


def _run(*args):
    return subprocess.run([sys.executable, "-m", "gdal_gf4cal.cli", *map(str, args)], capture_output=True, text=True)


def _refused(proc, out, *words):
    assert proc.returncode == 2, proc.stdout + proc.stderr
    err = [ln for ln in proc.stderr.strip().splitlines() if not ln.startswith("gf4cal: warning:")]
    assert len(err) == 1 and "Traceback" not in proc.stderr, proc.stderr
    for w in words:
        assert w in err[0], err[0]
    assert not out.exists() or not any(out.iterdir())
    return err[0]


@pytest.mark.parametrize("ortho", [False, True])
def test_field_gcps_outside_a_crop_are_used_with_a_warning(crop, tmp_path, ortho):
    d, img, dem = crop
    csv = tmp_path / "g.csv"
    C.gcps().to_csv(csv, index=False)
    out = tmp_path / "out"
    extra = ["--ortho", out / "ortho.tif"] if ortho else []
    proc = _run("refine", img, "--gcps", csv, "--dem", dem, "--out", out / "x.RPB", "--report", out / "r.json",
                *extra)
    assert proc.returncode == 0, proc.stderr
    rep = json.loads((out / "r.json").read_text())
    # all 10 are control points (4 outside the crop), none flagged: the known bias is recovered by translation
    assert rep["control"]["before"]["n"] == 10 and not rep["outliers"]
    assert rep["model"]["name"] == "translation"
    p = rep["model"]["parameters_px"]
    assert abs(p["sample_1"] - C.BIAS[0]) < 0.25 and abs(p["line_1"] - C.BIAS[1]) < 0.25, p
    assert rep["control"]["after"]["sample"]["rms"] < 0.35 and rep["control"]["after"]["line"]["rms"] < 0.35
    warn = [w for w in rep["warnings"] if "outside the 850 x 1450 px image" in w]
    assert len(warn) == 1 and "4 of 10 GCPs" in warn[0], rep["warnings"]
    for gid, where in (("F7", "284 px right"), ("F8", "184 px left"), ("F9", "505 px below"),
                       ("F10", "437 px above")):
        assert f"{gid} (" in warn[0] and where in warn[0], warn[0]
    assert "F3 (" not in warn[0]
    if ortho:
        assert (out / "ortho.tif").exists() and rep["ortho"]


def test_the_same_points_three_image_sizes_away_are_refused(crop, tmp_path):
    d, img, dem = crop
    csv = tmp_path / "far.csv"
    C.gcps(far=3.0).to_csv(csv, index=False)
    out = tmp_path / "out"
    msg = _refused(_run("refine", img, "--gcps", csv, "--dem", dem, "--out", out / "x.RPB"), out,
                   "4 of 10 GCPs", "F7", "--no-plausibility-check", "image sizes out")
    assert "3.3 image sizes out" in msg or "3.4 image sizes out" in msg, msg
    # the override lets an expert through
    proc = _run("refine", img, "--gcps", csv, "--dem", dem, "--out", out / "x.RPB", "--no-plausibility-check",
                "--model", "translation")
    assert proc.returncode == 0, proc.stderr


@pytest.mark.parametrize("case, words", [("feet", ("feet", "--no-plausibility-check")),
                                         ("datum", ("+31.0 m", "vertical datum", "--no-plausibility-check"))])
def test_heights_against_the_dem(crop, tmp_path, case, words):
    """Terrain 300-380 m: in feet (985-1250) the GCPs stay inside the RPC's height range -404..598 +/- 1000 m, so
    only the DEM sees it; 31 m above the DEM everywhere (orthometric vs ellipsoidal) likewise."""
    d, img, dem = crop
    tab = C.gcps()
    tab["h"] = tab["h"] / 0.3048 if case == "feet" else tab["h"] + 31.0
    csv = tmp_path / "g.csv"
    tab.to_csv(csv, index=False)
    out = tmp_path / "out"
    _refused(_run("refine", img, "--gcps", csv, "--dem", dem, "--out", out / "x.RPB"), out, *words)
    # without a DEM the range test is what there is: these heights pass it
    from gdal_gf4cal.plausibility import check_gcps_against
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert check_gcps_against(C.crop_rpc(), tab, C.SIZE)["n_outside_used"] == 4


def test_heights_with_dem_noise_pass(crop):
    """Surveyed heights scatter a few metres about the DEM, some DEM-filled: nothing to refuse."""
    from gdal_gf4cal.dem import DEM
    from gdal_gf4cal.plausibility import check_heights_against_dem
    tab = C.gcps()
    rng = np.random.default_rng(1)
    tab["h"] += rng.normal(0, 4.0, len(tab))
    check_heights_against_dem(tab, DEM.from_file(crop[2]))
    tab["h"] += 8.0                             # a consistent 8 m: below a geoid's size, not judged
    check_heights_against_dem(tab, DEM.from_file(crop[2]))


def test_outside_the_rpc_domain_is_refused_inside_the_use_margin():
    """The product's own RPC: a point 30 % right of the product lies within half an image size but beyond the
    RPC's validity box (normalised sample 1.6 > 1.1)."""
    from gdal_gf4cal.errors import GCPError
    from gdal_gf4cal.plausibility import check_gcps_against
    from gdal_gf4cal.rpc import RPCModel
    full = RPCModel.from_file(C.DATA + "/rpc/rpc.vrt")
    tab = C.gcps()
    tab["sample"] += C.ORIGIN[0]
    tab["line"] += C.ORIGIN[1]
    W, H = full.image_size
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_gcps_against(full, tab, (W, H))           # inside the product: no warning at all
    tab.loc[2, "sample"] = 1.3 * W
    with pytest.raises(GCPError, match=r"1 of 10 GCPs .*RPC's domain \(F3; .*--no-plausibility-check"):
        check_gcps_against(full, tab, (W, H))
