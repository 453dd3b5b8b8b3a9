"""QGIS simulatescene for gf7 (issue 20): the same writer as the CLI (4-band MS), and a crop at its place in the
product (origin column/row: pixel-unit geotransform, product RPC)."""
from __future__ import annotations

import pytest


def test_gf7_crop_with_origin(run_alg, tmp_path):
    from osgeo import gdal
    folder = tmp_path / "gf7"
    res, fb = run_alg("gf4cal:simulatescene", {"SENSOR": 4, "SEED": 1, "WIDTH": 256, "HEIGHT": 256, "CROP_X0": 10112,
                                               "CROP_Y0": 4000, "N_GCPS": 5, "RENDER": True,
                                               "OUTPUT_FOLDER": str(folder)})
    assert res["RPC"].endswith("product.RPB")
    pan = gdal.Open(res["IMAGE"])
    assert pan.GetGeoTransform() == (10112.0, 1.0, 0.0, 4000.0, 0.0, 1.0) and pan.RasterCount == 1
    ms = gdal.Open(str(folder / "ms" / "scene.tif"))
    assert (ms.RasterXSize, ms.RasterCount) == (64, 4) and ms.GetGeoTransform()[:4] == (2528.0, 1.0, 0.0, 1000.0)


def test_crop_origin_without_size_is_refused(run_alg, tmp_path):
    from qgis.core import QgsProcessingException
    with pytest.raises(QgsProcessingException, match="crop origin"):
        run_alg("gf4cal:simulatescene", {"SENSOR": 4, "CROP_X0": 0, "CROP_Y0": 0,
                                         "OUTPUT_FOLDER": str(tmp_path / "x")})
