"""``gf4cal:orthorectify`` in headless QGIS: the ortho loads georeferenced; a DEM above EGM96 (compound CRS) gives
the same ortho as the ellipsoidal DEM; EGM2008 without grid is refused naming the grid and the QGIS parameter."""
from __future__ import annotations

import numpy as np
import pytest
from osgeo import gdal


@pytest.fixture(scope="module")
def oscene(tmp_path_factory):
    from gdal_gf4cal.simulate import write_scene
    from rasters import write_geoid_dem
    d = tmp_path_factory.mktemp("qortho")
    write_scene("gf4", d / "s", seed=5, size=(192, 192), n_gcps=8, render=True, tile=192, reference_ortho=False)
    write_geoid_dem(d / "s" / "dem.tif", d / "dem_egm96.tif", 5773)
    write_geoid_dem(d / "s" / "dem.tif", d / "dem_egm2008.tif", 3855)
    return d


def test_orthorectify_loads_georeferenced_ortho(run_alg, oscene, tmp_path):
    from qgis.core import QgsRasterLayer
    out = tmp_path / "ortho.tif"
    res, fb = run_alg("gf4cal:orthorectify", {"INPUT": str(oscene / "s" / "scene.tif"),
                                               "DEM": str(oscene / "dem_egm96.tif"), "RESOLUTION": 60.0,
                                               "OUTPUT": str(out)})
    assert res["RESOLUTION_OUT"] == 60.0 and "egm96" in fb.text().lower()
    layer = QgsRasterLayer(res["OUTPUT"], "ortho", "gdal")
    assert layer.isValid() and layer.crs().authid().startswith("EPSG:326")
    ext = layer.extent()
    assert ext.width() > 60 * 150 and layer.rasterUnitsPerPixelX() == 60.0
    ell = tmp_path / "ortho_ell.tif"
    run_alg("gf4cal:orthorectify", {"INPUT": str(oscene / "s" / "scene.tif"), "DEM": str(oscene / "s" / "dem.tif"),
                                    "RESOLUTION": 60.0, "OUTPUT": str(ell)})
    a, b = (gdal.Open(str(p)).ReadAsArray().astype(float) for p in (out, ell))
    assert a.shape == b.shape and np.mean(np.abs(a - b)) < 0.05


def test_orthorectify_egm2008_without_grid_names_grid_and_parameter(run_alg, oscene, tmp_path):
    from qgis.core import QgsProcessingException
    from gdal_gf4cal.geoid import find_grid
    if find_grid("egm2008")[0] is not None:
        pytest.skip("an EGM2008 grid is installed here")
    with pytest.raises(QgsProcessingException) as info:
        run_alg("gf4cal:orthorectify", {"INPUT": str(oscene / "s" / "scene.tif"),
                                        "DEM": str(oscene / "dem_egm2008.tif"), "OUTPUT": str(tmp_path / "o.tif")})
    msg = str(info.value)
    assert "us_nga_egm08_25.tif" in msg and "Geoid grid file" in msg and "--geoid" not in msg
    assert not list(tmp_path.iterdir())


def test_refinerpc_auto_with_ortho_loads_the_ortho(run_alg, oscene, tmp_path):
    from qgis.core import QgsRasterLayer
    res, fb = run_alg("gf4cal:refinerpc", {"INPUT": str(oscene / "s" / "scene.tif"),
                                            "GCPS": str(oscene / "s" / "gcps.gpkg"), "DEM": str(oscene / "dem_egm96.tif"),
                                            "OUTPUT_RPC": str(tmp_path / "r.vrt"),
                                            "OUTPUT_GPKG": str(tmp_path / "r.gpkg"),
                                            "OUTPUT_ORTHO": str(tmp_path / "ortho.tif")})
    assert "automatic model choice:" in fb.text()
    assert res["OUTPUT_ORTHO"] == str(tmp_path / "ortho.tif")
    layer = QgsRasterLayer(res["OUTPUT_ORTHO"], "ortho", "gdal")
    assert layer.isValid() and layer.crs().authid().startswith("EPSG:326")


def test_residual_layers_share_one_exaggeration_and_label_ids(run_alg, oscene, tmp_path):
    from qgis.core import QgsVectorLayer
    gpkg = tmp_path / "res.gpkg"
    run_alg("gf4cal:refinerpc", {"INPUT": str(oscene / "s" / "scene.tif"), "GCPS": str(oscene / "s" / "gcps.gpkg"),
                                 "MODEL": 0, "OUTPUT_RPC": str(tmp_path / "r.RPB"), "OUTPUT_GPKG": str(gpkg)})
    factors = {}
    for name in ("residual_vectors", "residual_vectors_before"):
        layer = QgsVectorLayer(f"{gpkg}|layername={name}", name, "ogr")
        assert layer.isValid()
        values = {f["exaggeration"] for f in layer.getFeatures()}
        assert len(values) == 1
        factors[name] = values.pop()
    assert factors["residual_vectors"] == factors["residual_vectors_before"]
    gcps = QgsVectorLayer(f"{gpkg}|layername=gcps", "gcps", "ogr")
    assert gcps.isValid() and gcps.labelsEnabled()                # default style from layer_styles
    assert gcps.labeling().settings().fieldName == "id"


