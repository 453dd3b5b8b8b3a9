"""``gf4cal:blockadjust`` (METHODS §8) in real headless QGIS on a small simulated Jilin-1 group (tests/blocksim.py:
blue CCDs + the other bands, GCPs at 0.2 px, tie points at 0.1 px): seams removed, bands registered, every output
written; bad input gives one line and nothing written."""
import json
import os

import pytest

import blocksim as B


def _bands(sep=";"):
    return sep.join(f"{n}={n.split('_')[0]}_blue" for n in B.NAMES if n not in B.REF)


@pytest.mark.slow
def test_blockadjust_runs_and_removes_the_seams(run_alg, tmp_path_factory, tmp_path):
    d = B.block_scene(str(tmp_path_factory.getbasetemp()))
    obs = os.path.join(d, "observations.csv")
    images = [B.image_path(d, n) for n in B.NAMES]
    res, fb = run_alg("gf4cal:blockadjust", {"INPUT": images, "DEM": os.path.join(d, "dem.tif"), "GCPS_FILE": obs,
                                             "TIES_FILE": obs, "BANDS_OF": _bands(), "SOLVER": 0,
                                             "OUTPUT_FOLDER": str(tmp_path / "out")})
    assert len(res["OUTPUT_RPCS"]) == 20 and all(os.path.getsize(p) > 0 for p in res["OUTPUT_RPCS"])
    assert sorted(os.path.basename(p) for p in res["OUTPUT_RPCS"]) == sorted(f"{n}.RPB" for n in B.NAMES)
    for key in ("OUTPUT_CALIBRATION", "OUTPUT_GPKG", "OUTPUT_PLOT", "OUTPUT_REPORT"):
        assert os.path.getsize(res[key]) > 0, key
    # the simulator draws 2.5-4.5 px seams; after the adjustment the overlaps agree to the matching noise
    assert res["MAX_SEAM_BEFORE_PX"] > 1.5
    assert res["MAX_SEAM_PX"] < 0.1
    assert res["MAX_BAND_RMS_AFTER_PX"] < 0.3
    seams = B.true_seams(str(tmp_path / "out"), d)
    assert max(s["after"] for s in seams.values()) <= 0.1
    with open(res["OUTPUT_REPORT"]) as fh:
        assert set(json.load(fh)["images"]) == set(B.NAMES)
    with open(res["OUTPUT_CALIBRATION"]) as fh:
        assert json.load(fh)["model"] == "block-rpc-cubic"
    assert "seam ccd1_blue | ccd2_blue" in fb.text()


def test_blockadjust_bad_input(run_alg, tmp_path):
    from qgis.core import QgsProcessingException
    data = os.path.join(os.path.dirname(__file__), "..", "data", "matching")
    out = tmp_path / "out"
    with pytest.raises(QgsProcessingException, match="at least two CCDs"):
        run_alg("gf4cal:blockadjust", {"INPUT": [os.path.join(data, "pleiades_ventoux_left.tif")],
                                       "DEM": os.path.join(data, "srtm_ventoux_crop.tif"), "OUTPUT_FOLDER": str(out)})
    assert not out.exists()


@pytest.mark.slow
def test_blockadjust_bad_group_input_is_one_line_and_writes_nothing(run_alg, tmp_path_factory, tmp_path):
    from qgis.core import QgsProcessingException
    d = B.block_scene(str(tmp_path_factory.getbasetemp()))
    obs = os.path.join(d, "observations.csv")
    out = tmp_path / "bad"
    base = {"INPUT": [B.image_path(d, n) for n in B.NAMES], "DEM": os.path.join(d, "dem.tif"), "GCPS_FILE": obs,
            "TIES_FILE": obs, "OUTPUT_FOLDER": str(out)}
    for bands, match in (("ccd1 ccd2_blue", "IMAGE=REFIMAGE"), (_bands(",") + ", ccd9=ccd1_blue", "ccd9")):
        with pytest.raises(QgsProcessingException, match=match) as info:
            run_alg("gf4cal:blockadjust", dict(base, BANDS_OF=bands))
        assert "\n" not in str(info.value).strip()
        assert "(BANDS_OF)" in str(info.value) and "--bands-of" not in str(info.value)   # the dialog's name
        assert not out.exists() or os.listdir(out) == []
