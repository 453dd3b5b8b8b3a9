"""Small helper for tests: write a one-band GeoTIFF (optionally georeferenced, with no-data and an RPC)."""
from __future__ import annotations

from typing import Optional

import numpy as np

from gdal_gf4cal import RPCModel


def write_tif(path, arr, gt=None, epsg=None, nodata=None, rpc: Optional[RPCModel] = None, dtype=None) -> str:
    """Write ``arr`` to ``path`` as a tiled one-band GeoTIFF; returns the path as a string."""
    from osgeo import gdal, osr
    gdal.UseExceptions()
    arr = np.asarray(arr)
    gtype = {np.dtype("uint16"): gdal.GDT_UInt16, np.dtype("float32"): gdal.GDT_Float32,
             np.dtype("uint8"): gdal.GDT_Byte, np.dtype("float64"): gdal.GDT_Float64}[np.dtype(dtype or arr.dtype)]
    ds = gdal.GetDriverByName("GTiff").Create(str(path), arr.shape[1], arr.shape[0], 1, gtype, ["TILED=YES"])
    if gt is not None:
        ds.SetGeoTransform(gt)
    if epsg is not None:
        srs = osr.SpatialReference()
        srs.ImportFromEPSG(epsg)
        ds.SetProjection(srs.ExportToWkt())
    if rpc is not None:
        ds.SetMetadata(rpc.to_gdal_metadata(), "RPC")
    b = ds.GetRasterBand(1)
    if nodata is not None:
        b.SetNoDataValue(nodata)
    b.WriteArray(arr)
    ds = None
    return str(path)


def write_geoid_dem(src, dst, vertical_epsg: int) -> None:
    """The ellipsoidal DEM ``src`` as heights above EGM96 (H = h - N), declared as EPSG:4326+``vertical_epsg``."""
    from osgeo import gdal, osr
    from gdal_gf4cal.dem import geoid_transformer
    ds = gdal.Open(str(src))
    gt = ds.GetGeoTransform()
    h = ds.ReadAsArray().astype(float)
    W, H = ds.RasterXSize, ds.RasterYSize
    lon, lat = np.meshgrid(gt[0] + gt[1] * (np.arange(W) + 0.5), gt[3] + gt[5] * (np.arange(H) + 0.5))
    _, _, hg = geoid_transformer("egm96").transform(lon.ravel(), lat.ravel(), h.ravel(), direction="INVERSE")
    out = gdal.GetDriverByName("GTiff").Create(str(dst), W, H, 1, gdal.GDT_Float64)
    out.SetGeoTransform(gt)
    srs = osr.SpatialReference()
    srs.SetFromUserInput(f"EPSG:4326+{vertical_epsg}")
    out.SetSpatialRef(srs)
    out.GetRasterBand(1).WriteArray(hg.reshape(H, W))
    out = None
