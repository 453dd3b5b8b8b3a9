"""``gf4cal:blockadjust`` in real headless QGIS on a small simulated Jilin-1 group (METHODS §8): the four blue CCD
images and their pan images, GCPs at 0.2 px and tie points at 0.1 px; seams removed, bands registered, every output
written; bad input gives one line and nothing written."""
from __future__ import annotations

import json
import os

import pytest

pytestmark = pytest.mark.slow

REF = [f"ccd{k}_blue" for k in range(1, 5)]
PAN = [f"ccd{k}" for k in range(1, 5)]


@pytest.fixture(scope="module")
def group(tmp_path_factory):
    """The group's files: images (blue CCDs across track, then pan), DEM, the full observation table and the one
    restricted to these eight images."""
    import pandas as pd

    from gdal_gf4cal.simulate import write_scene
    d = tmp_path_factory.mktemp("jl1")
    write_scene("jl1", d, seed=3, size=(256, 128), n_gcps=30, gcp_noise_px=0.2, check_grid_n=5,
                reference_ortho=False)
    obs = pd.read_csv(d / "observations.csv")
    obs = obs[obs["image_id"].isin(REF + PAN)]
    obs = obs[obs.groupby("point_id")["image_id"].transform("size").gt(1) | obs["kind"].eq("gcp")]
    obs.to_csv(d / "obs8.csv", index=False)
    return {"dir": str(d), "images": [str(d / n / "scene.tif") for n in REF + PAN], "dem": str(d / "dem.tif"),
            "obs_all": str(d / "observations.csv"), "obs": str(d / "obs8.csv"),
            "bands_of": ", ".join(f"{p}={p}_blue" for p in PAN)}


def test_blockadjust_removes_seams_and_registers_bands(run_alg, group, tmp_path):
    out = tmp_path / "out"
    res, fb = run_alg("gf4cal:blockadjust", {
        "IMAGES": group["images"], "DEM": group["dem"], "GCP_TABLE": group["obs"], "TIE_TABLE": group["obs"],
        "BANDS_OF": group["bands_of"], "SOLVER": 0, "OUTPUT_FOLDER": str(out)})
    names = sorted(os.path.basename(p) for p in res["OUTPUT_RPCS"])
    assert names == sorted(f"{n}.RPB" for n in REF + PAN)
    for key in ("OUTPUT_CALIBRATION", "OUTPUT_GPKG", "OUTPUT_PLOT", "OUTPUT_REPORT"):
        assert os.path.getsize(res[key]) > 0, key
    for p in res["OUTPUT_RPCS"]:
        assert os.path.getsize(p) > 0
    # the simulator draws 2.5-4.5 px seams; after the adjustment the overlaps agree to the matching noise
    assert res["MAX_SEAM_BEFORE_PX"] > 1.5
    assert res["MAX_SEAM_AFTER_PX"] < 0.15
    assert res["MAX_BAND_RMS_AFTER_PX"] < 0.3
    with open(res["OUTPUT_REPORT"]) as fh:
        rep = json.load(fh)
    assert set(rep["images"]) == set(REF + PAN)
    with open(res["OUTPUT_CALIBRATION"]) as fh:
        assert json.load(fh)["model"] == "block-rpc-cubic"
    assert "seam ccd1_blue | ccd2_blue" in fb.text()


def test_blockadjust_bad_input_is_one_line_and_writes_nothing(run_alg, group, tmp_path):
    from qgis.core import QgsProcessingException
    out = tmp_path / "bad"
    # the full table names the green, red and nir images, which are not given
    with pytest.raises(QgsProcessingException, match="(?i)not among the images") as info:
        run_alg("gf4cal:blockadjust", {
            "IMAGES": group["images"], "DEM": group["dem"], "GCP_TABLE": group["obs_all"],
            "TIE_TABLE": group["obs_all"], "BANDS_OF": group["bands_of"], "OUTPUT_FOLDER": str(out)})
    assert "\n" not in str(info.value).strip()
    assert not out.exists() or os.listdir(out) == []
    with pytest.raises(QgsProcessingException, match="IMAGE=REFIMAGE") as info:
        run_alg("gf4cal:blockadjust", {
            "IMAGES": group["images"], "DEM": group["dem"], "GCP_TABLE": group["obs"], "TIE_TABLE": group["obs"],
            "BANDS_OF": "ccd1 ccd2_blue", "OUTPUT_FOLDER": str(out)})
    assert "\n" not in str(info.value).strip()
    assert not out.exists() or os.listdir(out) == []
