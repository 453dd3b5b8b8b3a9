"""The engine never switches GDAL exceptions on for the process (issue 10 "Must show"): no ``UseExceptions()`` call
in gdal_gf4cal/ outside the scoped helper (an AST scan), and running engine functions leaves the setting as it was."""
from __future__ import annotations

import ast
import subprocess
import sys

from engine_source import engine_nodes


def test_no_use_exceptions_call_in_the_engine():
    calls = [where for where, node in engine_nodes(skip=("_gdal.py",))
             if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
             and node.func.attr in ("UseExceptions", "DontUseExceptions")]
    assert calls == []


SCRIPT = r"""
import numpy as np
from osgeo import gdal, ogr, osr
state = lambda: (gdal.GetUseExceptions(), ogr.GetUseExceptions(), osr.GetUseExceptions())
before = state()
import gdal_gf4cal
from gdal_gf4cal import DEM
from gdal_gf4cal._gdal import gdal_exceptions, open_raster
from gdal_gf4cal.simulate.terrain import write_dem_tif
assert state() == before, ("import", state())
write_dem_tif("/vsimem/d.tif", np.full((4, 4), 100.0, np.float32), (10, 0.01, 0, 20, 0, -0.01))
dem = DEM.from_file("/vsimem/d.tif")
assert abs(float(dem.height(10.015, 19.985)) - 100.0) < 1e-9
assert state() == before, ("engine", state())
with gdal_exceptions():
    assert state() == (1, 1, 1)
    with gdal_exceptions():
        assert state() == (1, 1, 1)
    assert state() == (1, 1, 1)
assert state() == before, ("scope", state())
try:
    open_raster("/nonexistent/x.tif", what="DEM")
except gdal_gf4cal.Gf4calError as exc:
    assert "cannot open DEM /nonexistent/x.tif" in str(exc), exc
assert state() == before
print("ok", before)
"""


def test_engine_leaves_the_process_setting_as_it_was():
    # A fresh interpreter: the test modules of this suite switch exceptions on for themselves.
    for prelude in ("", "from osgeo import gdal; gdal.UseExceptions()\n"):
        proc = subprocess.run([sys.executable, "-c", prelude + SCRIPT], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.startswith("ok")
