"""Synthetic terrain for the simulator (METHODS §10): seeded fractal (spectral synthesis) DEMs as GeoTIFFs.

The DEM is written as an EPSG:4326 GeoTIFF of ellipsoidal heights (float32) and read back through
:class:`gdal_gf4cal.dem.DEM`, so the simulator and every downstream tool sample exactly the same surface.
"""
from __future__ import annotations

from typing import Tuple

import numpy as np
from osgeo import gdal, osr

from .._gdal import with_gdal_exceptions
from ..atomic import atomic_output
from ..outputs import gtiff_options


def fractal_surface(shape: Tuple[int, int], seed: int, beta: float = 3.2) -> np.ndarray:
    """Zero-mean, unit-range fractal surface by spectral synthesis (power spectrum ~ k^-beta), float64.

    ``beta`` about 3 gives natural-looking relief (Hurst exponent ~0.6); larger is smoother.
    """
    rng = np.random.default_rng(seed)
    ny, nx = shape
    ky = np.fft.fftfreq(ny)[:, None]
    kx = np.fft.rfftfreq(nx)[None, :]
    k = np.hypot(kx * max(nx, ny) / nx, ky * max(nx, ny) / ny)
    k[0, 0] = 1.0
    amp = k ** (-beta / 2.0)
    amp[0, 0] = 0.0
    spec = amp * (rng.standard_normal(k.shape) + 1j * rng.standard_normal(k.shape))
    z = np.fft.irfft2(spec, s=(ny, nx))
    z -= z.min()
    return z / z.max()


def synthetic_dem_array(bounds, cell_deg: float, seed: int, height_range=(3500.0, 6500.0), beta: float = 3.2):
    """Heights (float32, north-up) and GDAL geotransform covering ``bounds = (min_lon, min_lat, max_lon, max_lat)``.

    Heights span ``height_range`` exactly (min and max of the grid); the relief is ridged a little (``z**1.3``) so
    that valleys are broad and peaks sharp, as in Tibet.
    """
    x0, y0, x1, y1 = bounds
    # Cells to cover the bounds, rounded first: a width of exactly N cells (the caller's cell is often width / N)
    # came out as N +/- 1 ulp with the BLAS kernel, ceil gave N or N + 1 and an unrelated fractal (another FFT
    # size): every height of the scene changed with the CPU.
    nx = int(np.ceil(round((x1 - x0) / cell_deg, 6))) + 1
    ny = int(np.ceil(round((y1 - y0) / cell_deg, 6))) + 1
    z = fractal_surface((ny, nx), seed, beta) ** 1.3
    lo, hi = height_range
    h = (lo + (hi - lo) * z).astype(np.float32)
    gt = (x0, cell_deg, 0.0, y1, 0.0, -cell_deg)
    return h, gt


@with_gdal_exceptions
def write_dem_tif(path: str, heights: np.ndarray, geotransform) -> str:
    """Write a float32 EPSG:4326 GeoTIFF atomically (``/vsimem/`` paths are written directly)."""
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(4326)
    ny, nx = heights.shape
    with atomic_output(path) as target:
        ds = gdal.GetDriverByName("GTiff").Create(target, nx, ny, 1, gdal.GDT_Float32,
                                                  gtiff_options(predictor=3))
        ds.SetGeoTransform(geotransform)
        ds.SetProjection(srs.ExportToWkt())
        band = ds.GetRasterBand(1)
        band.WriteArray(heights)
        band.SetDescription("ellipsoidal height (m), WGS84")
        ds.SetMetadataItem("VERTICAL_DATUM", "WGS84 ellipsoid")
        band.FlushCache()
        ds = None
    return path
