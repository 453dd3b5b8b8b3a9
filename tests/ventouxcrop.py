"""The real Ventoux crop geometry for the crop tests (issue 19 item 8): a 500 x 500 px crop at product pixel
(5000, 5000) (pixel-unit geotransform without CRS, no RPC), the product's RPCs, and the product's physical-model
location grid (CNES, independent of the RPC; tests/data/crop_ventoux/PROVENANCE.txt) as truth."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from osgeo import gdal, osr

DATA = Path(__file__).parent / "data"
GRID = DATA / "crop_ventoux" / "GRID_PHR1B_P_201308051042194_SEN_690908101-001.tif"
GEOM = DATA / "rpc" / "ventoux_left_image.geom"
DIMAP = DATA / "rpc" / "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML"
ORIGIN = (5000.0, 5000.0)
SIZE = (500, 500)


def write_crop(path, gt=(5000.0, 1.0, 0.0, 5000.0, 0.0, 1.0), size=SIZE, epsg=None, rpc=None):
    """A crop like shareloc's left_image.tif (same size and georeference) whose two bands hold each pixel centre's
    own crop column and row (GDAL convention)."""
    W, H = size
    ds = gdal.GetDriverByName("GTiff").Create(str(path), W, H, 2, gdal.GDT_Float32)
    if gt is not None:
        ds.SetGeoTransform(gt)
    if epsg:
        srs = osr.SpatialReference()
        srs.ImportFromEPSG(epsg)
        ds.SetSpatialRef(srs)
    cols, rows = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    ds.GetRasterBand(1).WriteArray(cols.astype(np.float32))
    ds.GetRasterBand(2).WriteArray(rows.astype(np.float32))
    if rpc is not None:
        ds.SetMetadata(rpc.to_gdal_metadata(), "RPC")
    ds = None
    return path


def grid_nodes():
    """(col, row) product pixels (GDAL convention) and (lon, lat) at the grid's altitudes: arrays (n,), (k, n)."""
    g = gdal.Open(str(GRID))
    a = g.ReadAsArray()
    x0, dx, _, y0, _, dy = g.GetGeoTransform()
    j, i = np.meshgrid(np.arange(g.RasterXSize), np.arange(g.RasterYSize))
    alts = np.array([float(g.GetMetadataItem(f"LG_ALTITUDE_B{2 * k}", "GTiff")) for k in range(a.shape[0] // 2)])
    return ((x0 + dx * j).ravel(), (y0 + dy * i).ravel(), alts,
            a[0::2].reshape(len(alts), -1), a[1::2].reshape(len(alts), -1))


BIAS = (3.0, -2.0)          # image-space error of the product's RPC the GCPs reveal (sample, line) px
NOTE = "left_image.tif is a crop at (5000, 5000) of the product its RPC describes"


def grid_gcps(bias=BIAS):
    """GCPs at the physical grid's nodes over the crop and a margin around it, at its altitudes within the RPC's
    height range: ground (lon, lat, h), image = the node's crop pixel + ``bias``."""
    col, row, alts, lon, lat = grid_nodes()
    near = ((col > ORIGIN[0] - 210) & (col < ORIGIN[0] + SIZE[0] + 210) & (row > ORIGIN[1] - 210)
            & (row < ORIGIN[1] + SIZE[1] + 210))
    keep = [k for k, h in enumerate(alts) if 190 <= h <= 1960]
    rows = []
    for k in keep:
        for n in np.flatnonzero(near):
            rows.append({"id": f"a{int(alts[k])}_{n}", "lon": lon[k, n], "lat": lat[k, n], "h": alts[k],
                         "sample": col[n] - ORIGIN[0] + bias[0], "line": row[n] - ORIGIN[1] + bias[1]})
    return pd.DataFrame(rows)


def max_error_px(rpc, bias=BIAS):
    """Largest distance (px) between the RPC's projection of every grid node at every altitude and the node's crop
    pixel + ``bias``."""
    col, row, alts, lon, lat = grid_nodes()
    worst = 0.0
    for k, h in enumerate(alts):
        s, l = rpc.project(lon[k], lat[k], np.full(col.size, h))
        worst = max(worst, float(np.max(np.hypot(s - (col - ORIGIN[0] + bias[0]), l - (row - ORIGIN[1] + bias[1])))))
    return worst
