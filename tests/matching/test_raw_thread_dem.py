"""matching.raw.thread_dem (issue 23): the DEM a caller works with before matching (register-pan-ms's pair
geometry) is the matcher's per-thread one, read once: the same object on one thread, another on another thread,
the same heights as a DEM opened afresh; constants as they are."""
from __future__ import annotations

import os
import threading

import numpy as np

from gdal_gf4cal import DEM
from gdal_gf4cal.matching.raw import thread_dem

SRTM = os.path.join(os.path.dirname(__file__), "..", "data", "matching", "srtm_ventoux_crop.tif")


def test_thread_dem_is_the_matchers_dem_of_this_thread():
    a = thread_dem(DEM.from_file(SRTM, nodata="nan"))
    b = thread_dem(DEM.from_user_input(SRTM, nodata="nan"))
    assert a is b and isinstance(a, DEM)
    other = []
    t = threading.Thread(target=lambda: other.append(thread_dem(DEM.from_file(SRTM, nodata="nan"))))
    t.start()
    t.join()
    assert other[0] is not a                         # a GDAL handle per thread
    assert thread_dem(DEM.from_file(SRTM, nodata="error")) is not a    # its own no-data policy kept
    assert thread_dem(DEM.from_file(SRTM, nodata="error")).nodata_policy == "error"
    fresh = DEM.from_file(SRTM, nodata="nan")
    lon, lat = np.meshgrid(np.linspace(5.2, 5.3, 7), np.linspace(44.15, 44.2, 5))
    assert np.array_equal(a.sample(lon, lat), fresh.sample(lon, lat), equal_nan=True)


def test_thread_dem_keeps_constants():
    c = DEM.from_user_input(250.0)
    assert thread_dem(c) is c
