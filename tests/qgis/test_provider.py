"""The gf4cal Processing provider in real headless QGIS: registration, each algorithm on the test scene with its
outputs checked against the known truth, and bad input giving one clear message and no partial outputs."""
from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest


EXPECTED = {"rpcinfo", "simulatescene", "refinerpc", "orthorectify", "calibratelookangle", "applycalibration",
            "assessaccuracy", "collectgcps", "registerpanms", "blockadjust", "collectgcpsbatch", "refinerpcbatch",
            "applycalibrationbatch"}


def _exc():
    from qgis.core import QgsProcessingException
    return QgsProcessingException


def test_provider_registers_with_documented_algorithms(qgis_app):
    from qgis.core import QgsApplication
    provider = QgsApplication.processingRegistry().providerById("gf4cal")
    assert provider is not None and provider.name() == "GF4 RPC calibration"
    algs = {a.name(): a for a in provider.algorithms()}
    assert EXPECTED <= set(algs)
    for name, alg in algs.items():
        assert name == name.lower() and alg.id() == f"gf4cal:{name}"
        assert alg.shortHelpString() and alg.displayName() and alg.group()
        for p in alg.parameterDefinitions():
            assert p.help(), f"{name}: parameter {p.name()} has no help"
    refine = algs["refinerpc"]
    for p in ("INPUT", "GCPS", "MODEL", "DEM", "OUTPUT_RPC", "OUTPUT_GPKG"):
        assert refine.parameterDefinition(p) is not None, p
    assert refine.parameterDefinition("DEM").flags() & refine.parameterDefinition("DEM").FlagOptional
    assert len(refine.parameterDefinition("MODEL").options()) == 6
    assert refine.parameterDefinition("MODEL").defaultValue() == 5             # auto


def test_rpcinfo_reports_size_heights_gsd_and_footprint(run_alg, scene, tmp_path):
    files, truth = scene
    res, fb = run_alg("gf4cal:rpcinfo", {"INPUT": files["image"], "OUTPUT_FOOTPRINT": "TEMPORARY_OUTPUT",
                                         "OUTPUT_REPORT": str(tmp_path / "info.json")})
    rpc = truth["rpc"]
    assert (res["WIDTH"], res["HEIGHT"]) == truth["size"]
    assert (res["HEIGHT_MIN"], res["HEIGHT_MAX"]) == pytest.approx(rpc.height_range)
    assert res["GSD_SAMPLE"] == pytest.approx(1.6, abs=0.1) and res["GSD_LINE"] == pytest.approx(1.6, abs=0.1)
    layer = res["OUTPUT_FOOTPRINT"]
    assert layer.featureCount() == 1 and layer.crs().authid() == "EPSG:4326"
    poly = next(layer.getFeatures()).geometry()
    from qgis.core import QgsPointXY, QgsGeometry
    inside = [poly.contains(QgsGeometry.fromPointXY(QgsPointXY(x, y))) for x, y in zip(truth["lon"], truth["lat"])]
    assert all(inside)
    clon, clat = rpc.localize(truth["size"][0] / 2, truth["size"][1] / 2, rpc.height_off)
    assert (res["CENTER_LON"], res["CENTER_LAT"]) == pytest.approx((clon, clat), abs=2e-5)  # ~2 m
    assert os.path.getsize(tmp_path / "info.json") > 100
    assert "2003 x 1751" in fb.text()
    # a standalone sidecar works too, with a DEM
    res, _ = run_alg("gf4cal:rpcinfo", {"INPUT": files["rpc_file"], "DEM": files["dem"]})
    assert res["WIDTH"] == truth["size"][0]


def _refine(run_alg, files, tmp_path, **kw):
    params = {"INPUT": files["image"], "GCPS": files["gcps"], "MODEL": 2,
              "OUTPUT_RPC": str(tmp_path / "refined.RPB"), "OUTPUT_GPKG": str(tmp_path / "residuals.gpkg")}
    params.update(kw)
    return run_alg("gf4cal:refinerpc", params)


