"""The styled residual GeoPackage rendered headless by QGIS: the default styles stored in layer_styles draw
arrows coloured by magnitude. The composite PNG is kept as an artifact under test-artifacts/."""
from __future__ import annotations

import os

import numpy as np

RAMP = ["#2c7bb6", "#00a6ca", "#90eb9d", "#f9d057", "#f29e2e", "#d7191c"]  # gdal_gf4cal.report._RAMP


def _render(layers, extent, path, size=900):
    from qgis.core import QgsMapRendererParallelJob, QgsMapSettings
    from qgis.PyQt.QtCore import QSize
    from qgis.PyQt.QtGui import QColor
    settings = QgsMapSettings()
    settings.setLayers(layers)  # first = top
    settings.setDestinationCrs(layers[0].crs())
    settings.setOutputSize(QSize(size, size))
    settings.setBackgroundColor(QColor("white"))
    settings.setExtent(extent)
    job = QgsMapRendererParallelJob(settings)
    job.start()
    job.waitForFinished()
    image = job.renderedImage()
    assert image.save(path, "PNG")
    from osgeo import gdal
    ds = gdal.Open(path)
    return np.stack([ds.GetRasterBand(b).ReadAsArray() for b in (1, 2, 3)], -1).astype(int)


def _count(rgb, hex_colour, tol=12):
    c = [int(hex_colour[i:i + 2], 16) for i in (1, 3, 5)]
    return int((np.abs(rgb - np.array(c)).max(-1) <= tol).sum())


def test_styled_gpkg_renders_arrows(run_alg, scene, tmp_path, artifacts_dir):
    from qgis.core import QgsVectorLayer
    files, truth = scene
    res, _ = run_alg("gf4cal:refinerpc", {
        "INPUT": files["image"], "GCPS": files["gcps"], "MODEL": 2, "OUTPUT_RPC": str(tmp_path / "r.RPB"),
        "OUTPUT_GPKG": str(tmp_path / "residuals.gpkg")})
    gpkg = res["OUTPUT_GPKG"]
    layers = {n: QgsVectorLayer(f"{gpkg}|layername={n}", n, "ogr")
              for n in ("gcps", "residual_vectors", "residual_vectors_before", "footprint")}
    for name, layer in layers.items():
        assert layer.isValid(), name
    vectors = layers["residual_vectors"]
    assert vectors.renderer().type() == "graduatedSymbol"
    ranges = vectors.renderer().ranges()
    symbol = ranges[0].symbol()
    assert symbol.symbolLayer(0).layerType() == "ArrowLine"
    extent = layers["footprint"].extent()
    extent.scale(1.15)

    # the arrows alone: drawn, in the magnitude colours, several classes
    rgb = _render([vectors], extent, str(tmp_path / "arrows.png"))
    drawn = (rgb != 255).any(-1).sum()
    per_class = {c: _count(rgb, c) for c in RAMP}
    assert drawn > 2000, drawn
    assert sum(per_class.values()) > 0.2 * drawn, per_class  # fills in class colours (the rest: outlines, AA)
    assert sum(v > 50 for v in per_class.values()) >= 2, per_class  # coloured by magnitude, not one colour

    # the footprint alone draws none of the arrow colours (so the counts above come from the arrows)
    rgb_fp = _render([layers["footprint"]], extent, str(tmp_path / "footprint.png"))
    assert sum(_count(rgb_fp, c) for c in RAMP) < 20

    # the composite, kept as the artifact
    out = os.path.join(artifacts_dir, "residuals_render.png")
    rgb_all = _render([layers["gcps"], layers["residual_vectors"], layers["residual_vectors_before"],
                       layers["footprint"]], extent, out)
    assert _count(rgb_all, "#1f4fd1") > 50  # control points (blue triangles)
    assert _count(rgb_all, "#18a025") > 20  # check points (green circles)
    assert _count(rgb_all, "#e4002b") > 10  # the flagged blunder (red cross)
    assert os.path.getsize(out) > 10000
