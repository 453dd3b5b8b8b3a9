"""Appliers of the pan-MS model (METHODS §9): ``correction.tif`` on the MS grid, the MS resampled onto the pan's
raw grid (``ms_on_pan.tif``), the MS RPC refitted to the model, and the measured misregistration of an image
against the pan's edges."""
from __future__ import annotations

import functools
import math
import os
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from osgeo import gdal, gdal_array
from scipy import ndimage

from .. import threads
from .._gdal import gdal_exceptions, with_gdal_exceptions
from ..matching.correlate import block_reduce, phase_correlate
from ..outputs import gtiff_options
from ..progress import report
from ..rpc_fit import refit_numerators
from .model import PanMSError, PanMSModel

#: zlib level of correction.tif and ms_on_pan.tif (DEFLATE, readable everywhere): level 1 compresses in a third of
#: the default's (6) CPU for ~7 % larger files (the same pixels), on a 1024 x 1024 MS crop: correction.tif 0.18 ->
#: 0.06 s, 3.05 -> 3.27 MB; ms_on_pan.tif 0.07 -> 0.04 s, 2.91 -> 3.01 MB (the PNGs' choice, report/plot.py).
ZLEVEL = 1

#: Tile size (px) of correction.tif and ms_on_pan.tif: their blocks, and the unit of their rounds over the pool.
TILE_PX = 512


def _tiles(W: int, H: int, tile: int) -> List[Tuple[int, int, int, int]]:
    """``(x0, y0, w, h)`` of the ``tile`` x ``tile`` blocks of a ``W`` x ``H`` grid, row by row."""
    return [(x0, y0, min(tile, W - x0), min(tile, H - y0)) for y0 in range(0, H, tile) for x0 in range(0, W, tile)]


def write_correction(model: PanMSModel, path, *, tile: int = TILE_PX, progress=None, rpc=None,
                     band_models: Optional[Dict[str, PanMSModel]] = None) -> str:
    """Write ``correction.tif``: float32 bands delta sample / delta line (MS px) at every MS pixel centre (GDAL
    convention), on the MS image grid as given, tile by tile (METHODS §9): the model's, then a pair per entry of
    ``band_models`` (``{label: model}``: bands with their own correction). ``rpc``: the MS image's RPC, written in
    the RPC metadata domain (no geotransform) so that GDAL and QGIS place the grid on the ground."""
    W, H = model.ms_size
    path = os.fspath(path)
    pairs = [("", model)] + [(f" {k}", m) for k, m in (band_models or {}).items()]
    with gdal_exceptions():
        ds = gdal.GetDriverByName("GTiff").Create(path, W, H, 2 * len(pairs), gdal.GDT_Float32, gtiff_options(
            tile=tile, zlevel=ZLEVEL, predictor=3, threads=threads.num_threads(), extra=["INTERLEAVE=BAND"]))
        for i, (label, _) in enumerate(pairs):
            ds.GetRasterBand(2 * i + 1).SetDescription(f"delta_sample_ms_px{label}")
            ds.GetRasterBand(2 * i + 2).SetDescription(f"delta_line_ms_px{label}")
        ds.SetMetadataItem("GF4CAL_PANMS", "delta = MS image point - pan/DEM/MS-RPC prediction (METHODS §9), MS "
                           "pixels, at MS pixel centres, GDAL convention")
        if rpc is not None:
            ds.SetMetadata(rpc.to_gdal_metadata(), "RPC")
        tiles = _tiles(W, H, tile)
        done = 0
        models = [m for _, m in pairs]
        for batch in threads.rounds(tiles):       # a round of tiles over the pool, written here in order
            for (x0, y0, _, _), arrays in zip(batch, threads.run_tasks(
                    [functools.partial(_correction_tile, models, t) for t in batch])):
                for b, a in enumerate(arrays, start=1):
                    ds.GetRasterBand(b).WriteArray(a, x0, y0)
                ds.FlushCache()   # the tile to disk, out of GDAL's block cache (up to 5 % of the RAM otherwise)
                done += 1
                report(progress, done / len(tiles), f"correction.tif tile {done}/{len(tiles)}")
        ds.FlushCache()
        ds = None
    return path


