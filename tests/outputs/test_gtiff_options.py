"""GeoTIFF creation options live in one place (``outputs.gtiff_options``): no other engine module spells a GTiff
layout or compression option (an AST scan of gdal_gf4cal/), and what it asks for is what GDAL writes."""
from __future__ import annotations

import ast

import numpy as np
from engine_source import engine_nodes
from osgeo import gdal

from gdal_gf4cal.outputs import gtiff_options
from gdal_gf4cal.simulate.terrain import write_dem_tif

#: Options that only gtiff_options may spell.
LAYOUT = ("TILED=", "BLOCKXSIZE=", "BLOCKYSIZE=", "COMPRESS=", "PREDICTOR=", "ZLEVEL=", "BIGTIFF=")


def test_no_engine_module_spells_gtiff_layout_options():
    found = [f"{where}: {node.value!r}" for where, node in engine_nodes(skip=("outputs.py",))
             if isinstance(node, ast.Constant) and isinstance(node.value, str)
             and any(node.value.upper().startswith(k) for k in LAYOUT)]
    assert found == []


def test_gdal_writes_what_the_options_ask(tmp_path):
    path = str(tmp_path / "t.tif")
    opts = gtiff_options(tile=128, predictor=3, zlevel=1, threads=2, extra=["INTERLEAVE=BAND"])
    ds = gdal.GetDriverByName("GTiff").Create(path, 300, 200, 2, gdal.GDT_Float32, opts)
    ds.GetRasterBand(1).WriteArray(np.arange(60000, dtype=np.float32).reshape(200, 300))
    ds = None
    ds = gdal.Open(path)
    structure = ds.GetMetadata("IMAGE_STRUCTURE")
    assert structure["COMPRESSION"] == "DEFLATE" and structure["PREDICTOR"] == "3"
    assert structure["INTERLEAVE"] == "BAND"
    assert ds.GetRasterBand(1).GetBlockSize() == [128, 128]
    assert np.array_equal(ds.GetRasterBand(1).ReadAsArray(), np.arange(60000, dtype=np.float32).reshape(200, 300))


def test_an_engine_writer_gets_the_shared_layout(tmp_path):
    """The simulator's DEM writer (one of the engine's GTiff writers): tiled in GDAL's 256 blocks, DEFLATE with the
    floating-point predictor, the heights back exactly."""
    heights = np.linspace(100.0, 900.0, 300 * 280, dtype=np.float32).reshape(280, 300)
    path = str(tmp_path / "dem.tif")
    write_dem_tif(path, heights, (5.0, 1e-4, 0.0, 44.0, 0.0, -1e-4))
    ds = gdal.Open(path)
    structure = ds.GetMetadata("IMAGE_STRUCTURE")
    assert structure["COMPRESSION"] == "DEFLATE" and structure["PREDICTOR"] == "3"
    assert ds.GetRasterBand(1).GetBlockSize() == [256, 256]
    assert np.array_equal(ds.GetRasterBand(1).ReadAsArray(), heights)
