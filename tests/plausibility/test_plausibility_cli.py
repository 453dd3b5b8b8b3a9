"""Issue 11 through ``gf4cal refine``: GCPs that cannot belong to the image are refused (exit 2, one line, nothing
written), and weak layouts are refused with their propagated uncertainty in px (METHODS §4.3, §6)."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from gcpsim import gcps_from_truth

BIAS = (40.0, -30.0)          # a real RPC bias (sample, line) px: must pass


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A simulated GF4 scene (10,240 x 10,240 px, fixed seed) written through the public CLI."""
    out = tmp_path_factory.mktemp("scene")
    proc = subprocess.run([sys.executable, "-m", "gdal_gf4cal.cli", "simulate", "--sensor", "gf4", "--out", str(out),
                           "--n-gcps", "40", "--seed", "3", "--no-reference-ortho"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return out


@pytest.fixture(scope="module")
def rpc(scene):
    from gdal_gf4cal import RPCModel
    return RPCModel.from_file(scene / "scene.RPB")


def _gcps(rpc, n=30, layout=None, seed=5, sigma_px=0.25):
    """GCPs from the scene's RPC as truth, measured with ``sigma_px`` noise and the known bias ``BIAS``."""
    tab, _ = gcps_from_truth(rpc, n, size=(10240, 10240), heights=(3500, 6000), sigma_px=sigma_px, seed=seed,
                             layout=layout)
    tab["sample"] += BIAS[0]
    tab["line"] += BIAS[1]
    return tab.drop(columns=["truth_sample", "truth_line"])


def _refine(scene, gcps, tmp_path, *extra):
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "gdal_gf4cal.cli", "refine", str(scene / "scene.tif"), "--gcps",
                           str(gcps), "--out", str(out / "x.RPB"), "--report", str(out / "report.json"), *extra],
                          capture_output=True, text=True)
    return proc, out


def _refused(proc, out, *words):
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    for w in words:
        assert w in lines[0], lines[0]
    assert not out.exists() or not any(out.iterdir())


def test_clean_set_with_a_40px_bias_passes(scene, rpc, tmp_path):
    csv = tmp_path / "g.csv"
    _gcps(rpc).to_csv(csv, index=False)
    proc, out = _refine(scene, csv, tmp_path, "--model", "affine")
    assert proc.returncode == 0, proc.stderr
    assert "correction uncertainty over the image" in proc.stdout
    rep = json.loads((out / "report.json").read_text())
    pr = rep["precision_px"]
    # 30 spread GCPs, 0.25 px noise, affine: the correction is known to a fraction of a pixel everywhere
    assert 0.05 < pr["max"] < 0.5 and pr["rms"] < pr["max"]
    assert rep["control"]["before"]["sample"]["rms"] == pytest.approx(BIAS[0], abs=1.0)
    assert rep["control"]["before"]["line"]["rms"] == pytest.approx(-BIAS[1], abs=1.0)
    assert rep["control"]["after"]["sample"]["rms"] < 0.4 and rep["control"]["after"]["line"]["rms"] < 0.4
    assert not any("uncertain" in w for w in rep["warnings"])


def test_point_30000px_outside_a_10240px_image(scene, rpc, tmp_path):
    tab = _gcps(rpc)
    tab.loc[3, "sample"] = 30000.0
    csv = tmp_path / "g.csv"
    tab.to_csv(csv, index=False)
    _refused(*_refine(scene, csv, tmp_path, "--model", "affine"), "outside the 10240 x 10240 px image", "g3")


def test_swapped_lon_lat_is_named(scene, rpc, tmp_path):
    tab = _gcps(rpc)
    tab["lon"], tab["lat"] = tab["lat"].to_numpy(), tab["lon"].to_numpy()
    csv = tmp_path / "g.csv"
    tab.to_csv(csv, index=False)
    _refused(*_refine(scene, csv, tmp_path, "--model", "affine"), "swapped")


def test_wrong_crs_geopackage(scene, rpc, tmp_path):
    import geopandas as gpd
    tab = _gcps(rpc)
    g = gpd.GeoDataFrame(tab.drop(columns=["lon", "lat"]), geometry=gpd.points_from_xy(tab["lon"], tab["lat"]),
                         crs="EPSG:4326").to_crs("EPSG:32645")
    g = g.set_crs("EPSG:32644", allow_override=True)            # the wrong UTM zone declared
    path = tmp_path / "g.gpkg"
    g.to_file(path, driver="GPKG")
    _refused(*_refine(scene, path, tmp_path, "--model", "affine"), "check the layer's CRS")


@pytest.mark.parametrize("case, words", [("1e6", ("height range", "1e+06")), ("feet", ("feet",))])
def test_implausible_heights(scene, rpc, tmp_path, case, words):
    tab = _gcps(rpc)
    if case == "1e6":
        tab.loc[0, "h"] = 1e6
    else:
        tab["h"] = tab["h"] / 0.3048
    csv = tmp_path / "g.csv"
    tab.to_csv(csv, index=False)
    _refused(*_refine(scene, csv, tmp_path, "--model", "affine"), *words)


def _collinear(rng, n):
    t = rng.uniform(0.1, 0.9, n)
    return 10240 * t, 10240 * t + rng.normal(0, 15, n)          # along the diagonal, +/-15 px across