def test_refinerpc_affine_recovers_the_bias(run_alg, scene, tmp_path):
    from osgeo import ogr

    from gdal_gf4cal.rpc import RPCModel
    files, truth = scene
    res, fb = _refine(run_alg, files, tmp_path, OUTPUT_PLOT=str(tmp_path / "res.png"),
                      OUTPUT_REPORT=str(tmp_path / "report.json"))
    # before: the injected bias (~3.6 px); after: the GCP noise (planar sqrt(2) * sigma)
    assert res["CONTROL_RMS_BEFORE"] > 3.0 and res["CHECK_RMS_BEFORE"] > 3.0
    assert res["CONTROL_RMS_AFTER"] < 1.3 * math.sqrt(2) * truth["noise_px"]
    assert res["CHECK_RMS_AFTER"] < 1.5 * math.sqrt(2) * truth["noise_px"]
    assert res["N_OUTLIERS"] == 1 and truth["blunder"] in fb.text()
    assert res["REFIT_MAX_PX"] < 0.01
    # layout strength in px (issue 11): in the outputs, the feedback and the report; bounded by the true error below
    with open(res["OUTPUT_REPORT"]) as f:
        rep = json.load(f)
    assert res["PRECISION_MAX_PX"] == pytest.approx(rep["precision_px"]["max"])
    assert 0.0 < res["PRECISION_MAX_PX"] < 1.0
    assert "correction uncertainty over the image" in fb.text()
    # the refined RPC predicts the bias-corrected positions everywhere in the image
    new = RPCModel.from_file(res["OUTPUT_RPC"])
    rpc = truth["rpc"]
    W, H = truth["size"]
    s, l = np.meshgrid(np.linspace(50, W - 50, 9), np.linspace(50, H - 50, 9))
    lon, lat = rpc.localize(s.ravel(), l.ravel(), np.full(s.size, 120.0))
    s1, l1 = new.project(lon, lat, 120.0)
    ds_, dl_ = truth["bias"](s.ravel(), l.ravel())
    err = np.hypot(s1 - (s.ravel() + ds_), l1 - (l.ravel() + dl_))
    assert err.max() < 0.2
    # the GeoPackage: layers, fields, counts, the blunder flagged
    gpkg = ogr.Open(res["OUTPUT_GPKG"])
    names = {gpkg.GetLayer(i).GetName() for i in range(gpkg.GetLayerCount())}
    assert {"gcps", "residual_vectors", "footprint", "layer_styles"} <= names
    gl = gpkg.GetLayerByName("gcps")
    assert gl.GetFeatureCount() == len(truth["ids"])
    defn = gl.GetLayerDefn()
    fields = {defn.GetFieldDefn(i).GetName() for i in range(defn.GetFieldCount())}
    assert {"id", "lon", "lat", "h", "sample", "line", "role", "res_sample_before", "res_line_before",
            "res_sample_after", "res_line_after", "res_px_before", "res_px_after", "outlier"} <= fields
    flagged = [f["id"] for f in gl if f["outlier"]]
    assert flagged == [truth["blunder"]]
    assert gpkg.GetLayerByName("residual_vectors").GetFeatureCount() == len(truth["ids"])
    assert os.path.getsize(res["OUTPUT_PLOT"]) > 10000 and os.path.getsize(res["OUTPUT_REPORT"]) > 100
    assert fb.progress and max(fb.progress) == 100


def test_refinerpc_field_choice_vrt_output_and_layers_loaded(qgis_app, scene, tmp_path):
    import processing
    from osgeo import gdal
    from qgis.core import QgsProject

    files, truth = scene
    QgsProject.instance().removeAllMapLayers()
    res = processing.runAndLoadResults("gf4cal:refinerpc", {
        "INPUT": files["image"], "GCPS": files["gcps_colrow"], "SAMPLE_FIELD": "col", "LINE_FIELD": "row",
        "HEIGHT_FIELD": "elev", "MODEL": 1, "OUTPUT_RPC": str(tmp_path / "refined.vrt"),
        "OUTPUT_GPKG": str(tmp_path / "res.gpkg")})
    ds = gdal.Open(res["OUTPUT_RPC"])
    assert (ds.RasterXSize, ds.RasterYSize) == truth["size"] and ds.GetMetadata("RPC")
    assert os.path.exists(files["image"]) and not gdal.Open(files["image"]).GetFileList()[1:]  # input untouched
    layers = {lyr.name(): lyr for lyr in QgsProject.instance().mapLayers().values()}
    after = [n for n in layers if n.startswith("residuals after (x")]     # the name states the exaggeration
    assert {"gcps", "footprint", "Refined RPC (VRT)"} <= set(layers) and len(after) == 1
    assert layers[after[0]].renderer().type() == "graduatedSymbol"      # default style from layer_styles
    assert layers["gcps"].renderer().type() == "RuleRenderer"
    # QGIS georeferences the VRT through its (refined) RPC: the layer covers the GCPs on the ground
    vrt = layers["Refined RPC (VRT)"]
    assert vrt.isValid() and vrt.crs().isGeographic()
    ext = vrt.extent()
    assert ext.xMinimum() < truth["lon"].min() < truth["lon"].max() < ext.xMaximum()
    assert ext.yMinimum() < truth["lat"].min() < truth["lat"].max() < ext.yMaximum()
    QgsProject.instance().removeAllMapLayers()


