"""collectgcps in headless QGIS on a rendered simulated GF4 scene (built-in texture, known true model), then its
GCPs straight into refinerpc: matched positions within 0.1 px of the truth, the refined RPC at the noise level."""
from __future__ import annotations

import os

import numpy as np
import pytest

SIZE = (256, 256)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    from gdal_gf4cal.simulate import write_reference_ortho, write_scene
    from gdal_gf4cal.simulate.render import model_bounds
    d = tmp_path_factory.mktemp("rendered")
    res = write_scene("gf4", str(d / "scene"), seed=2, size=SIZE, n_gcps=10, render=True, workers=1)
    sim = res.scene.images[0]
    ref = write_reference_ortho(str(d / "reference.tif"), model_bounds(sim.true, margin=0.1), 40.0 / 111320.0,
                                seed=2, scale_m=3.0 * sim.gsd_m)
    far = write_reference_ortho(str(d / "elsewhere.tif"), (10.0, 10.0, 10.2, 10.2), 200.0 / 111320.0, seed=2)
    return {"image": res.images[""].paths["image"], "dem": res.dem_path, "reference": ref, "far": far,
            "true": sim.true, "dir": str(d)}


def test_collectgcps_then_refinerpc(run_alg, rendered, tmp_path):
    from gdal_gf4cal.gcp import read_gcps
    res, fb = run_alg("gf4cal:collectgcps", {"INPUT": rendered["image"], "REFERENCE": rendered["reference"],
                                             "DEM": rendered["dem"], "SPACING": 32, "WINDOW": 64, "THREADS": 2,
                                             "OUTPUT": str(tmp_path / "gcps.gpkg")})
    assert res["N_GCPS"] >= 0.9 * res["N_WINDOWS"] >= 20
    g = read_gcps(res["OUTPUT"])
    assert len(g) == res["N_GCPS"]
    ts, tl = rendered["true"].project(g["lon"].to_numpy(), g["lat"].to_numpy(), g["h"].to_numpy())
    err = np.hypot(g["sample"].to_numpy() - ts, g["line"].to_numpy() - tl)
    assert np.sqrt(np.mean(err ** 2)) <= 0.1
    # the matched GCPs feed refinerpc as they are (default field names)
    ref, _ = run_alg("gf4cal:refinerpc", {"INPUT": rendered["image"], "GCPS": res["OUTPUT"], "MODEL": 2,
                                          "OUTPUT_RPC": str(tmp_path / "refined.RPB"),
                                          "OUTPUT_GPKG": str(tmp_path / "residuals.gpkg")})
    assert ref["CONTROL_RMS_BEFORE"] > 1.0 and ref["CONTROL_RMS_AFTER"] < 0.25


def test_collectgcps_spacing_left_empty_is_the_default_grid(run_alg, rendered, tmp_path):
    """SPACING left empty (optional, as the dialog shows it): the engine's default grid, 64 px on this 256 px scene
    (eight windows across, never closer than a window: 3 x 3 windows), not an error or a zero step."""
    res, fb = run_alg("gf4cal:collectgcps", {"INPUT": rendered["image"], "REFERENCE": rendered["reference"],
                                             "DEM": rendered["dem"], "THREADS": 1,
                                             "OUTPUT": str(tmp_path / "gcps.gpkg")})
    assert res["N_WINDOWS"] == 9 and res["N_GCPS"] >= 8
    assert "windows 9 every 64 px" in fb.text()


def test_collectgcps_without_overlap_fails_cleanly(run_alg, rendered, tmp_path):
    from qgis.core import QgsProcessingException
    with pytest.raises(QgsProcessingException, match="(?i)no GCP found"):
        run_alg("gf4cal:collectgcps", {"INPUT": rendered["image"], "REFERENCE": rendered["far"],
                                       "DEM": rendered["dem"], "SPACING": 64, "THREADS": 1,
                                       "OUTPUT": str(tmp_path / "gcps.gpkg")})
    assert os.listdir(tmp_path) == []
