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


def test_registerpanms_on_the_real_pair_loads_layers_a_gis_places(qgis_app, tmp_path):
    """The Ventoux Pleiades crops as delivered (.geom beside each), defaults: ms_on_pan is placed by QGIS through
    its RPC over the pan crop's ground (not at pixel coordinates), the correction loads once per component with a
    diverging style, the cell layer is named for what it holds (issue 20)."""
    import shutil

    import processing
    from qgis.core import QgsProject, QgsRasterLayer
    data = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "data")
    shutil.copy(os.path.join(data, "matching", "pleiades_ventoux_left.tif"), tmp_path / "left_image.tif")
    shutil.copy(os.path.join(data, "rpc", "ventoux_left_image.geom"), tmp_path / "left_image.geom")
    for name in ("lowres_color_image.tif", "lowres_color_image.geom"):
        shutil.copy(os.path.join(data, "panms_ventoux", name), tmp_path / name)
    QgsProject.instance().removeAllMapLayers()
    res = processing.runAndLoadResults("gf4cal:registerpanms", {
        "PAN": str(tmp_path / "left_image.tif"), "MS": str(tmp_path / "lowres_color_image.tif"),
        "DEM": os.path.join(data, "dem", "N44E005.hgt"), "GEOID": 1, "OUTPUT_FOLDER": str(tmp_path / "out")})
    assert res["RMS_SAMPLE_AFTER"] < 0.1 and res["RMS_LINE_AFTER"] < 0.1
    layers = {lyr.name(): lyr for lyr in QgsProject.instance().mapLayers().values()}
    assert "gcps" not in layers and any(n.startswith("pan-MS cells") for n in layers), sorted(layers)
    for what, band in (("sample", 1), ("line", 2)):
        lyr = layers[f"pan-MS correction, {what} (MS px)"]
        r = lyr.renderer()
        assert r.type() == "singlebandpseudocolor" and r.band() == band
        ramp = r.shader().rasterShaderFunction()
        assert ramp.minimumValue() == pytest.approx(-ramp.maximumValue()) and ramp.maximumValue() > 0
    ms_on_pan = layers["MS on the pan grid"]
    assert isinstance(ms_on_pan, QgsRasterLayer) and ms_on_pan.crs().isValid()
    ext = ms_on_pan.extent()                   # on the ground at Mont Ventoux, not at pixel coordinates
    assert 5.1 < ext.center().x() < 5.3 and 44.1 < ext.center().y() < 44.3, ext.toString()