def test_refinerpc_heights_from_dem(run_alg, scene, tmp_path):
    files, truth = scene
    res, _ = _refine(run_alg, files, tmp_path, GCPS=files["gcps_noh"], DEM=files["dem"])
    assert res["CHECK_RMS_AFTER"] < 1.5 * math.sqrt(2) * truth["noise_px"]
    with pytest.raises(_exc(), match="(?i)height.*DEM"):
        _refine(run_alg, files, tmp_path / "x", GCPS=files["gcps_noh"])
    assert not (tmp_path / "x").exists() or not os.listdir(tmp_path / "x")


@pytest.mark.parametrize("case, match", [
    ("norpc", "(?i)RPC"),
    ("missing_field", "has no field 'sample'"),
    ("too_few", "(?i)at least 3 control"),
    ("missing_chosen_field", "has no field 'elev'"),
])
def test_bad_input_clear_message_and_no_outputs(run_alg, scene, tmp_path, case, match):
    files, _ = scene
    out = tmp_path / "out"
    out.mkdir()
    kw = {"OUTPUT_RPC": str(out / "refined.RPB"), "OUTPUT_GPKG": str(out / "res.gpkg"),
          "OUTPUT_PLOT": str(out / "res.png"), "OUTPUT_REPORT": str(out / "report.json")}
    kw.update({"norpc": {"INPUT": files["norpc"]},
               "missing_field": {"GCPS": files["gcps_colrow"]},
               "too_few": {"GCPS": files["gcps_few"]},
               "missing_chosen_field": {"HEIGHT_FIELD": "elev"}}[case])
    with pytest.raises(_exc(), match=match) as info:
        _refine(run_alg, files, tmp_path, **kw)
    assert "\n" not in str(info.value).strip()  # one line
    assert os.listdir(out) == []


def test_cancel_leaves_no_outputs(qgis_app, scene, tmp_path):
    import processing
    from qgis.core import QgsProcessingFeedback

    files, _ = scene
    fb = QgsProcessingFeedback()
    fb.cancel()
    with pytest.raises(_exc(), match="(?i)cancel"):
        processing.run("gf4cal:refinerpc", {
            "INPUT": files["image"], "GCPS": files["gcps"], "MODEL": 2,
            "OUTPUT_RPC": str(tmp_path / "refined.RPB"), "OUTPUT_GPKG": str(tmp_path / "res.gpkg")}, feedback=fb)
    assert os.listdir(tmp_path) == []


def test_assessaccuracy_measures_the_injected_bias(run_alg, scene, tmp_path):
    from osgeo import ogr
    files, truth = scene
    res, fb = run_alg("gf4cal:assessaccuracy", {"INPUT": files["image"], "GCPS": files["gcps"],
                                                "OUTPUT_GPKG": str(tmp_path / "acc.gpkg"),
                                                "OUTPUT_REPORT": str(tmp_path / "acc.json")})
    # expected: the mean of the injected affine bias over the GCPs (blunder excluded), from the truth
    ok = np.array(truth["ids"]) != truth["blunder"]
    rpc = truth["rpc"]
    s_rpc, l_rpc = rpc.project(truth["lon"], truth["lat"], truth["h"])
    ds_, dl_ = truth["bias"](s_rpc, l_rpc)
    assert res["N"] == len(truth["ids"])
    assert res["MEAN_LINE"] == pytest.approx(dl_[ok].mean(), abs=0.1)
    # the blunder (+25 px in sample) enters the plain statistics: the mean moves by 25/n
    assert res["MEAN_SAMPLE"] == pytest.approx((ds_[ok].sum() + ds_[~ok].sum() + 25.0) / len(ok), abs=0.1)
    assert res["CE90_M"] > 1.6 * 3.0 and res["CHECK_RMS_PLANAR"] > 3.0
    ds = ogr.Open(res["OUTPUT_GPKG"])
    assert ds.GetLayerByName("gcps").GetFeatureCount() == len(truth["ids"])
    assert ds.GetLayerByName("residual_vectors").GetFeatureCount() == len(truth["ids"])
    assert os.path.exists(res["OUTPUT_REPORT"]) and "check: n=" in fb.text()


