"""``gf4cal ortho`` / QGIS "Orthorectify": an orthoimage from an image, its (refined) RPC and a DEM.

GDAL does the warping (``gdal.Warp`` with the RPC transformer and ``RPC_DEM``, on ``GF4CAL_NUM_THREADS`` threads,
into a warped VRT with an alpha band, written by ``gdal.Translate`` as a tiled, compressed GeoTIFF with a no-data
value, the alpha as an internal mask and internal overviews: no black collar, fast to pan). This module makes sure
the DEM GDAL samples holds ELLIPSOIDAL heights: when the DEM's heights are above a geoid (declared by its compound
CRS, ``geoid="auto"``, or named with ``geoid=``) it writes a temporary ellipsoidal GeoTIFF over the image footprint
(the DEM's own grid, ``h = H + N`` at each pixel centre through PROJ's grid of that geoid, blocks of pixels over the
thread pool of :mod:`gdal_gf4cal.threads`) and warps with it; GDAL's own vertical
handling is switched off (``RPC_DEM_APPLY_VDATUM_SHIFT=FALSE``), so a declared datum whose grid is missing is
refused (:class:`~gdal_gf4cal.geoid.GeoidGridMissing`, naming the grid) instead of silently ignored. The result
equals ``gdalwarp -rpc -to RPC_DEM=<ellipsoidal DEM>`` with the same grid pixel for pixel, whatever the warped
blocks and threads (:func:`whole_ortho_kernel`).
"""
from __future__ import annotations

import os
import warnings
from typing import Any, Dict, Optional, Tuple

import numpy as np

from ..errors import CancelledError, DEMError, Gf4calError
from ..geodesy import crs_transformer
from ..outputs import OutputSet, check_raster, gtiff_options
from ..threads import blas_serial, num_threads, split_points
from ._common import _open_image, cancel_check, collect_warnings, finish_report

#: Resampling names accepted by :func:`orthorectify` (GDAL's ``-r`` names).
RESAMPLING = ("near", "bilinear", "cubic", "cubicspline", "lanczos", "average", "mode")


def creation_options(data_type: int) -> list:
    """Creation options of an ortho of GDAL type ``data_type``: 512-px tiles, DEFLATE level 1 with the predictor of
    the type (2 for integers, 3 for floats; none for complex), BigTIFF when needed (COG-friendly layout). Against
    GDAL's level 6 without a predictor (before): the QuickBird-2 ortho of bench_refine_ortho (Byte) 17 % smaller in
    70 % of the compression CPU, a 11,048 x 9,552 UInt16 raster 3 % smaller in 62 %, the real Pleiades Ventoux crop's
    ortho (UInt16) 10 % smaller in the same CPU."""
    from osgeo import gdal
    if gdal.DataTypeIsComplex(data_type):
        predictor = None
    else:
        predictor = 3 if data_type in (gdal.GDT_Float32, gdal.GDT_Float64) else 2
    return gtiff_options(tile=512, predictor=predictor, zlevel=1)


#: Overviews are built (factors 2, 4, 8, ...) until the smaller side is at most this many pixels.
OVERVIEW_MIN_SIZE = 256


