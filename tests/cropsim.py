"""A crop of a real product with field GCPs around it (issue 19): the QuickBird-2 RPC of GDAL's autotest
(tests/data/rpc/rpc.vrt, 30402 x 32682 px) cut to an 850 x 1450 px "crop" by shifting its offsets (what a vendor or a
cutting tool does: the scales stay the product's), a DEM over it and GCPs made by projecting ground points of known
image positions with the crop's RPC, plus a known bias and seeded noise. Some GCPs lie outside the crop."""
from __future__ import annotations

import os

import numpy as np

DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data")
ORIGIN = (12000, 15000)                 # the crop's place in the product (px)
SIZE = (850, 1450)                      # the crop (px)
BIAS = (3.0, -2.0)                      # measured - RPC, px (sample, line)
NOISE_PX = 0.3
#: Image positions of the GCPs (fractions of the crop's width and height): six inside, four outside by up to 35 %.
INSIDE = [(0.1, 0.1), (0.9, 0.15), (0.5, 0.5), (0.15, 0.85), (0.85, 0.9), (0.4, 0.25)]
OUTSIDE = {"F7": (1.33, -0.025), "F8": (-0.22, 0.6), "F9": (0.5, 1.35), "F10": (-0.35, -0.3)}


def crop_rpc():
    from gdal_gf4cal.rpc import RPCModel
    full = RPCModel.from_file(os.path.join(DATA, "rpc", "rpc.vrt"))
    return full.replace(samp_off=full.samp_off - ORIGIN[0], line_off=full.line_off - ORIGIN[1])


def terrain(lon, lat, lon0, lat0, base=300.0):
    """A gentle slope, about ``base`` + 40 m +/- 30 m over the crop (m, ellipsoidal)."""
    return base + 4e3 * (np.asarray(lon) - lon0) - 2e3 * (np.asarray(lat) - lat0) + 40.0


def write_crop(d, base=300.0):
    """``crop.tif`` (RPC in its tags) and ``dem.tif`` (the terrain, EPSG:4326, heights ellipsoidal) in ``d``."""
    from osgeo import gdal, osr
    gdal.UseExceptions()
    rpc = crop_rpc()
    img = os.path.join(d, "crop.tif")
    ds = gdal.GetDriverByName("GTiff").Create(img, SIZE[0], SIZE[1], 1, gdal.GDT_Byte, ["COMPRESS=DEFLATE"])
    ds.GetRasterBand(1).WriteArray((np.add.outer(np.arange(SIZE[1]), np.arange(SIZE[0])) % 251).astype(np.uint8))
    ds.SetMetadata(rpc.to_gdal_metadata(), "RPC")
    ds = None
    # the DEM covers the crop with 2 crop sizes around it (the far GCPs too)
    s = np.array([-2, 3, 3, -2]) * SIZE[0]
    l_ = np.array([-2, -2, 3, 3]) * SIZE[1]
    lon, lat = rpc.localize(s, l_, base)
    x0, x1, y0, y1 = lon.min(), lon.max(), lat.min(), lat.max()
    n = 200
    dem = os.path.join(d, "dem.tif")
    ds = gdal.GetDriverByName("GTiff").Create(dem, n, n, 1, gdal.GDT_Float32)
    ds.SetGeoTransform((x0, (x1 - x0) / n, 0, y1, 0, -(y1 - y0) / n))
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(4326)
    ds.SetProjection(srs.ExportToWkt())
    gx, gy = np.meshgrid(x0 + (np.arange(n) + 0.5) * (x1 - x0) / n, y1 - (np.arange(n) + 0.5) * (y1 - y0) / n)
    lon0, lat0 = rpc.localize(0.0, 0.0, base)
    ds.GetRasterBand(1).WriteArray(terrain(gx, gy, lon0, lat0, base).astype(np.float32))
    ds = None
    return img, dem


def gcps(far: float = 0.0, seed: int = 7, base: float = 300.0):
    """The GCP table (id, lon, lat, h, sample, line): ground from the crop's RPC at true image positions on the
    terrain, measured = true + BIAS + noise. ``far``: the outside GCPs moved this many image sizes farther out."""
    import pandas as pd
    rpc = crop_rpc()
    ids = [f"F{i + 1}" for i in range(len(INSIDE))] + list(OUTSIDE)
    fr = np.array(INSIDE + list(OUTSIDE.values()), float)
    out = np.arange(len(fr)) >= len(INSIDE)
    fr[out] += far * np.sign(fr[out] - 0.5)
    s, l_ = fr[:, 0] * SIZE[0], fr[:, 1] * SIZE[1]
    lon0, lat0 = rpc.localize(0.0, 0.0, base)
    lon, lat = rpc.localize(s, l_, np.full(s.size, base + 40.0))
    for _ in range(4):                              # onto the terrain: (lon, lat, h) projects to (s, l) exactly
        h = terrain(lon, lat, lon0, lat0, base)
        lon, lat = rpc.localize(s, l_, h)
    rng = np.random.default_rng(seed)
    return pd.DataFrame({"id": ids, "lon": lon, "lat": lat, "h": h,
                         "sample": s + BIAS[0] + rng.normal(0, NOISE_PX, s.size),
                         "line": l_ + BIAS[1] + rng.normal(0, NOISE_PX, s.size)})