@pytest.mark.parametrize("model, exact", [(0, True), (1, True), (3, False), (4, False)])
def test_refinerpc_every_model(run_alg, scene, tmp_path, model, exact):
    import json
    files, truth = scene
    res, fb = _refine(run_alg, files, tmp_path, MODEL=model, ORDER=2, OUTPUT_REPORT=str(tmp_path / "r.json"))
    with open(res["OUTPUT_REPORT"]) as fh:
        rep = json.load(fh)
    assert rep["apply"]["exact"] is exact and res["REFIT_MAX_PX"] < 0.01
    assert rep["model"]["name"] == ["translation", "shift-drift", "affine", "poly2", "detector-poly"][model]
    # every model removes most of the injected affine bias (the simpler ones leave what they cannot represent)
    assert res["CHECK_RMS_AFTER"] < 0.5 * res["CHECK_RMS_BEFORE"]
    if model == 3:  # poly2 contains the affine bias: noise level
        assert res["CHECK_RMS_AFTER"] < 1.5 * math.sqrt(2) * truth["noise_px"]


def test_unexpected_error_is_one_line_and_removes_partial_outputs(qgis_app, tmp_path):
    """A bug inside an algorithm (here a KeyError after an output was written) still reaches the user as one
    QgsProcessingException line, with the traceback in the log and the partial output removed."""
    from qgis.core import QgsProcessingContext, QgsProcessingFeedback, QgsProcessingParameterFileDestination

    from processing_provider.base import Gf4calAlgorithm

    class Broken(Gf4calAlgorithm):
        NAME = "broken"

        def initAlgorithm(self, config=None):
            self.addParameter(QgsProcessingParameterFileDestination("OUT", "out", "JSON (*.json)"))

        def run_algorithm(self, parameters, context, feedback, progress):
            import warnings
            path = self.output_file(parameters, "OUT", context)
            with open(path, "w") as fh:
                fh.write("{")
            warnings.warn("poorly conditioned", UserWarning)
            return {}["missing"]

    class Log(QgsProcessingFeedback):
        def __init__(self):
            super().__init__()
            self.lines = []

        def pushDebugInfo(self, info):
            self.lines.append(info)

        def pushWarning(self, warning):
            self.lines.append(warning)

    alg = Broken()
    alg.initAlgorithm()
    fb = Log()
    out = tmp_path / "partial.json"
    with pytest.raises(_exc(), match="Internal error \\(KeyError") as info:
        alg.processAlgorithm({"OUT": str(out)}, QgsProcessingContext(), fb)
    assert "\n" not in str(info.value).strip()
    assert not out.exists()
    log = "\n".join(fb.lines)
    assert "Traceback" in log and "poorly conditioned" in log  # warnings are logged on failure too


def test_memory_layer_with_renamed_fields_reaches_the_engine_reader(run_alg, scene, tmp_path):
    """A layer without a file (memory, renamed role field) goes through parameterAsCompatibleSourceLayerPathAnd
    LayerName and the engine's own layer reader: every point read, roles from the chosen field, no CSV written."""
    from qgis.core import QgsFeatureRequest, QgsVectorLayer

    files, truth = scene
    src = QgsVectorLayer(files["gcps"], "gcps", "ogr")
    mem = src.materialize(QgsFeatureRequest())
    idx = mem.fields().indexOf("role")
    assert mem.dataProvider().renameAttributes({idx: "kind"})
    mem.updateFields()
    n = mem.featureCount()
    res, _ = run_alg("gf4cal:assessaccuracy", {"INPUT": files["image"], "GCPS": mem, "ROLE_FIELD": "kind",
                                              "OUTPUT_REPORT": str(tmp_path / "a.json")})
    assert res["N"] == n == src.featureCount()
    import json
    rep = json.loads((tmp_path / "a.json").read_text())
    roles = [f["role"] for f in src.getFeatures()]
    assert rep["check"]["n"] == roles.count("check") > 0 and rep["control"]["n"] == roles.count("control")
    assert sorted(os.listdir(tmp_path)) == ["a.json"]
