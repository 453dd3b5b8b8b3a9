"""``gf4cal:registerpanms`` in headless QGIS on a small rendered GF7 crop: the outputs exist, the cells register
to the quarter MS pixel, a reuse model of another camera is refused as a QgsProcessingException, nothing left."""
from __future__ import annotations

import json
import os

import pytest

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def gf7(tmp_path_factory):
    from gdal_gf4cal.simulate.gf7 import write_gf7_scene
    d = tmp_path_factory.mktemp("qgf7")
    write_gf7_scene(d, seed=0, jitter=False, size=(1024, 1024), crop_center_ms_px=2560, workers=2)
    return d


def _params(d, out, **kw):
    p = {"PAN": str(d / "pan" / "scene.tif"), "MS": str(d / "ms" / "scene.tif"), "DEM": str(d / "dem.tif"),
         "BREAKS": "128", "CELL": 16, "OUTPUT_FOLDER": str(out)}
    p.update(kw)
    return p


def test_registerpanms_writes_everything(run_alg, gf7, tmp_path):
    out = tmp_path / "reg"
    res, fb = run_alg("gf4cal:registerpanms", _params(gf7, out))
    assert os.path.exists(res["OUTPUT_MS_ON_PAN"]) and os.path.exists(res["OUTPUT_CORRECTION"])
    assert res["P_AFTER"] >= 0.99 and res["RMS_SAMPLE_AFTER"] < 0.05
    with open(res["OUTPUT_REPORT"]) as fh:
        rep = json.load(fh)
    assert rep["sizes"]["ms_on_pan"] == [256, 256] and "piecewise" in fb.text()


def test_registerpanms_refuses_reuse_of_another_camera(run_alg, gf7, tmp_path):
    from qgis.core import QgsProcessingException
    from gdal_gf4cal.panms import PanMSModel, default_breaks
    other = PanMSModel(ms_size=(7680, 7680), breaks=default_breaks(7680)).to_json(tmp_path / "other.json")
    out = tmp_path / "reg"
    with pytest.raises(QgsProcessingException) as info:
        run_alg("gf4cal:registerpanms", _params(gf7, out, REUSE=other, BREAKS=""))
    assert "reuse" in str(info.value) and "Traceback" not in str(info.value)
    assert not out.exists()