def overview_factors(width: int, height: int, min_size: int = OVERVIEW_MIN_SIZE) -> list:
    """Overview decimation factors 2, 4, 8, ... until the smaller side of the coarsest level is <= ``min_size`` px
    (none for a raster already that small)."""
    factors, f = [], 2
    while min(width, height) / (f // 2) > min_size:
        factors.append(f)
        f *= 2
    return factors


def _write_ortho(warped, out_path: str, resampling: str, callback) -> Dict[str, Any]:
    """The warped VRT (image bands + alpha) written as the ortho GeoTIFF: tiled, compressed, the image bands with a
    no-data value (the source's, else 0; valid pixels equal to it lifted, :func:`lift_valid_nodata`) and the alpha as
    an internal per-dataset mask (QGIS and GDAL draw no collar), internal overviews of the bands and the mask.
    Returns ``res_m``, ``size_px``, ``nodata``, ``overviews`` and ``empty`` (no valid pixel)."""
    from osgeo import gdal
    from ..outputs import raster_has_data
    n = warped.RasterCount - 1                          # the last band is the alpha
    nodata = warped.GetRasterBand(1).GetNoDataValue()
    nodata = 0.0 if nodata is None else float(nodata)
    prev = gdal.GetThreadLocalConfigOption("GDAL_TIFF_INTERNAL_MASK", None)
    gdal.SetThreadLocalConfigOption("GDAL_TIFF_INTERNAL_MASK", "YES")
    try:
        ds = gdal.Translate(out_path, warped, format="GTiff", bandList=list(range(1, n + 1)), maskBand=n + 1,
                            noData=nodata, creationOptions=creation_options(warped.GetRasterBand(1).DataType),
                            callback=lambda f, m, d: callback(0.9 * f, m, d))
        if ds is None:
            raise Gf4calError("writing the ortho failed without a message")
        lifted, value = lift_valid_nodata(ds, nodata)
        if lifted:
            warnings.warn(f"{lifted} valid pixel(s) of the ortho equal to its no-data value {nodata:g} were written "
                          f"as {value:g} (GIS software hides a pixel with the no-data value even where the mask "
                          "says valid)")
        factors = overview_factors(ds.RasterXSize, ds.RasterYSize)
        if factors:
            method = {"near": "NEAREST", "mode": "MODE"}.get(resampling, "AVERAGE")
            ds.BuildOverviews(method, factors, callback=lambda f, m, d: callback(0.9 + 0.1 * f, m, d))
        gt = ds.GetGeoTransform()
        out = {"res_m": float(abs(gt[1])), "size_px": [ds.RasterXSize, ds.RasterYSize], "nodata": nodata,
               "overviews": len(factors), "empty": not raster_has_data(ds)}
        ds = None
    finally:
        gdal.SetThreadLocalConfigOption("GDAL_TIFF_INTERNAL_MASK", prev)
    return out


def lift_valid_nodata(ds, nodata: float) -> Tuple[int, float]:
    """Valid pixels (inside the mask) of ``ds``'s bands equal to the no-data value, set to the next value above it
    (below it at the type's maximum), as GDAL's warper does from 3.11: QGIS hides a pixel equal to the no-data value
    even where the mask says valid, and a dark 0 of an image without a no-data value (0 is the ortho's then) would
    show as a hole. Block by block (the mask read only for a block holding the value, a block written only when one
    of its valid pixels does). Returns ``(pixels changed, the value they got)``."""
    from osgeo import gdal_array
    band1 = ds.GetRasterBand(1)
    dtype = np.dtype(gdal_array.GDALTypeCodeToNumericTypeCode(band1.DataType))
    if dtype.kind not in "uif" or not np.isfinite(nodata):
        return 0, nodata
    if dtype.kind == "f":
        if abs(nodata) > np.finfo(dtype).max:
            return 0, nodata                                      # beyond the type's range: no pixel can hold it
        nd = dtype.type(nodata)
        value = np.nextafter(nd, dtype.type(np.inf))
    else:
        info = np.iinfo(dtype)
        if nodata != round(nodata) or not info.min <= nodata <= info.max:
            return 0, nodata                                      # no pixel can hold it
        nd = dtype.type(nodata)
        value = nd + 1 if nd < info.max else nd - 1
    (bx, by), W, H = band1.GetBlockSize(), ds.RasterXSize, ds.RasterYSize
    lifted = 0
    for y in range(0, H, by):
        for x in range(0, W, bx):
            w, h = min(bx, W - x), min(by, H - y)
            valid = None
            for i in range(1, ds.RasterCount + 1):
                band = ds.GetRasterBand(i)
                a = band.ReadAsArray(x, y, w, h)
                hit = a == nd
                if not hit.any():
                    continue
                if valid is None:
                    valid = band1.GetMaskBand().ReadAsArray(x, y, w, h) > 0
                hit &= valid
                if hit.any():
                    a[hit] = value
                    band.WriteArray(a, x, y)
                    lifted += int(hit.sum())
    return lifted, float(value)


def utm_epsg(lon_deg: float, lat_deg: float) -> int:
    """EPSG code of the WGS84 UTM zone holding (lon, lat): 326zz north, 327zz south."""
    zone = int(np.floor((((lon_deg + 180.0) % 360.0)) / 6.0)) + 1
    return (32600 if lat_deg >= 0 else 32700) + min(max(zone, 1), 60)


def footprint_lonlat(rpc, image_size: Tuple[int, int], h_range_m: Tuple[float, float],
                     margin: float = 0.05) -> Tuple[float, float, float, float]:
    """(west, south, east, north) degrees of the image seen at every height of ``h_range_m`` (image border
    localised with the RPC at both heights), widened by ``margin`` of its size on each side."""
    W, H = image_size
    t = np.linspace(0.0, 1.0, 17)
    s = np.concatenate([t * W, np.full_like(t, W), t[::-1] * W, np.zeros_like(t)])
    l = np.concatenate([np.zeros_like(t), t * H, np.full_like(t, H), t[::-1] * H])
    lons, lats = [], []
    for h in h_range_m:
        lon, lat = rpc.localize(s, l, np.full(s.size, float(h)))
        lons.append(np.asarray(lon, float))
        lats.append(np.asarray(lat, float))
    lon, lat = np.concatenate(lons), np.concatenate(lats)
    ok = np.isfinite(lon) & np.isfinite(lat)
    if not np.any(ok):
        raise Gf4calError(f"the RPC cannot localise the image's border ({W} x {H} px) at heights {h_range_m[0]:.0f} "
                          f"to {h_range_m[-1]:.0f} m: it does not describe this image's pixels (another image, or a "
                          "crop whose origin is not stated)")
    lon, lat = lon[ok], lat[ok]
    w, e, so, n = lon.min(), lon.max(), lat.min(), lat.max()
    dx, dy = (e - w) * margin + 1e-4, (n - so) * margin + 1e-4
    return (float(w - dx), float(so - dy), float(e + dx), float(n + dy))


def scene_footprint(rpc, image_size, dem=None):
    """The scene footprint polygon (lon/lat) of the residual GeoPackages: the image border localised on ``dem``
    (its lines of sight intersected with the DEM, as the ortho is warped: within a pixel of the ortho's valid
    area), border points beyond the DEM at the RPC's HEIGHT_OFF; without a DEM at HEIGHT_OFF. None when the border
    does not localise."""
    from ..report import footprint_from_rpc
    h0 = float(rpc.height_off)
    try:
        return footprint_from_rpc(rpc, image_size, h=h0 if dem is None else dem.with_nodata(h0))
    except Gf4calError:
        return None


def write_ellipsoidal_dem(dem_path: str, grid: str, bounds_lonlat, out_path: str) -> str:
    """Write the part of ``dem_path`` covering ``bounds_lonlat`` as ellipsoidal heights (METHODS §2).

    Same grid as the source (a pixel window of it), ``h = H + N(lon, lat)`` at each pixel centre with ``N`` from
    the geoid ``grid`` (PROJ ``vgridshift``), float32, no-data -9999, the source's horizontal CRS only.
    """
    from osgeo import gdal
    import pyproj
    from ..dem import geoid_transformer
    from .._gdal import open_raster
    src = open_raster(dem_path, what="DEM", error=DEMError)
    gt = src.GetGeoTransform()
    srs = src.GetSpatialRef()
    if srs is None:
        raise DEMError(f"DEM {dem_path} has no CRS; assign one (gdal_edit.py -a_srs EPSG:4326)")
    srs = srs.Clone()
    if srs.IsCompound():
        srs.StripVertical()
    crs = pyproj.CRS.from_wkt(srs.ExportToWkt())
    w, s, e, n = bounds_lonlat
    lon = np.concatenate([np.linspace(w, e, 33), np.full(33, e), np.linspace(e, w, 33), np.full(33, w)])
    lat = np.concatenate([np.full(33, s), np.linspace(s, n, 33), np.full(33, n), np.linspace(n, s, 33)])
    to_dem = crs_transformer("EPSG:4326", crs)
    x, y = to_dem.transform(lon, lat)
    px = (np.asarray(x) - gt[0]) / gt[1]
    py = (np.asarray(y) - gt[3]) / gt[5]
    x0 = int(max(np.floor(np.nanmin(px)) - 2, 0))
    y0 = int(max(np.floor(np.nanmin(py)) - 2, 0))
    x1 = int(min(np.ceil(np.nanmax(px)) + 2, src.RasterXSize))
    y1 = int(min(np.ceil(np.nanmax(py)) + 2, src.RasterYSize))
    if x1 <= x0 or y1 <= y0:
        raise DEMError(f"DEM {dem_path} does not cover the image; use a DEM that covers the scene")
    band = src.GetRasterBand(1)
    H = band.ReadAsArray(x0, y0, x1 - x0, y1 - y0).astype(float)
    nd = band.GetNoDataValue()
    if nd is not None:
        H[H == nd] = np.nan
    cols = gt[0] + gt[1] * (x0 + np.arange(x1 - x0) + 0.5)
    rows = gt[3] + gt[5] * (y0 + np.arange(y1 - y0) + 0.5)
    X, Y = np.meshgrid(cols, rows)
    geoid = geoid_transformer(grid)

    def ellipsoidal(x, y, z):
        """h = H + N at DEM pixel centres (x, y), -9999 where H is no-data (one block of pixels)."""
        plon, plat = to_dem.transform(x, y, direction="INVERSE")
        ok = np.isfinite(z)
        out = np.full(z.size, -9999.0)
        if np.any(ok):
            out[ok] = geoid.transform(np.asarray(plon)[ok], np.asarray(plat)[ok], z[ok])[2]
        return (out,)

    (h,) = split_points(ellipsoidal, X.ravel(), Y.ravel(), H.ravel())      # blocks over the thread pool
    ok = np.isfinite(H.ravel())
    if not np.all(np.isfinite(h[ok])):
        raise DEMError(f"the geoid grid {grid} does not cover the DEM around the image; use a global grid")
    ds = gdal.GetDriverByName("GTiff").Create(out_path, x1 - x0, y1 - y0, 1, gdal.GDT_Float32,
                                              gtiff_options())
    ds.SetGeoTransform((gt[0] + x0 * gt[1], gt[1], 0.0, gt[3] + y0 * gt[5], 0.0, gt[5]))
    ds.SetProjection(srs.ExportToWkt())
    ob = ds.GetRasterBand(1)
    ob.SetNoDataValue(-9999.0)
    ob.WriteArray(h.reshape(H.shape).astype(np.float32))
    ds = None
    return out_path


#: An output CRS is refused when the scene's centre lies farther than this (degrees) outside the CRS's area of use
#: (generous: a neighbouring UTM zone is fine; a zone on the other side of the Earth or a polar CRS is not).
AREA_OF_USE_MARGIN_DEG = 10.0


def _target_srs(crs, bounds_lonlat) -> str:
    """The output CRS as GDAL takes it; refused (one line, the cause) when unknown, geocentric, not horizontal, or
    made for another part of the Earth than the scene (its area of use)."""
    from osgeo import osr
    from .._gdal import gdal_exceptions, quiet
    if crs is None or str(crs).strip().lower() == "utm":
        w, s, e, n = bounds_lonlat
        return f"EPSG:{utm_epsg((w + e) / 2.0, (s + n) / 2.0)}"
    srs = osr.SpatialReference()
    try:
        with gdal_exceptions(), quiet():
            srs.SetFromUserInput(str(crs))
    except RuntimeError:
        raise Gf4calError(f"unknown output CRS {crs!r}; give EPSG:XXXX, a WKT/PROJ string or 'utm'") from None
    if srs.IsGeocentric():
        raise Gf4calError(f"the output CRS {crs} is geocentric (X, Y, Z from the Earth's centre): it cannot hold an "
                          "ortho; give a projected or geographic CRS (e.g. utm or EPSG:4326)")
    if not (srs.IsProjected() or srs.IsGeographic()):
        raise Gf4calError(f"the output CRS {crs} is not a horizontal (projected or geographic) CRS: it cannot hold "
                          "an ortho; give e.g. utm or EPSG:4326")
    _check_area_of_use(crs, srs, bounds_lonlat)
    return str(crs)


def _check_area_of_use(crs, srs, bounds_lonlat) -> None:
    area = srs.GetAreaOfUse()
    if area is None:
        return
    w, s, e, n = bounds_lonlat
    lon, lat = (w + e) / 2.0, (s + n) / 2.0
    west, east = area.west_lon_degree, area.east_lon_degree
    span = (east - west) % 360.0 or 360.0
    dlon = 0.0 if (lon - west) % 360.0 <= span else min((west - lon) % 360.0, (lon - east) % 360.0)
    dlat = max(area.south_lat_degree - lat, lat - area.north_lat_degree, 0.0)
    if max(dlon, dlat) > AREA_OF_USE_MARGIN_DEG:
        raise Gf4calError(
            f"the output CRS {crs} ({area.name.rstrip('.')}: lon {west:g} to {east:g}, lat {area.south_lat_degree:g} to "
            f"{area.north_lat_degree:g}) is made for another part of the Earth than the scene (lon {lon:.2f}, lat "
            f"{lat:.2f}); give a CRS for the scene's area (e.g. utm)")


def _extent_in(dst_srs: str, bounds_lonlat) -> Tuple[float, float]:
    """(width, height) of the footprint's bounding box in the output CRS's units; refused when it cannot be
    expressed there."""
    import pyproj
    w, s, e, n = bounds_lonlat
    t = np.linspace(0.0, 1.0, 21)
    lon = np.concatenate([w + (e - w) * t, np.full_like(t, e), e - (e - w) * t, np.full_like(t, w)])
    lat = np.concatenate([np.full_like(t, s), s + (n - s) * t, np.full_like(t, n), n - (n - s) * t])
    try:
        x, y = crs_transformer("EPSG:4326", dst_srs).transform(lon, lat, errcheck=False)
    except pyproj.exceptions.ProjError as exc:
        raise Gf4calError(f"the scene cannot be expressed in the output CRS {dst_srs} ({exc}); give a CRS for the "
                          "scene's area (e.g. utm)") from None
    x, y = np.asarray(x, float), np.asarray(y, float)
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise Gf4calError(f"the scene cannot be expressed in the output CRS {dst_srs} (its projection is not defined "
                          "over the whole footprint); give a CRS for the scene's area (e.g. utm)")
    return float(np.ptp(x)), float(np.ptp(y))


def check_ortho_size(image: str, image_size, dst_srs: str, bounds_lonlat, res_m: Optional[float], out_path: str,
                     force: bool = False) -> None:
    """Refuse, before writing, an ortho the output resolution makes 1 px wide or larger than the pixel limit or
    the free space (:func:`~gdal_gf4cal.outputs.check_raster_size`, ``--force`` passes); the footprint in the output
    CRS is checked in any case."""
    from osgeo import gdal
    from ..outputs import check_raster_size
    from .._gdal import open_raster
    dx, dy = _extent_in(dst_srs, bounds_lonlat)
    if res_m is None:
        return
    res = float(res_m)
    if res >= min(dx, dy):
        gsd = min(dx, dy) / max(min(image_size), 1)
        raise Gf4calError(f"--res {res:g} is coarser than the scene's footprint ({dx:.4g} x {dy:.4g} in {dst_srs}'s "
                          f"units): the ortho would be a pixel or two; give a resolution near the image's ground "
                          f"sampling (about {gsd:.3g})")
    ds = open_raster(image, what="image")
    bytes_per_sample = gdal.GetDataTypeSize(ds.GetRasterBand(1).DataType) // 8
    check_raster_size(np.ceil(dx / res), np.ceil(dy / res), bands=ds.RasterCount, bytes_per_sample=bytes_per_sample,
                      out_path=out_path, what=f"at --res {res:g} in {dst_srs}", force=force)


def _check_dem_covers(dem_obj, dem: str, bounds_lonlat) -> None:
    """Refuse a DEM without a single height over the scene (one line naming the DEM and the scene)."""
    w, s, e, n = bounds_lonlat
    lon, lat = np.meshgrid(np.linspace(w, e, 9), np.linspace(s, n, 9))
    h = np.asarray(dem_obj.sample(lon.ravel(), lat.ravel(), nodata="nan"), float)
    if not np.any(np.isfinite(h)):
        raise DEMError(f"the DEM {os.path.basename(dem)} has no height over the scene (lon {w:.4f} to {e:.4f}, lat "
                       f"{s:.4f} to {n:.4f}); give a DEM that covers it")


def _warp_failure(exc: BaseException, out_path: str) -> Gf4calError:
    """One line naming what stopped GDAL's warper: a full disk (by GDAL's words or the folder's free space), else
    GDAL's own first line."""
    import shutil
    from .._gdal import first_line
    text = first_line(exc)
    folder = os.path.dirname(os.path.abspath(out_path))
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        free = None
    low = text.lower()
    if any(w in low for w in ("no space left", "disk full", "disk is full", "file too large")) or (
            free is not None and free < FULL_DISK_BYTES):
        return Gf4calError(f"the disk is full: writing the ortho in {folder} failed ({text}); free space or choose "
                           "another output folder; nothing was kept")
    return Gf4calError(f"orthorectification failed: {text}")


#: A write that failed with less than this free in the output folder is reported as a full disk.
FULL_DISK_BYTES = 64 * 1024 * 1024


@blas_serial()     # BLAS on the calling thread, as in the CLI and QGIS (threads.py)
def orthorectify(image, *, dem, out, rpc=None, geoid="auto", crs="utm", res_m: Optional[float] = None,
                 resampling: str = "bilinear", overwrite: bool = False, force: bool = False,
                 progress=None) -> Dict[str, Any]:
    """Orthorectify ``image`` with its RPC (or ``rpc``) over ``dem`` into a GeoTIFF (METHODS §2, §4.2).

    Parameters
    ----------
    image : a raster GDAL opens (its own RPC is used unless ``rpc`` is given)
    dem : DEM path (any CRS); ``geoid`` says what its heights are above: ``"auto"`` (default: what its CRS
        declares), ``"none"`` (use as they are), ``"egm96"``, ``"egm2008"`` or a grid path
    out : output GeoTIFF (tiled, deflate-compressed, a no-data value and an internal mask of the valid area,
        internal overviews); never an input; an existing file only with ``overwrite``
    rpc : optional RPC source (refined ``.vrt``, ``.RPB``, ``_RPC.TXT``, ...) replacing the image's own
    crs : output CRS (``"utm"``: the UTM zone of the scene centre; else ``EPSG:XXXX`` or any GDAL CRS string)
    res_m : output pixel size in CRS units (metres for UTM); default GDAL's choice (about the image's GSD)
    resampling : one of :data:`RESAMPLING`
    force : write an ortho larger than :data:`~gdal_gf4cal.outputs.MAX_RASTER_PIXELS` (or than the free space,
        uncompressed); without it such a ``res_m`` is refused before anything is written

    Returns
    -------
    dict
        ``input``, ``rpc``, ``dem``, ``geoid`` (``{"name", "grid"}``, absent when heights are used as they are),
        ``crs``, ``res_m``, ``size_px``, ``nodata``, ``overviews`` (number of levels), ``resampling``, ``outputs``,
        ``warnings``, ``notes`` (e.g. the crop origin applied, :func:`gdal_gf4cal.crop.image_rpc`).
        Raises :class:`~gdal_gf4cal.geoid.GeoidGridMissing` (nothing written) when a geoid cannot be applied; a
        :class:`Gf4calError` (nothing written) for an output CRS that cannot hold the scene, a resolution coarser than
        the footprint or beyond the size limit, a full disk, or an ortho without a valid pixel.
    """
    from .. import progress as _progress
    from ..crop import image_rpc
    from ..geoid import resolve_geoid

    image, out, dem = os.fspath(image), os.fspath(out), os.fspath(dem)
    check_ortho_options(resampling, res_m)
    image_size, inputs = _open_image(image)
    if image_size is None:
        raise Gf4calError(f"{image} is not an image GDAL can read; orthorectify needs the image's pixels")
    inputs.append(dem)
    if rpc is not None:
        rpc = os.fspath(rpc)
        inputs.append(rpc)
    grid = resolve_geoid(geoid, dem)            # refuses a declared geoid without grid before any work
    outs = OutputSet(inputs, overwrite=overwrite, cancelled=cancel_check(progress))
    outs.declare("ortho", out, check=check_raster())
    warns: list = []
    rep: Dict[str, Any] = {"input": image, "rpc": rpc or image, "dem": dem}
    with outs, collect_warnings(warns):
        _progress.report(progress, 0.0, "reading the RPC and the DEM")
        model, note = image_rpc(image, rpc)
        if note:
            rep.setdefault("notes", []).append(note)
        own = rpc is None and note is None                  # the image's own RPC: GDAL reads it itself
        rep.update(warp_ortho(image, image_size, None if own else model, dem, grid, outs.tmp("ortho"),
                              crs=crs, res_m=res_m, resampling=resampling, force=force, progress=progress))
        rep["outputs"] = outs.paths
    finish_report(rep, warns)
    _progress.report(progress, 1.0, "done")
    return rep


def check_ortho_options(resampling: str = "bilinear", res_m: Optional[float] = None) -> None:
    """Refuse an unknown resampling or a non-positive resolution (before any work)."""
    if resampling not in RESAMPLING:
        raise Gf4calError(f"unknown resampling {resampling!r}; use one of {', '.join(RESAMPLING)}")
    if res_m is not None and not (float(res_m) > 0):
        raise Gf4calError(f"the output resolution must be a positive number of metres, not {res_m!r}")


def kernel_scales(dst_size: Tuple[int, int], src_size: Tuple[int, int]) -> Tuple[float, float]:
    """GDAL's resampling-kernel scales (``XSCALE``, ``YSCALE``: destination pixels per source pixel) of a warp whose
    one chunk is the whole output of ``dst_size`` (w, h) over the whole source of ``src_size``: the ratio of the sizes,
    below 1 (downsampling: the kernel widens) snapped to 1 / n when within 0.05 of it, as GDAL's warp kernel does."""
    scales = []
    for d, s in zip(dst_size, src_size):
        r = d / s
        if r < 1.0 and abs(1.0 / r - int(1.0 / r + 0.5)) < 0.05:
            r = 1.0 / int(1.0 / r + 0.5)
        scales.append(float(r))
    return scales[0], scales[1]


def whole_ortho_kernel(warped, vrt_path: str, src_path: str):
    """The warped VRT ``warped`` (written at ``vrt_path``, warping ``src_path``) reopened with the resampling kernel's
    scales of the whole ortho (:func:`kernel_scales`) in its warp options.

    Without them GDAL estimates the scales for each block it warps from that block's source window: a 512 x 128
    block of a slanted scene needs more source lines than it has rows, the bilinear or cubic kernel widened along y
    and the ortho came out softer than ``gdalwarp -rpc``'s (57 % of the pixels of a real Pleiades crop, up to 50 DN
    off), differently in blocks of another shape. With them every block uses the scales gdalwarp uses when the ortho
    is one chunk: the same pixels as gdalwarp, whatever the blocks and threads. The source is the raster GDAL warps
    from: for an ortho coarser than the image, the image's overview gdalwarp chose (``-ovr AUTO``, the VRT's
    ``OVERVIEW_LEVEL`` open option), opened with the VRT's own open options."""
    import xml.etree.ElementTree as ET
    from osgeo import gdal
    if warped is None:
        raise Gf4calError("gdal.Warp failed without a message")
    dst_size = (warped.RasterXSize, warped.RasterYSize)
    warped = None                                            # written to vrt_path
    tree = ET.parse(vrt_path)
    options = tree.getroot().find("GDALWarpOptions")
    source = gdal.OpenEx(src_path, gdal.OF_RASTER, open_options=[f"{o.get('key')}={o.text}" for o in
                                                                 options.iterfind("OpenOptions/OOI")])
    src_size = (source.RasterXSize, source.RasterYSize)
    source = None
    for name, scale in zip(("XSCALE", "YSCALE"), kernel_scales(dst_size, src_size)):
        ET.SubElement(options, "Option", name=name).text = repr(scale)
    tree.write(vrt_path)
    return gdal.Open(vrt_path)


def warp_ortho(image: str, image_size, model, dem: str, grid: Optional[str], out_path: str, *, crs="utm",
               res_m: Optional[float] = None, resampling: str = "bilinear", force: bool = False,
               progress=None) -> Dict[str, Any]:
    """Warp ``image`` (with ``model`` as its RPC, or its own when None) over ``dem`` into ``out_path`` (a temporary
    of an :class:`OutputSet`); ``grid``: the geoid grid making the DEM ellipsoidal (None: heights used as they are).

    Returns the ortho part of the report: ``geoid`` (when applied), ``crs``, ``res_m``, ``size_px``, ``nodata``,
    ``overviews``, ``resampling`` (the file: :func:`_write_ortho`).
    The output CRS and size are checked before anything is written (:func:`check_ortho_size`); a result without a
    valid pixel is refused.
    """
    from osgeo import gdal
    from .. import progress as _progress
    from ..dem import DEM
    from ..rpc import RPCModel
    from ..outputs import process_tempdir
    from .._gdal import gdal_exceptions, open_raster
    rep: Dict[str, Any] = {}
    with process_tempdir("gf4cal_ortho_") as tmpdir:
        rpc_model = model if model is not None else RPCModel.from_file(image)
        dem_obj = DEM.from_file(dem, geoid=grid if grid else False)
        lo, hi = dem_obj.height_range()
        pad = 120.0 if grid else 0.0           # geoid undulations are within +-110 m
        bounds = footprint_lonlat(rpc_model, image_size, (lo - pad, hi + pad))
        dst_srs = _target_srs(crs, bounds)
        mid = footprint_lonlat(rpc_model, image_size, ((lo + hi) / 2.0,), margin=0.0)
        _check_dem_covers(dem_obj, dem, mid)
        check_ortho_size(image, image_size, dst_srs, mid, res_m, out_path, force=force)
        if grid:
            _progress.report(progress, 0.05, "writing the ellipsoidal DEM")
            dem_used = write_ellipsoidal_dem(dem, grid, bounds, os.path.join(tmpdir, "dem_ellipsoidal.tif"))
            rep["geoid"] = {"name": os.path.basename(grid), "grid": grid}
        else:
            dem_used = dem
        rep["crs"] = dst_srs
        src_path = image
        if model is not None:                   # the image's pixels with the given RPC
            src_path = os.path.join(tmpdir, "source.vrt")
            with gdal_exceptions():
                gdal.Translate(src_path, open_raster(image, what="image"), format="VRT")
                vrt = gdal.Open(src_path, gdal.GA_Update)
                vrt.SetMetadata(model.to_gdal_metadata(), "RPC")
                vrt = None
        cancelled = []

        def _cb(fraction, _msg, _data):
            try:
                _progress.report(progress, 0.1 + 0.85 * fraction, "warping" if fraction < 0.9 else "overviews")
            except CancelledError as exc:
                cancelled.append(exc)
                return 0
            return 1

        n_threads = num_threads()               # GF4CAL_NUM_THREADS (QGIS's setting in QGIS, 1 in a Dask worker)
        opts = dict(format="VRT", dstSRS=dst_srs, rpc=True, resampleAlg=resampling, multithread=n_threads > 1,
                    dstAlpha=True, transformerOptions=[f"RPC_DEM={dem_used}", "RPC_DEMINTERPOLATION=bilinear",
                                                       "RPC_DEM_APPLY_VDATUM_SHIFT=FALSE"],
                    warpOptions=[f"NUM_THREADS={n_threads}"])
        if res_m is not None:
            opts.update(xRes=float(res_m), yRes=float(res_m), targetAlignedPixels=True)
        try:
            with gdal_exceptions():
                vrt_path = os.path.join(tmpdir, "warped.vrt")
                warped = whole_ortho_kernel(gdal.Warp(vrt_path, src_path, **opts), vrt_path, src_path)
                rep.update(_write_ortho(warped, out_path, resampling, _cb))
        except RuntimeError as exc:
            if cancelled:
                raise cancelled[0] from None
            raise _warp_failure(exc, out_path) from None
        if cancelled:
            raise cancelled[0]
        if rep.pop("empty"):
            raise Gf4calError(f"the ortho came out without a single valid pixel: the image's RPC does not see the "
                              f"DEM {os.path.basename(dem)} (the DEM does not cover the scene, or the RPC is not the "
                              "image's); nothing was kept")
    rep["resampling"] = resampling
    return rep
