"""Reference resampling: decimated block reads and the batched (one interpolation per tile) sampling path."""
from __future__ import annotations

import numpy as np
import pytest
from osgeo import gdal

from rasters import write_tif

from gdal_gf4cal.matching.resample import ReferenceImage, _sample_reference, _sample_reference_each, read_block

gdal.UseExceptions()


def _write(path, arr, nodata=None):
    return write_tif(path, np.asarray(arr, dtype=np.float32), gt=(100.0, 0.001, 0.0, 30.0, 0.0, -0.001), epsg=4326,
                     nodata=nodata)


@pytest.fixture()
def texture():
    """Smooth random texture (a Gaussian-filtered noise field, seeded), 300 x 260 px."""
    from scipy import ndimage
    rng = np.random.default_rng(7)
    return 1000 + 200 * ndimage.gaussian_filter(rng.standard_normal((300, 260)), 1.5, mode="wrap")


def test_read_block_decimated_is_the_block_mean_and_outside_is_nan(tmp_path, texture):
    path = _write(tmp_path / "t.tif", texture.astype(np.float32))
    ds = gdal.Open(path)
    band = ds.GetRasterBand(1)
    # Inside: GDAL's average over whole 4 x 4 cells equals the block mean.
    got = read_block(band, 260, 300, None, 40, 20, 64, 32, 4)
    want = texture[20:52, 40:104].reshape(8, 4, 16, 4).mean(axis=(1, 3))
    np.testing.assert_allclose(got, want, rtol=1e-5)
    # Straddling the top-left corner: only whole cells inside the raster are read, the rest is NaN.
    got = read_block(band, 260, 300, None, -6, -8, 16, 16, 4)
    assert got.shape == (4, 4)
    assert np.all(np.isnan(got[:2])) and np.all(np.isnan(got[:, :2]))
    np.testing.assert_allclose(got[2:, 2:], texture[0:8, 2:10].reshape(2, 4, 2, 4).mean(axis=(1, 3)), rtol=1e-5)


def test_batched_sampling_matches_the_one_window_path(tmp_path, texture):
    """The batched path (one prefilter + one map_coordinates for all windows of a tile) gives the values of the
    per-window path evaluated with a wide margin (the exact spline interpolant), and the same no-data samples."""
    tex = texture.astype(np.float32)
    tex[:40, :60] = -9999  # a no-data corner
    ref = ReferenceImage(_write(tmp_path / "t.tif", tex, nodata=-9999))
    rng = np.random.default_rng(1)
    n, w = 6, 24
    j, k = np.mgrid[0:w, 0:w].astype(float)
    corners = np.array([[10.0, 12.0], [50.0, 30.0], [150.0, 200.0], [200.0, 100.0], [80.0, 220.0], [180.0, 20.0]])
    rot = rng.uniform(-0.05, 0.05, n)
    fx = corners[:, 0, None, None] + k * np.cos(rot)[:, None, None] - j * np.sin(rot)[:, None, None] + 0.37
    fy = corners[:, 1, None, None] + k * np.sin(rot)[:, None, None] + j * np.cos(rot)[:, None, None] + 0.61
    batched = _sample_reference_each(ref, fx, fy, 1, 0.0, 4, 3)
    exact = np.array([_sample_reference(ref, fx[i:i + 1], fy[i:i + 1], 1, 0.0, 30, 3)[0] for i in range(n)])
    per_window = np.array([_sample_reference(ref, fx[i:i + 1], fy[i:i + 1], 1, 0.0, 4, 3)[0] for i in range(n)])
    assert np.isnan(batched[0]).any() and not np.isnan(batched[2]).any()  # the no-data corner is seen
    np.testing.assert_array_equal(np.isnan(batched), np.isnan(per_window))
    ok = ~np.isnan(batched) & ~np.isnan(exact)
    assert np.nanmax(np.abs(batched - exact)[ok]) < 1e-3 * tex[tex > 0].std()