def _corner(rng, n):
    return rng.uniform(0, 1500, n), rng.uniform(0, 1500, n)


@pytest.mark.parametrize("model, layout", [("affine", _collinear), ("poly2", _corner)])
def test_weak_layout_refused_with_its_uncertainty(scene, rpc, tmp_path, model, layout):
    from gdal_gf4cal.compensation import fit_compensation
    from gdal_gf4cal.plausibility import correction_precision
    tab = _gcps(rpc, n=20, layout=layout)
    csv = tmp_path / "g.csv"
    tab.to_csv(csv, index=False)
    proc, out = _refine(scene, csv, tmp_path, "--model", model)
    _refused(proc, out, "uncertain by up to", "simpler model", "--max-uncertainty")
    # the uncertainty is real: the true error of the correction (known bias) is of the same size
    res = fit_compensation(rpc, tab, model)
    prec = correction_precision(res, (10240, 10240))
    ss, ll = np.meshgrid(np.linspace(0, 10240, 21), np.linspace(0, 10240, 21))
    ds, dl = res.correction(ss, ll)
    true_err = np.hypot(ds - BIAS[0], dl - BIAS[1])
    # (seeded: collinear affine 62 px propagated / 64 px true, 1,500 px corner poly2 94 / 69 px)
    assert prec["max"] > 30 and true_err.max() > 30
    assert 0.5 * prec["max"] < true_err.max() < 2 * prec["max"]
    # raising the threshold lets the expert through, with the uncertainty reported
    proc, out = _refine(scene, csv, tmp_path, "--model", model, "--max-uncertainty", str(2 * prec["max"]))
    assert proc.returncode == 0, proc.stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["precision_px"]["max"] == pytest.approx(prec["max"], rel=1e-6)
    assert any("uncertain by up to" in w for w in rep["warnings"])
    # and the clean spread passes with the same model
    good = tmp_path / "good.csv"
    _gcps(rpc, n=20).to_csv(good, index=False)
    proc, out = _refine(scene, good, tmp_path / "g2", "--model", model)
    assert proc.returncode == 0, proc.stderr


def test_opt_out_for_experts(scene, rpc, tmp_path):
    tab = _gcps(rpc)
    tab.loc[0, "h"] = 1e6
    from gdal_gf4cal.errors import GCPError
    from gdal_gf4cal.workflows import refine_rpc
    with pytest.raises(GCPError, match="height range"):
        refine_rpc(scene / "scene.tif", tab, "affine", out=tmp_path / "a.RPB")
    assert not (tmp_path / "a.RPB").exists()
    rep = refine_rpc(scene / "scene.tif", tab, "affine", out=tmp_path / "b.RPB", check_plausibility=False)
    assert (tmp_path / "b.RPB").exists() and "precision_px" in rep


@pytest.mark.parametrize("job", ["calibrate", "assess"])
def test_calibrate_and_assess_refuse_swapped_gcps(scene, rpc, tmp_path, job):
    from gdal_gf4cal.errors import GCPError
    from gdal_gf4cal.workflows import assess_accuracy, calibrate_lookangle_files
    tab = _gcps(rpc, n=40)
    tab["lon"], tab["lat"] = tab["lat"].to_numpy(), tab["lon"].to_numpy()
    out = tmp_path / "o"
    with pytest.raises(GCPError, match="swapped"):
        if job == "calibrate":
            calibrate_lookangle_files(scene / "scene.RPB", tab, scene / "camera_current.json", out)
        else:
            assess_accuracy(scene / "scene.tif", tab, report=out / "a.json")
    assert not out.exists() or not any(out.iterdir())


def test_check_gcps_against_margins(rpc):
    """The engine function alone: the stated margins, and a bias of tens of px passing."""
    from gdal_gf4cal.errors import GCPError
    from gdal_gf4cal.plausibility import check_gcps_against
    tab = _gcps(rpc)
    info = check_gcps_against(rpc, tab, (10240, 10240))
    assert info["predicted_margin_px"] == pytest.approx(0.1 * np.hypot(10240, 10240))   # 1,448 px
    assert 49.0 < info["max_predicted_offset_px"] < 51.5                                # the 50 px bias
    tab.loc[2, "sample"] += 2000.0                                                      # inside, but 2,000 px off
    with pytest.raises(GCPError, match=r"1 of 30 GCPs \(g2\) project more than 1448 px"):
        check_gcps_against(rpc, tab, (10240, 10240))


def test_swap_detection_in_the_engine(rpc):
    """Swapped columns that still pass as WGS84 degrees are caught by projection, and named."""
    from gdal_gf4cal.errors import GCPError
    from gdal_gf4cal.plausibility import check_gcps_against
    tab = _gcps(rpc)
    tab["lon"], tab["lat"] = tab["lat"].to_numpy(), tab["lon"].to_numpy()
    with pytest.raises(GCPError, match=r"lon/lat look swapped: .* swapped they agree \(median (49|50)\.\d px\)"):
        check_gcps_against(rpc, tab, (10240, 10240))


def test_max_uncertainty_must_be_positive(scene, rpc, tmp_path):
    csv = tmp_path / "g.csv"
    _gcps(rpc).to_csv(csv, index=False)
    _refused(*_refine(scene, csv, tmp_path, "--model", "affine", "--max-uncertainty", "0"), "positive number")
