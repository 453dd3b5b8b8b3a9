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
