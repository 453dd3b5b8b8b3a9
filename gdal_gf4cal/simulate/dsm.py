"""Synthetic urban DSM with stereo-like holes (METHODS §2, §10): buildings on real terrain, no-data blobs at walls.

A stereo pipeline's DSM has sharp building walls and holes (no-data) where one view was occluded, i.e. next to
walls. :func:`urban_dsm` builds one deterministically (fixed seed) on the heights of any :class:`DEM` (e.g. real
SRTM) in the UTM zone of its centre, and writes it as a float32 GeoTIFF with a no-data value; ``filled_path`` also
gets the same DSM with its holes filled by GDAL's FillNodata (what GDAL's RPC_DEM needs: it cannot bridge holes).
"""
from __future__ import annotations

from typing import Optional

import numpy as np
from osgeo import gdal, osr

from .._gdal import with_gdal_exceptions
from ..geodesy import crs_transformer

NODATA = -9999.0


def _utm_epsg(lon: float, lat: float) -> int:
    zone = int(np.floor((lon + 180.0) / 6.0)) % 60 + 1
    return (32600 if lat >= 0 else 32700) + zone


def _buildings(terrain: np.ndarray, rng, res_m: float, built_fraction: float):
    """Flat-roofed rectangular buildings 5-40 m high on ``terrain``: (surface, list of (r0, r1, c0, c1))."""
    ny, nx = terrain.shape
    dsm = terrain.copy()
    occupied = np.zeros(terrain.shape, dtype=bool)
    boxes = []
    for _ in range(4000):
        if occupied.mean() >= built_fraction:
            break
        h_px, w_px = (rng.uniform(8.0, 30.0, 2) / res_m).astype(int)
        r0, c0 = int(rng.integers(4, ny - h_px - 4)), int(rng.integers(4, nx - w_px - 4))
        r1, c1 = r0 + h_px, c0 + w_px
        if occupied[r0 - 6:r1 + 6, c0 - 6:c1 + 6].any():      # streets of 3 m at least
            continue
        occupied[r0:r1, c0:c1] = True
        dsm[r0:r1, c0:c1] = terrain[r0:r1, c0:c1].max() + rng.uniform(5.0, 40.0)
        boxes.append((r0, r1, c0, c1))
    return dsm, boxes


def _holes(shape, boxes, rng, res_m: float, hole_fraction: float) -> np.ndarray:
    """No-data mask: elliptic blobs 2-8 m across centred on a building wall (occlusion-like), until
    ``hole_fraction`` of the raster."""
    ny, nx = shape
    yy, xx = np.mgrid[0:ny, 0:nx]
    mask = np.zeros(shape, dtype=bool)
    for _ in range(20 * len(boxes) + 100):
        if mask.mean() >= hole_fraction or not boxes:
            break
        r0, r1, c0, c1 = boxes[int(rng.integers(len(boxes)))]
        side = int(rng.integers(4))
        if side < 2:      # north or south wall
            cy, cx = (r0 if side == 0 else r1), rng.uniform(c0, c1)
        else:             # west or east wall
            cy, cx = rng.uniform(r0, r1), (c0 if side == 2 else c1)
        ry, rx = rng.uniform(1.0, 4.0, 2) / res_m
        mask |= ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 <= 1.0
    return mask


@with_gdal_exceptions
def urban_dsm(path, terrain, center, *, size_px: int = 400, res_m: float = 0.5, built_fraction: float = 0.3,
              hole_fraction: float = 0.11, seed: int = 0, filled_path: Optional[str] = None) -> dict:
    """Write a synthetic urban DSM (float32 GeoTIFF, UTM, no-data ``NODATA``) and return what it holds.

    Parameters
    ----------
    path : output GeoTIFF.
    terrain : a :class:`~gdal_gf4cal.dem.DEM` giving the ground's ellipsoidal heights (e.g. SRTM with its geoid).
    center : (lon, lat) of the DSM's centre, degrees.
    size_px, res_m : raster size (square) and pixel size in metres.
    built_fraction, hole_fraction : share of the raster covered by buildings and by no-data.
    filled_path : if given, the same DSM with its holes filled (GDAL FillNodata) is written there too.

    Returns
    -------
    dict: ``epsg``, ``geotransform``, ``hole_fraction`` (measured), ``n_buildings``, ``height_range`` (m).
    """
    rng = np.random.default_rng(seed)
    epsg = _utm_epsg(*center)
    to_utm = crs_transformer("EPSG:4326", f"EPSG:{epsg}")
    cx, cy = to_utm.transform(*center)
    half = 0.5 * size_px * res_m
    gt = (cx - half, res_m, 0.0, cy + half, 0.0, -res_m)
    xs = gt[0] + (np.arange(size_px) + 0.5) * res_m
    ys = gt[3] - (np.arange(size_px) + 0.5) * res_m
    xx, yy = np.meshgrid(xs, ys)
    lon, lat = to_utm.transform(xx.ravel(), yy.ravel(), direction="INVERSE")
    ground = np.asarray(terrain.sample(lon, lat), dtype=float).reshape(size_px, size_px)
    dsm, boxes = _buildings(ground, rng, res_m, built_fraction)
    holes = _holes(dsm.shape, boxes, rng, res_m, hole_fraction)
    out = np.where(holes, NODATA, dsm).astype(np.float32)
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(epsg)
    targets = [(str(path), False)] + ([(str(filled_path), True)] if filled_path else [])
    for target, fill in targets:
        ds = gdal.GetDriverByName("GTiff").Create(target, size_px, size_px, 1, gdal.GDT_Float32)
        ds.SetGeoTransform(gt)
        ds.SetProjection(srs.ExportToWkt())
        band = ds.GetRasterBand(1)
        band.SetNoDataValue(NODATA)
        band.WriteArray(out)
        if fill:
            gdal.FillNodata(band, None, maxSearchDist=size_px, smoothingIterations=0)
        ds = None
    return {"epsg": epsg, "geotransform": gt, "hole_fraction": float(holes.mean()), "n_buildings": len(boxes),
            "height_range": (float(dsm.min()), float(dsm.max()))}
