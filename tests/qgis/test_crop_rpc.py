"""Issue 19 item 8 in headless QGIS: a crop that states its origin in the product (the real Ventoux crop geometry,
tests/ventouxcrop.py) paired with its product's RPC through the optional "RPC file (if not in the image)" parameter;
the refined RPC lands on the product's physical location grid, the log says the origin was applied."""
import pytest

from gdal_gf4cal import RPCModel
from ventouxcrop import GEOM, NOTE, grid_gcps, max_error_px, write_crop


@pytest.fixture()
def crop(tmp_path):
    grid_gcps().to_csv(tmp_path / "gcps.csv", index=False)
    uri = f"file://{tmp_path / 'gcps.csv'}?xField=lon&yField=lat&crs=EPSG:4326"
    return str(write_crop(tmp_path / "left_image.tif")), uri


def test_refinerpc_of_a_crop_with_its_products_rpc(run_alg, crop, tmp_path):
    image, gcps = crop
    from qgis.core import QgsVectorLayer
    layer = QgsVectorLayer(gcps, "gcps", "delimitedtext")
    assert layer.isValid() and layer.featureCount() == 50
    res, fb = run_alg("gf4cal:refinerpc", {"INPUT": image, "RPC": str(GEOM), "GCPS": layer, "MODEL": 0,
                                           "OUTPUT_RPC": str(tmp_path / "refined.RPB"),
                                           "OUTPUT_GPKG": str(tmp_path / "residuals.gpkg")})
    assert max_error_px(RPCModel.from_file(res["OUTPUT_RPC"])) < 0.01
    assert 3.5 < res["CONTROL_RMS_BEFORE"] < 3.7 and res["CONTROL_RMS_AFTER"] < 0.01
    assert any(NOTE in m for _, m in fb.log), fb.text()


def test_assessaccuracy_of_a_crop_with_its_products_rpc(run_alg, crop, tmp_path):
    """The residuals are the GCPs' bias (3, -2) px to 1e-3 px (unshifted, the product's RPC is 7000 px off)."""
    image, gcps = crop
    from qgis.core import QgsVectorLayer
    layer = QgsVectorLayer(gcps, "gcps", "delimitedtext")
    res, fb = run_alg("gf4cal:assessaccuracy", {"INPUT": image, "RPC": str(GEOM), "GCPS": layer})
    assert res["N"] == 50 and abs(res["MEAN_SAMPLE"] - 3.0) < 1e-3 and abs(res["MEAN_LINE"] + 2.0) < 1e-3
    assert res["RMS_SAMPLE"] - 3.0 < 1e-3 and any(NOTE in m for _, m in fb.log), fb.text()


def test_rpcinfo_of_a_crop_with_its_products_rpc(run_alg, crop, tmp_path):
    image, _ = crop
    res, fb = run_alg("gf4cal:rpcinfo", {"INPUT": image, "RPC": str(GEOM), "OUTPUT_FOOTPRINT": "memory:"})
    product = RPCModel.from_file(GEOM)
    s, l = product.project(res["CENTER_LON"], res["CENTER_LAT"], product.height_off)
    assert res["WIDTH"] == 500 and abs(s - 5250) < 1 and abs(l - 5250) < 1
    assert any(NOTE in m for _, m in fb.log), fb.text()


def test_rpc_parameter_is_optional_where_an_image_is_the_source(qgis_app):
    from qgis.core import QgsApplication
    reg = QgsApplication.processingRegistry()
    for alg in ("refinerpc", "rpcinfo", "assessaccuracy", "calibratelookangle", "collectgcps"):
        p = reg.algorithmById(f"gf4cal:{alg}").parameterDefinition("RPC")
        assert p is not None and p.flags() & p.FlagOptional, alg


def test_many_image_algorithms_have_rpc_pairs(qgis_app):
    from qgis.core import QgsApplication
    for alg in ("blockadjust", "applycalibration"):
        p = QgsApplication.processingRegistry().algorithmById(f"gf4cal:{alg}").parameterDefinition("RPCS")
        assert p is not None and p.flags() & p.FlagOptional and "IMAGE=RPC" in p.description(), alg


def test_applycalibration_of_a_crop_with_its_products_rpc(run_alg, tmp_path):
    """The GF4-type frame (tests/gf4frame.py): the crop's RPB is the product's recalibrated RPC moved to the crop."""
    import numpy as np
    from gf4frame import HEIGHTS, frame_model, make_cameras
    from gdal_gf4cal.rpc_fit import fit_rpc_from_model
    cur, true = make_cameras()
    product, _ = fit_rpc_from_model(frame_model(cur), height_range=HEIGHTS)
    product.write_rpb(tmp_path / "product.RPB")
    cur.to_json(tmp_path / "current.json")
    true.to_json(tmp_path / "true.json")
    crop = write_crop(tmp_path / "crop.tif", gt=(4000.0, 1.0, 0.0, 6000.0, 0.0, 1.0))
    res, fb = run_alg("gf4cal:applycalibration", {"INPUT": [str(crop)], "RPCS": f"crop.tif={tmp_path / 'product.RPB'}",
                                                  "CURRENT_CAMERA": str(tmp_path / "current.json"),
                                                  "NEW_CAMERA": str(tmp_path / "true.json"),
                                                  "OUTPUT_FOLDER": str(tmp_path / "out")})
    assert any("crop.tif is a crop at (4000, 6000)" in m for _, m in fb.log), fb.text()
    got = RPCModel.from_file(tmp_path / "out" / "crop.RPB")
    S, L = np.meshgrid(4000.0 + np.linspace(0, 500, 5), 6000.0 + np.linspace(0, 500, 5))
    h = np.full(S.size, float(np.mean(HEIGHTS)))
    lon, lat = product.localize(S.ravel(), L.ravel(), h)
    ts, tl = frame_model(true).project(lon, lat, h)
    s, l = got.project(lon, lat, h)
    assert np.max(np.hypot(s - (ts - 4000.0), l - (tl - 6000.0))) < 0.05
