"""matching.raw.thread_dem (issue 23): the DEM a caller works with before matching (register-pan-ms's pair
geometry) is the matcher's one, read once: the same object on every thread (a DEM opens its own GDAL handle per
thread: the pool threads of the matching do not read the raster again), the same heights as a DEM opened afresh,
on any thread; constants as they are."""
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
    lon, lat = np.meshgrid(np.linspace(5.2, 5.3, 7), np.linspace(44.15, 44.2, 5))
    other = []

    def on_other_thread():
        d = thread_dem(DEM.from_file(SRTM, nodata="nan"))
        other.extend([d, d.sample(lon, lat)])
    t = threading.Thread(target=on_other_thread)
    t.start()
    t.join()
    assert other[0] is a                             # one DEM for every thread (its handles per thread)
    assert thread_dem(DEM.from_file(SRTM, nodata="error")) is not a    # its own no-data policy kept
    assert thread_dem(DEM.from_file(SRTM, nodata="error")).nodata_policy == "error"
    fresh = DEM.from_file(SRTM, nodata="nan").sample(lon, lat)
    assert np.array_equal(a.sample(lon, lat), fresh, equal_nan=True)
    assert np.array_equal(other[1], fresh, equal_nan=True)


def test_thread_dem_keeps_constants():
    c = DEM.from_user_input(250.0)
    assert thread_dem(c) is c