def test_loaded_layers_name_one_exaggeration_label_ids_and_ortho_is_georeferenced(qgis_app, oscene, tmp_path):
    """What a QGIS user sees after `refinerpc` with an ortho (issue 15): the before and after arrow layers are named
    with the same factor, which is the factor their features were drawn with; the GCP ids are labelled; the ortho
    (not the RPC VRT) is loaded, georeferenced in UTM over the GCPs."""
    import re

    import processing
    from qgis.core import QgsCoordinateTransform, QgsProject, QgsRasterLayer
    from gdal_gf4cal.gcp import read_gcps
    QgsProject.instance().removeAllMapLayers()
    res = processing.runAndLoadResults("gf4cal:refinerpc", {
        "INPUT": str(oscene / "s" / "scene.tif"), "GCPS": str(oscene / "s" / "gcps.gpkg"), "MODEL": 0,
        "DEM": str(oscene / "dem_egm96.tif"), "OUTPUT_RPC": str(tmp_path / "r.vrt"),
        "OUTPUT_GPKG": str(tmp_path / "r.gpkg"), "OUTPUT_ORTHO": str(tmp_path / "ortho.tif")})
    layers = list(QgsProject.instance().mapLayers().values())
    names = [lyr.name() for lyr in layers]
    arrows = {}
    for lyr in layers:
        m = re.fullmatch(r"residuals (before|after) \(x([0-9.e+-]+)\)", lyr.name())
        if m:
            arrows[m.group(1)] = (float(m.group(2)), lyr)
    assert set(arrows) == {"before", "after"}, names
    assert arrows["before"][0] == arrows["after"][0]
    for factor, lyr in arrows.values():      # the name's factor is the one the arrows were drawn with
        drawn = {f["exaggeration"] for f in lyr.getFeatures()}
        assert len(drawn) == 1 and drawn.pop() == pytest.approx(factor, rel=1e-6)
        assert lyr.renderer().type() == "graduatedSymbol"
    gcps = next(lyr for lyr in layers if lyr.name() == "gcps")
    assert gcps.labelsEnabled() and gcps.labeling().settings().fieldName == "id"
    assert {f["id"] for f in gcps.getFeatures()} == set(read_gcps(oscene / "s" / "gcps.gpkg")["id"].astype(str))
    ortho = [lyr for lyr in layers if isinstance(lyr, QgsRasterLayer)]
    assert len(ortho) == 1 and ortho[0].source() == res["OUTPUT_ORTHO"]          # the ortho, not the VRT
    assert ortho[0].name() == "scene ortho"                                       # not the parameter's label
    assert ortho[0].isValid() and ortho[0].crs().authid().startswith("EPSG:326")
    to_utm = QgsCoordinateTransform(gcps.crs(), ortho[0].crs(), QgsProject.instance())
    ext = ortho[0].extent()
    for f in gcps.getFeatures():             # every GCP lies on the ortho
        assert ext.contains(to_utm.transform(f.geometry().asPoint()))


def test_orthorectify_writes_nodata_mask_overviews_and_names_the_layer(qgis_app, oscene, tmp_path):
    """Issue 24: the ortho has a no-data value, an internal per-dataset mask that is exactly the valid (non-collar)
    area, internal overviews (bands and mask) down to <= 256 px, 512 px tiles; QGIS names it '<image stem> ortho'."""
    import processing
    from qgis.core import QgsProject, QgsRasterLayer
    QgsProject.instance().removeAllMapLayers()
    out = tmp_path / "ortho.tif"
    res = processing.runAndLoadResults("gf4cal:orthorectify", {
        "INPUT": str(oscene / "s" / "scene.tif"), "DEM": str(oscene / "s" / "dem.tif"), "RESOLUTION": 15.0,
        "OUTPUT": str(out)})
    layers = [lyr for lyr in QgsProject.instance().mapLayers().values() if isinstance(lyr, QgsRasterLayer)]
    assert [lyr.name() for lyr in layers] == ["scene ortho"]
    ds = gdal.Open(res["OUTPUT"])
    band = ds.GetRasterBand(1)
    assert band.GetNoDataValue() == 0.0
    assert band.GetMaskFlags() == gdal.GMF_PER_DATASET                  # a real mask, not derived from no-data
    assert not any(f.endswith(".msk") for f in ds.GetFileList())         # the mask is internal
    assert band.GetBlockSize() == [512, 512]
    w, h = ds.RasterXSize, ds.RasterYSize
    n_ovr = band.GetOverviewCount()
    assert n_ovr >= 2 and band.GetMaskBand().GetOverviewCount() == n_ovr
    assert min(w, h) / 2 ** n_ovr <= 256 < min(w, h) / 2 ** (n_ovr - 1)
    mask = band.GetMaskBand().ReadAsArray()
    valid = mask > 0
    assert 0.2 < valid.mean() < 0.95                              # a collar exists and is masked
    assert valid[0, 0] == 0 and valid[h // 2, w // 2]
    # the mask is the warp's own footprint: the rendered scene is non-zero where valid
    data = band.ReadAsArray()
    assert (data[valid] > 0).mean() > 0.99 and (data[~valid] == 0).all()