def _correction_tile(models, tile) -> List[np.ndarray]:
    """correction.tif's bands on one tile ``(x0, y0, w, h)``: delta sample and delta line (float32) of every model."""
    x0, y0, w, h = tile
    s, l = np.meshgrid(x0 + np.arange(w) + 0.5, y0 + np.arange(h) + 0.5)
    arrays = []
    for m in models:
        arrays.extend(v.astype(np.float32) for v in m.predict(s, l))
    return arrays


def _tile_points(pan_rpc, ms_rpc, dem, ratio, tile, step, models) -> Dict[int, Tuple[np.ndarray, np.ndarray]]:
    """The MS points ``p'`` every model of ``models`` gives for the ms_on_pan tile ``(x0, y0, w, h)``:
    ``{id(model): (sample, line)}`` (:func:`_predicted_grid`, then :func:`_apply_model` once per model)."""
    s2, l2 = _predicted_grid(pan_rpc, ms_rpc, dem, ratio, *tile, step)
    where: dict = {}
    for m in models:
        if id(m) not in where:
            where[id(m)] = _apply_model(m, s2, l2)
    return where


def _predicted_grid(pan_rpc, ms_rpc, dem, ratio, x0, y0, w, h, step):
    """MS points ``p''`` predicted for the ms_on_pan pixels ``[x0, x0+w) x [y0, y0+h)``: pan pixel centre ->
    pan RPC on the DEM -> MS RPC, on a coarse node grid (every ``step`` px) interpolated bilinearly (the mapping
    is smooth; the pan-MS ray angle makes the DEM's fine structure negligible, METHODS §9)."""
    xs = np.unique(np.r_[np.arange(x0, x0 + w, step), x0 + w]).astype(float)
    ys = np.unique(np.r_[np.arange(y0, y0 + h, step), y0 + h]).astype(float)
    X, Y = np.meshgrid(xs, ys)
    lon, lat, hh = pan_rpc.localize_dem(X * ratio, Y * ratio, dem)
    s2, l2 = ms_rpc.project(lon, lat, hh)
    # fractional node index of every pixel centre (nodes are regular but for the last one)
    fx = np.interp(x0 + np.arange(w) + 0.5, xs, np.arange(xs.size))
    fy = np.interp(y0 + np.arange(h) + 0.5, ys, np.arange(ys.size))
    FY, FX = np.meshgrid(fy, fx, indexing="ij")
    return tuple(ndimage.map_coordinates(np.asarray(v, float), [FY, FX], order=1, mode="nearest")
                 for v in (s2, l2))


