"""``gf4cal:blockadjust`` (METHODS §8) on a small simulated Jilin-1 group: blue CCDs + the other bands."""
import os

import pytest

import blocksim as B


@pytest.mark.slow
def test_blockadjust_runs_and_removes_the_seams(run_alg, tmp_path_factory, tmp_path):
    d = B.block_scene(str(tmp_path_factory.getbasetemp()))
    obs = os.path.join(d, "observations.csv")
    images = [B.image_path(d, n) for n in B.NAMES]
    bands = ";".join(f"{n}={n.split('_')[0]}_blue" for n in B.NAMES if n not in B.REF)
    res, fb = run_alg("gf4cal:blockadjust", {"INPUT": images, "DEM": os.path.join(d, "dem.tif"), "GCPS_FILE": obs,
                                             "TIES_FILE": obs, "BANDS_OF": bands, "SOLVER": 0,
                                             "OUTPUT_FOLDER": str(tmp_path / "out")})
    assert len(res["OUTPUT_RPCS"]) == 20 and all(os.path.exists(p) for p in res["OUTPUT_RPCS"])
    assert os.path.exists(res["OUTPUT_CALIBRATION"]) and os.path.exists(res["OUTPUT_RESIDUALS"])
    assert res["MAX_SEAM_PX"] < 0.1
    seams = B.true_seams(str(tmp_path / "out"), d)
    assert max(s["after"] for s in seams.values()) <= 0.1


def test_blockadjust_bad_input(run_alg, tmp_path):
    from qgis.core import QgsProcessingException
    data = os.path.join(os.path.dirname(__file__), "..", "data", "matching")
    out = tmp_path / "out"
    with pytest.raises(QgsProcessingException, match="at least two CCDs"):
        run_alg("gf4cal:blockadjust", {"INPUT": [os.path.join(data, "pleiades_ventoux_left.tif")],
                                       "DEM": os.path.join(data, "srtm_ventoux_crop.tif"), "OUTPUT_FOLDER": str(out)})
    assert not out.exists()
