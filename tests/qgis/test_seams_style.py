"""Issue 24: block calibration's ``seams`` layer as QGIS loads it: its own style graduated by the after-offset (not
the GCP role style: no grey "other" squares), arrows of the after-offset drawn eastwards for a sample offset, the
exaggeration stated in the layer's title."""
from __future__ import annotations

import re

import numpy as np

from test_render import _render


def _write_seams(path, ds_after, dl_after, n_pairs=3, n=20):
    from gdal_gf4cal.report import write_points_layer
    line = np.tile(np.linspace(0.0, 4000.0, n), n_pairs)
    lon = np.repeat(100.0 + 0.05 * np.arange(n_pairs), n)
    lat = 40.0 - line * 1e-5                         # 1.11 m per line
    cols = {"pair": np.repeat([f"c{k}|c{k + 1}" for k in range(n_pairs)], n).astype(object),
            "point_id": np.arange(line.size).astype(str).astype(object), "line_b": line,
            "ds_before": np.full(line.size, 2.0), "dl_before": np.zeros(line.size),
            "ds_after": np.asarray(ds_after, float), "dl_after": np.asarray(dl_after, float)}
    cols["offset_px_before"] = np.hypot(cols["ds_before"], cols["dl_before"])
    cols["offset_px_after"] = np.hypot(cols["ds_after"], cols["dl_after"])
    write_points_layer(path, "seams", cols, lon, lat, description="seams")
    return lon, lat


def test_seams_layer_graduated_arrows_factor_in_the_title(qgis_app, tmp_path):
    from qgis.core import QgsVectorLayer
    from gdal_gf4cal.report.gpkg import layer_titles
    gpkg = tmp_path / "res.gpkg"
    rng = np.random.default_rng(3)
    ds_after = np.abs(rng.normal(0.3, 0.1, 60)) + 0.05        # every offset eastwards (sample +), none along line
    lon, lat = _write_seams(gpkg, ds_after, np.zeros(60))
    title = layer_titles(gpkg)["seams"]
    m = re.fullmatch(r"seams after \(x([0-9.e+]+)\)", title)
    assert m, title
    layer = QgsVectorLayer(f"{gpkg}|layername=seams", title, "ogr")
    assert layer.isValid()
    r = layer.renderer()
    assert r.type() == "graduatedSymbol" and r.classAttribute() == "offset_px_after"
    ranges = r.ranges()           # keep the copies alive: a range's symbol belongs to it
    assert len(ranges) >= 4 and ranges[0].lowerValue() == 0.0 and ranges[-1].upperValue() >= ds_after.max()
    sym = ranges[0].symbol()
    assert [sym.symbolLayer(i).layerType() for i in range(sym.symbolLayerCount())] == ["GeometryGenerator",
                                                                                    "SimpleMarker"]
    ext = layer.extent()
    ext.scale(1.6)
    rgb = _render([layer], ext, str(tmp_path / "seams.png"), size=600)
    drawn = np.argwhere((rgb != 255).any(-1))
    assert drawn.shape[0] > 500
    # the arrows point east of the tie points: beside each seam, drawn pixels on its east side, not on its west
    xs = drawn[:, 1]
    for x_seam in (np.unique(lon) - ext.xMinimum()) / ext.width() * 600:
        east = int(((xs > x_seam + 5) & (xs < x_seam + 40)).sum())
        west = int(((xs < x_seam - 5) & (xs > x_seam - 40)).sum())
        assert east > 50 and east > 5 * west, (x_seam, east, west)
