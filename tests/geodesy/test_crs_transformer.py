"""geodesy.crs_transformer: one Transformer per pair of CRSs, x first, the same coordinates as pyproj's own, usable
from the thread pool; a CRS pyproj cannot read raises its error (and is not kept)."""
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pyproj
import pytest

from gdal_gf4cal.geodesy import crs_transformer

UTM31N = "EPSG:32631"


def test_one_transformer_per_pair_same_coordinates_as_pyproj():
    wkt = pyproj.CRS.from_epsg(32631).to_wkt()
    tr = crs_transformer("EPSG:4326", wkt)
    assert crs_transformer("EPSG:4326", wkt) is tr                      # kept
    assert crs_transformer("EPSG:4326", UTM31N) is not tr                # another key: its own
    lon, lat = np.array([2.0, 3.5, 5.9]), np.array([43.1, 44.0, 45.2])
    ref = pyproj.Transformer.from_crs(4326, 32631, always_xy=True).transform(lon, lat)
    np.testing.assert_array_equal(tr.transform(lon, lat), ref)          # lon first in, easting first out
    x, y = ref
    assert 400e3 < x[1] < 600e3 and 4.8e6 < y[1] < 5.0e6
    back = crs_transformer(UTM31N, "EPSG:4326").transform(x, y)
    np.testing.assert_allclose(back, (lon, lat), atol=1e-9)


def test_same_results_from_the_thread_pool():
    tr = crs_transformer("EPSG:4326", UTM31N)
    rng = np.random.default_rng(3)
    pts = [(rng.uniform(0, 6, 5000), rng.uniform(-60, 60, 5000)) for _ in range(8)]
    with ThreadPoolExecutor(2) as pool:
        got = list(pool.map(lambda p: tr.transform(*p), pts))
    for p, g in zip(pts, got):
        np.testing.assert_array_equal(g, tr.transform(*p))


def test_unreadable_crs_raises_and_is_not_kept():
    with pytest.raises(pyproj.exceptions.CRSError):
        crs_transformer("EPSG:4326", "not a CRS")
    before = crs_transformer.cache_info().currsize
    with pytest.raises(pyproj.exceptions.CRSError):
        crs_transformer("EPSG:4326", "not a CRS")
    assert crs_transformer.cache_info().currsize == before
