"""Issue 19 in headless QGIS: ``gf4cal:refinerpc`` on a crop of a real QuickBird-2 product (tests/cropsim.py) uses
field GCPs up to 35 % of the crop outside it, warning with their names; the same points 3 image sizes away are
refused with the dialog's override named (CHECK_PLAUSIBILITY, an advanced parameter), which lets them through."""
import os

import pytest

import cropsim as C


def _gpkg(tab, path):
    import geopandas as gpd
    g = gpd.GeoDataFrame(tab.drop(columns=["lon", "lat"]), geometry=gpd.points_from_xy(tab["lon"], tab["lat"]),
                         crs="EPSG:4326")
    g.to_file(path, driver="GPKG")
    return str(path)


@pytest.fixture(scope="module")
def crop(tmp_path_factory):
    d = tmp_path_factory.mktemp("qcrop")
    img, dem = C.write_crop(str(d))
    return d, img, dem


def _params(img, dem, gcps, out, **kw):
    p = {"INPUT": img, "GCPS": gcps, "DEM": dem, "MODEL": 5, "OUTPUT_RPC": str(out / "refined.RPB"),
         "OUTPUT_GPKG": str(out / "residuals.gpkg")}
    p.update(kw)
    return p


def test_refinerpc_uses_field_gcps_outside_the_crop(run_alg, crop, tmp_path):
    d, img, dem = crop
    gcps = _gpkg(C.gcps(), tmp_path / "g.gpkg")
    res, fb = run_alg("gf4cal:refinerpc", _params(img, dem, gcps, tmp_path))
    assert os.path.getsize(res["OUTPUT_RPC"]) > 0
    # 10 control points, bias (3, -2) px before, the 0.3 px noise after
    assert 3.0 < res["CONTROL_RMS_BEFORE"] < 4.3 and res["CONTROL_RMS_AFTER"] < 0.5
    assert res["N_OUTLIERS"] == 0
    warn = [m for kind, m in fb.log if kind == "warning" and "outside the 850 x 1450 px image" in m]
    assert len(warn) == 1 and all(f"{g} (" in warn[0] for g in ("F7", "F8", "F9", "F10")), fb.text()


def test_refinerpc_far_points_refused_naming_the_qgis_override(run_alg, crop, tmp_path):
    from qgis.core import QgsProcessingException
    d, img, dem = crop
    gcps = _gpkg(C.gcps(far=3.0), tmp_path / "far.gpkg")
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(QgsProcessingException) as info:
        run_alg("gf4cal:refinerpc", _params(img, dem, gcps, out))
    msg = str(info.value)
    assert "4 of 10 GCPs" in msg and "off (CHECK_PLAUSIBILITY, an advanced parameter)" in msg and "--no-plausibility-check" not in msg, msg
    assert os.listdir(out) == []
    res, _ = run_alg("gf4cal:refinerpc", _params(img, dem, gcps, out, MODEL=0, CHECK_PLAUSIBILITY=False))
    assert os.path.getsize(res["OUTPUT_RPC"]) > 0


def test_plausibility_parameter_is_advanced_everywhere_gcps_are_checked(qgis_app):
    from qgis.core import QgsApplication, QgsProcessingParameterDefinition
    reg = QgsApplication.processingRegistry()
    for alg in ("refinerpc", "refinerpcbatch", "assessaccuracy", "calibratelookangle", "blockadjust"):
        p = reg.algorithmById(f"gf4cal:{alg}").parameterDefinition("CHECK_PLAUSIBILITY")
        assert p is not None, alg
        assert p.flags() & QgsProcessingParameterDefinition.FlagAdvanced and p.defaultValue() is True, alg