def resample_ms_on_pan(model, pan_path, ms_path, path, *, pan_rpc, ms_rpc, dem, ratio: int,
                       tile: int = TILE_PX, node_step: int = 8, progress=None, band_names=None) -> str:
    """Write ``ms_on_pan.tif``: every MS band resampled onto the pan's raw grid at MS resolution (pan size /
    ``ratio``, same extent as the pan) so that ``gdal_pansharpen.py PAN ms_on_pan.tif fused.tif`` fuses without
    halos (METHODS §9). Output pixel ``(x, y)`` covers pan pixels ``[x r, (x+1) r)``: its centre, localised with
    the pan RPC on the DEM and projected with the MS RPC, is ``p''``; the MS shows that ground at ``p' = p'' +
    delta(p')`` (fixed point, 2 iterations: the field's gradient is ~1e-4 px/px), sampled bicubically. ``model``:
    one :class:`PanMSModel` for every band, a list of one per band, or None (through the RPCs only: the
    uncorrected product). The grid covers the pan's extent (``ceil(size / ratio)``). ``band_names``: per band
    ``(description, GDAL colour interpretation)`` (default: the MS file's, Alpha never). Tile by tile, each tile
    reads only its MS window."""
    path = os.fspath(path)
    with gdal_exceptions():
        pan = gdal.Open(os.fspath(pan_path))
        ms = gdal.Open(os.fspath(ms_path))
        PW, PH = pan.RasterXSize, pan.RasterYSize
        MW, MH, nb = ms.RasterXSize, ms.RasterYSize, ms.RasterCount
        W, H = -(-PW // ratio), -(-PH // ratio)
        models = list(model) if isinstance(model, (list, tuple)) else [model] * nb
        dt = ms.GetRasterBand(1).DataType
        out = gdal.GetDriverByName("GTiff").Create(path, W, H, nb, dt, gtiff_options(
            tile=tile, zlevel=ZLEVEL, threads=threads.num_threads(), extra=["INTERLEAVE=BAND"]))
        nodata = ms.GetRasterBand(1).GetNoDataValue()
        fill = 0.0 if nodata is None else nodata
        for b in range(nb):
            ob = out.GetRasterBand(b + 1)
            ob.SetNoDataValue(fill)
            if band_names is not None:
                desc, ci = band_names[b]
            else:
                desc, ci = ms.GetRasterBand(b + 1).GetDescription(), ms.GetRasterBand(b + 1).GetColorInterpretation()
                ci = gdal.GCI_Undefined if ci == gdal.GCI_AlphaBand else ci
            ob.SetDescription(desc)
            ob.SetColorInterpretation(ci)
        out.SetMetadataItem("GF4CAL_PANMS", f"MS resampled onto the pan raw grid at 1/{ratio} of its size "
                            f"({'pan-MS registration model applied' if models[0] else 'RPCs only'}; METHODS §9)")
        _set_ms_on_pan_rpc(out, pan, ratio, pan_rpc)
        tiles = _tiles(W, H, tile)
        ms_here = threads.PerThread(lambda: gdal.Open(os.fspath(ms_path)))   # a handle per pool thread
        done = 0
        for batch in threads.rounds(tiles):
            # a round of tiles over the pool: their MS points, then every band of every tile (each reads its own MS
            # window; GDAL and SciPy release the GIL); written here in order
            points = threads.run_tasks([functools.partial(_tile_points, pan_rpc, ms_rpc, dem, ratio, t, node_step,
                                                          models) for t in batch])
            bands = threads.run_tasks([functools.partial(_band_tile, ms_here, b, where[id(models[b])], (MW, MH),
                                                         fill, nodata, dt) for where in points for b in range(nb)])
            for i, (x0, y0, _, _) in enumerate(batch):
                for b in range(nb):
                    out.GetRasterBand(b + 1).WriteArray(bands[i * nb + b], x0, y0)
                # the written tile to disk, out of GDAL's block cache (the full GF7 ms_on_pan.tif is 236 MB of
                # blocks); the MS blocks read stay cached (a strip-organised MS is read again by the next tile)
                out.FlushCache()
                done += 1
                report(progress, done / len(tiles), f"ms_on_pan.tif tile {done}/{len(tiles)}")
        out.FlushCache()
        out = None
    return path


@with_gdal_exceptions            # on a pool thread: GDAL's error handler is per thread
def _band_tile(ms_here, b, where, ms_size, fill, nodata, dt) -> np.ndarray:
    """MS band ``b`` (0-based) of one ms_on_pan tile, sampled at ``where = (sp, lp)`` (:func:`_sample_band`), in the
    output's data type (integers rounded and clipped, 0 kept for nodata when that is the MS's nodata)."""
    sp, lp = where
    arr = np.full(sp.shape, fill, dtype=np.float64)
    _sample_band(ms_here.get(), b, sp, lp, ms_size[0], ms_size[1], arr)
    a = arr
    if np.issubdtype(_np_dtype(dt), np.integer):
        info = np.iinfo(_np_dtype(dt))
        a = np.clip(np.round(arr), max(info.min, 1 if nodata == 0 else info.min), info.max)
        a = np.where(np.isfinite(arr) & (arr != fill), a, fill)
    return a.astype(_np_dtype(dt))


def _np_dtype(gdal_type):
    return np.dtype(gdal_array.GDALTypeCodeToNumericTypeCode(gdal_type))


def _apply_model(model, s2, l2):
    """``p' = p'' + delta(p')`` by fixed point (2 iterations); ``p''`` itself when ``model`` is None."""
    sp, lp = s2.copy(), l2.copy()
    if model is not None:
        for _ in range(2):
            ds_, dl_ = model.predict(sp, lp)
            sp, lp = s2 + ds_, l2 + dl_
    return sp, lp


def _sample_band(ms, b, sp, lp, MW, MH, into, margin: int = 3) -> None:
    """Bicubic samples of MS band ``b`` (0-based) at ``(sp, lp)`` (GDAL convention) into ``into`` where inside,
    reading only the window they need."""
    ok = np.isfinite(sp) & np.isfinite(lp)
    inside = ok & (sp >= 0) & (sp <= MW) & (lp >= 0) & (lp <= MH)
    if not inside.any():
        return
    wx0 = int(max(0, math.floor(np.min(sp[inside])) - margin))
    wy0 = int(max(0, math.floor(np.min(lp[inside])) - margin))
    wx1 = int(min(MW, math.ceil(np.max(sp[inside])) + margin))
    wy1 = int(min(MH, math.ceil(np.max(lp[inside])) + margin))
    if wx1 <= wx0 or wy1 <= wy0:
        return
    src = ms.GetRasterBand(b + 1).ReadAsArray(wx0, wy0, wx1 - wx0, wy1 - wy0)
    into[inside] = ndimage.map_coordinates(src.astype(np.float64), [lp[inside] - 0.5 - wy0, sp[inside] - 0.5 - wx0],
                                           order=3, mode="nearest", prefilter=True)


def _set_ms_on_pan_rpc(out, pan, ratio, pan_rpc=None):
    """Give ms_on_pan the pan's RPC (``pan_rpc``: the RPC of the pan's own pixels, e.g. a crop's shifted product
    RPC; else the pan file's) rescaled to its grid (GDAL: x_out = x_pan / r, i.e. RPC convention
    ``(x + 0.5) / r - 0.5``), and the pan's geotransform scaled by ``r`` when the pan has a map georeference
    (a pixel-unit geotransform without CRS -- a crop's origin in its product -- is not one: QGIS would place the
    image at pixel coordinates instead of through the RPC)."""
    md = dict(pan_rpc.to_gdal_metadata()) if hasattr(pan_rpc, "to_gdal_metadata") else pan.GetMetadata("RPC")
    if md:
        md = dict(md)
        for off, scale in (("SAMP_OFF", "SAMP_SCALE"), ("LINE_OFF", "LINE_SCALE")):
            md[off] = repr((float(md[off]) + 0.5) / ratio - 0.5)
            md[scale] = repr(float(md[scale]) / ratio)
        out.SetMetadata(md, "RPC")
    gt = pan.GetGeoTransform(can_return_null=True)
    srs = pan.GetSpatialRef()
    if gt is not None and srs is not None and not srs.IsLocal():
        out.SetGeoTransform((gt[0], gt[1] * ratio, gt[2] * ratio, gt[3], gt[4] * ratio, gt[5] * ratio))
        out.SetProjection(pan.GetProjection())


def approximate_rpc(model: PanMSModel, ms_rpc, *, n: int = 41, n_heights: int = 7,
                    terms: Sequence[str] = ("linear", "piecewise", "jitter")):
    """Refit the MS RPC so that it predicts ``p' = p'' + delta(p')`` (METHODS §9): a smooth approximation of
    the model, which an RPC cannot carry exactly (the sub-CCD jumps). Its numerators are refitted, its
    denominators kept (:func:`~gdal_gf4cal.rpc_fit.refit_numerators`: one linear solve; a free rational refit
    chased the jumps with its denominators, and rounding decided whether it passed). Returns ``(rpc, errors)``
    with the refit's RMS and max error (MS px) against the full model on an ``n x n`` grid x ``n_heights``
    heights. ``terms``: the model terms the RPC is fitted to (the errors are always against the full model)."""
    W, H = model.ms_size
    s, l = np.meshgrid((np.arange(n) + 0.5) * W / n, (np.arange(n) + 0.5) * H / n)
    s, l = s.ravel(), l.ravel()
    h0, h1 = ms_rpc.height_range
    lons, lats, hs, ss, ls = [], [], [], [], []
    ds_, dl_ = model.predict(s, l, terms=terms)
    for h in np.linspace(h0, h1, n_heights):
        lon, lat = ms_rpc.localize(s - ds_, l - dl_, np.full(s.shape, h))
        lons.append(lon), lats.append(lat), hs.append(np.full(s.shape, h)), ss.append(s), ls.append(l)
    lon, lat, hh, S, L = (np.concatenate(v) for v in (lons, lats, hs, ss, ls))
    ok = np.isfinite(lon) & np.isfinite(lat)
    rpc = refit_numerators(ms_rpc, lon[ok], lat[ok], hh[ok], S[ok], L[ok])
    ps, pl = rpc.project(lon[ok], lat[ok], hh[ok])
    es, el = S[ok] - ps, L[ok] - pl
    if tuple(terms) != ("linear", "piecewise", "jitter"):       # errors against the full model
        fs, fl = model.predict(s, l)
        ks, kl = model.predict(s, l, terms=terms)
        es = es + np.tile(fs - ks, n_heights)[ok]
        el = el + np.tile(fl - kl, n_heights)[ok]
    r = np.hypot(es, el)
    errors = {"rms_sample_px": float(np.sqrt(np.mean(es ** 2))), "rms_line_px": float(np.sqrt(np.mean(el ** 2))),
              "rms_px": float(np.sqrt(np.mean(r ** 2))), "max_px": float(np.max(r)), "n_points": int(ok.sum()),
              "note": "an RPC cannot carry the sub-CCD jumps: use correction.tif / ms_on_pan.tif for the exact "
                      "registration (METHODS §9)"}
    return rpc, errors


def edge_misregistration(pan_path, image_path, *, band: int = 1, ratio: int = 4, window: int = 64,
                         region=None, min_ncc: float = 0.5) -> dict:
    """Measured misregistration (MS px) of an image on the pan's grid (``ms_on_pan.tif`` at 1/``ratio``, or a
    fused product at the pan's size) against the pan's edges (METHODS §9's halos): both are reduced to MS
    resolution (block means), cut into ``window`` x ``window`` MS-px windows and phase-correlated; returns the
    mean and RMS per axis and the planar RMS of the window shifts (``image`` minus pan), over windows whose
    correlation ``ncc >= min_ncc`` (textured, cloud-free). ``region = (x0, y0, w, h)`` in MS px limits it."""
    with gdal_exceptions():
        pan = gdal.Open(os.fspath(pan_path))
        img = gdal.Open(os.fspath(image_path))
        W, H = pan.RasterXSize // ratio, pan.RasterYSize // ratio
        x0, y0, w, h = region if region is not None else (0, 0, W, H)
        p = block_reduce(pan.GetRasterBand(1).ReadAsArray(x0 * ratio, y0 * ratio, w * ratio, h * ratio), ratio)
        f = img.RasterXSize // W
        a = img.GetRasterBand(band).ReadAsArray(x0 * f, y0 * f, w * f, h * f)
        m = block_reduce(a, f) if f > 1 else a.astype(np.float64)
    ny, nx = h // window, w // window
    if nx == 0 or ny == 0:
        raise PanMSError(f"the region is smaller than one {window} px window")
    cut = (slice(0, ny * window), slice(0, nx * window))

    def stack(v):
        return v[cut].reshape(ny, window, nx, window).transpose(0, 2, 1, 3).reshape(-1, window, window)
    r = phase_correlate(stack(p), stack(m))
    ok = np.isfinite(r.dx) & np.isfinite(r.dy) & (r.ncc >= min_ncc)
    dx, dy = r.dx[ok], r.dy[ok]
    return {"n_windows": int(ok.sum()), "mean_sample_px": float(np.mean(dx)) if dx.size else None,
            "mean_line_px": float(np.mean(dy)) if dy.size else None,
            "rms_sample_px": float(np.sqrt(np.mean(dx ** 2))) if dx.size else None,
            "rms_line_px": float(np.sqrt(np.mean(dy ** 2))) if dy.size else None,
            "rms_px": float(np.sqrt(np.mean(dx ** 2 + dy ** 2))) if dx.size else None}
