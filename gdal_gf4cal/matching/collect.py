"""Automatic GCP collection: match the raw image against a reference orthophoto + DEM (issue 7).

For each window of a regular grid over the raw image (GDAL pixel convention throughout):

1. Its centre ``c`` is localised on the DEM through the RPC: ground point ``X = (lon, lat, h)``; the RPC predicts
   ``X`` at ``c``.
2. The reference is resampled into the raw geometry around ``c`` (:mod:`.resample`), so it shows the ground the
   RPC *claims* each raw pixel sees.
3. Coarse to fine: the windows are first correlated on an ``f x f`` block-averaged level covering ``f`` times the
   window (read decimated by GDAL, so it never holds full-resolution pixels), which finds offsets up to
   ~``window * f / 4`` px (``search_px``); the raw window is then read at the integer offset found, and a
   full-resolution phase correlation (:mod:`.correlate`) gives the residual shift (windows whose residual
   exceeds half a pixel are re-read there and correlated again, up to three passes; the reference windows'
   spectra are computed once). Re-centring keeps the final correlation near zero shift, where window overlap is
   complete and the sub-pixel estimate unbiased.
4. ``X`` is truly imaged at ``c + d``: that is the GCP ``(lon, lat, h, sample, line)``; ``d`` is the RPC error.
5. Windows on no-data, with featureless texture (water, flat cloud: :func:`.correlate.texture_strength`) in
   either image, with a weak or ambiguous correlation, or with a textured quarter of the reference that the raw
   image does not reproduce (cloud over land) are skipped, never guessed.
6. The accepted offsets are checked against a low-order model with seeded RANSAC + MAD (:mod:`.filters`);
   inconsistent ones are flagged ``outlier=True``.

The work is split into tiles of windows. :func:`match_tile` is a plain top-level function of one picklable
:class:`TileSpec` returning plain arrays, so it runs unchanged in a thread pool (default: its heavy steps release
the GIL), a process pool, or as Dask tasks on a cluster::

    >>> import dask                                            # doctest: +SKIP
    >>> from gdal_gf4cal.matching import plan_tiles, match_tile, assemble_gcps
    >>> specs, ctx = plan_tiles("raw.tif", rpc, "ortho.tif", "dem.tif", spacing_px=256, window_px=64)
    >>> results = dask.compute(*[dask.delayed(match_tile)(s) for s in specs])
    >>> gcps = assemble_gcps(results, ctx)

or simply ``collect_gcps(..., executor=client.get_executor())`` with a ``distributed.Client``. Memory per task is
bounded by the tile (a few ``window x window`` float32 stacks of its windows; GDAL's block cache is flushed
after each tile, or on :func:`run_tiles`' own threads when the next tile reads other rows or the cache passes
:data:`KEEP_BLOCKS_BYTES`), whatever the image size and the search range.
"""
from __future__ import annotations

import concurrent.futures as cf
from dataclasses import dataclass, field
import math
import os
import threading
import warnings
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
from osgeo import gdal

from .. import threads
from .._gdal import with_gdal_exceptions
from ..dem import DEM
from ..errors import Gf4calError
from ..executors import keep_heap, map_ordered
from ..gcp import make_gcps
from ..progress import report
from ..rpc import RPCModel
from .correlate import chunks, correlate_spectra, null_result, phase_correlate, spectra, window_measures
from .filters import reject_outliers
from .resample import (RawReference, ReferenceImage, cut_boxes, read_block, read_boxes, reference_on_grids,
                       whole_pixel_shift)

__all__ = ["TileSpec", "STATUS", "collect_gcps", "plan_tiles", "match_tile", "assemble_gcps", "run_tiles"]

#: Status codes of windows, as returned by :func:`match_tile` and counted in ``gcps.attrs['windows']``.
STATUS = {0: "accepted", 1: "nodata", 2: "featureless", 3: "weak_correlation", 4: "cloud_or_change",
          5: "outside_image"}


@dataclass(frozen=True)
class TileSpec:
    """Everything :func:`match_tile` needs for one tile: plain, picklable data (paths, not open datasets)."""

    image: str
    band: int
    image_nodata: Optional[float]
    rpc: Any                                  # RPCModel (frozen dataclass of floats/arrays: picklable)
    reference: str
    reference_band: int
    dem: Tuple                                # ("constant", h) or ("file", path, geoid, nodata)
    centers: np.ndarray                       # (N, 2) window centres (sample, line), GDAL convention
    window_px: int
    factor: int                               # coarse level's block size (1 = no coarse level)
    params: Dict[str, float] = field(default_factory=dict)
    reference_model: Any = None               # None: ``reference`` is an ortho; else the raw reference's model


# ---------------------------------------------------------------------------------------------- worker side
_CACHE: Dict[Tuple, Any] = {}
_CACHE_LOCK = threading.Lock()


def _cached(key, make, shared: bool = False):
    """Per-process, per-thread cache of opened datasets (GDAL handles are not shared across threads); ``shared``:
    one object for every thread of the process (a :class:`~gdal_gf4cal.DEM`: its own handle per thread)."""
    key = key + ((None,) if shared else (threading.get_ident(),)) + (os.getpid(),)
    with _CACHE_LOCK:
        obj = _CACHE.get(key)
    if obj is None:
        obj = make()
        with _CACHE_LOCK:
            if len(_CACHE) > 32:
                _CACHE.clear()
            _CACHE[key] = obj
    return obj


def _file_key(path: str) -> Tuple:
    """``(path, mtime, size)``: a file rewritten at the same path (a re-run in a long-lived QGIS session, whose
    thread ids are reused) is reopened instead of being read through a stale cached handle."""
    try:
        st = os.stat(path)
    except (OSError, TypeError, ValueError):  # /vsi paths, URLs
        return (path,)
    return (path, st.st_mtime_ns, st.st_size)


def _dem_from_spec(spec: Tuple):
    if spec[0] == "constant":
        return DEM.from_user_input(float(spec[1]))
    # One DEM for every thread (a DEM opens a handle per thread itself): the raster held in memory and its slope
    # bound are read and computed once, not once more on every pool thread (~0.13 s each on the GF7 crop's DEM)
    return _cached(("dem",) + _file_key(spec[1]) + tuple(spec[2:]),
                   lambda: DEM.from_user_input(spec[1], geoid=spec[2], nodata=spec[3]), shared=True)


def _dem_spec(dem) -> Tuple:
    if isinstance(dem, (int, float, np.integer, np.floating)):
        return ("constant", float(dem))
    if isinstance(dem, DEM):
        if dem.is_constant:
            return ("constant", float(dem.constant_height))
        return ("file", dem.path, dem._geoid_name, dem.nodata_policy)
    return ("file", os.fspath(dem), None, "nan")


def _read_boxes(ds, band: int, nodata, x0: np.ndarray, y0: np.ndarray, size: int, decimation: int = 1) -> np.ndarray:
    """Stack of ``size x size`` raw blocks with top-left corners ``(x0, y0)`` (ints), averaged by ``decimation``
    while reading (:func:`.resample.read_boxes`: dense boxes in one read); outside/no-data -> NaN. float32
    ``(N, size/d, size/d)``."""
    return read_boxes(ds.GetRasterBand(band), ds.RasterXSize, ds.RasterYSize, nodata, x0, y0, size, decimation)


#: Smallest quarter (px) in which a change on the ground is told from a cover (see :func:`_quadrant_ok`).
CHANGE_QUARTER_PX = 64


def _quadrant_ok(ref: np.ndarray, raw: np.ndarray, min_ncc: float, which=None, shared=None) -> np.ndarray:
    """Every quarter of the window where the reference has texture must correlate with the raw image, unless the
    raw image keeps its texture there: a failing quarter counts only where it is *covered*.

    Catches a cloud (haze, a shadow) covering part of a window whose remaining texture still produces a
    correlation peak: under it the raw image loses its texture. Quarters flat in the reference (water, flat land)
    are not judged. A quarter of at least :data:`CHANGE_QUARTER_PX` px as textured in the raw image as the
    window's typical quarter (its raw-to-reference gradient ratio at least half of the median of the textured
    quarters'; the best quarter's made a window with one quarter that gained texture, new structure on the ground,
    look covered everywhere else: 7 of 8 such 256-px windows on the Sentinel-2 pair, whose offsets agree with
    AROSICS's) but different is a change on the ground, such as fields between two dates: the window's own
    correlation checks judge it. On a real Sentinel-2 pair ten days apart, the 256-px windows so admitted lie 0.05 px (median) from
    the pair's smooth offset field, the others 0.035 px; 64-px ones 0.17 px against 0.074 (hence the size); painted
    clouds keep their quarters' ratios below 0.25. ``which``: indices of the windows of the stacks to judge (one
    result each; no copy of the stacks). ``shared``: the reference side already computed
    (:class:`_GroupReference`, for windows of the stacks' size).
    """
    which = np.arange(ref.shape[0]) if which is None else np.asarray(which, dtype=np.intp).ravel()
    n, (h, w) = which.size, ref.shape[1:]
    hh, hw = h // 2, w // 2
    ref, raw = ref[:, :2 * hh, :2 * hw], raw[:, :2 * hh, :2 * hw]
    grad = _quarter_gradient(ref, which) if shared is None else shared.grad[which]
    textured = grad >= 0.25 * grad.mean(axis=1, keepdims=True)
    if min(hh, hw) < CHANGE_QUARTER_PX:
        judged = textured          # quarters too small to tell a change from a cover: every textured one judged
    else:
        judged = textured & _covered(_quarter_gradient(raw, which), grad, textured)
    ok = np.ones(n, dtype=bool)
    # The quarters' NCC only for the windows with a quarter to judge (at 256 px, few: most pass on gradients).
    sel = np.flatnonzero(judged.any(axis=1))
    if sel.size:
        # Quarters as views (m, 2, hh, 2, hw): axes 2 and 4 run inside a quarter; results (m, 2, 2) -> (m, 4).
        rows = which[sel]
        a, va = _centred_quarters(ref, rows) if shared is None else (shared.quarters[0][rows],
                                                                     shared.quarters[1][rows])
        b, vb = _centred_quarters(raw, rows)
        with np.errstate(invalid="ignore", divide="ignore"):
            ncc = (np.einsum("nyixj,nyixj->nyx", a, b) / np.sqrt(va * vb)).reshape(sel.size, 4)
        ok[sel] = np.all(~judged[sel] | (np.nan_to_num(ncc, nan=-1.0) >= min_ncc), axis=1)
    return ok


def _covered(raw_grad, grad, textured) -> np.ndarray:
    """The quarters (``n, 4``) of :func:`_quadrant_ok` that may be covered: whose raw-to-reference gradient ratio
    is below half the typical one (the median of the textured quarters')."""
    with np.errstate(invalid="ignore", divide="ignore"):
        kept = raw_grad / grad
        # Against the median of the textured quarters: one quarter that *gained* texture (new structure on the
        # ground) does not make the others look covered, as against the maximum.
        use = textured & np.isfinite(kept)
        srt = np.sort(np.where(use, kept, np.inf), axis=1)  # the quarters judged first
        k = use.sum(axis=1)
        lo, hi = (np.take_along_axis(srt, np.maximum(j, 0)[:, None], axis=1) for j in ((k - 1) // 2, k // 2))
        typical = np.where(k[:, None] > 0, 0.5 * (lo + hi), -np.inf)
        return ~(kept >= 0.5 * typical)


def _centred_quarters(win: np.ndarray, rows):
    """The quarters of the windows ``rows`` of a stack ``(N, 2 hh, 2 hw)`` (or more rows and columns: an odd last
    one left out) minus their means, as views ``(n, 2, hh, 2, hw)`` (axes 2 and 4 run inside a quarter), and their
    sums of squares ``(n, 2, 2)`` (:func:`_quadrant_ok`)."""
    hh, hw = win.shape[1] // 2, win.shape[2] // 2
    q = win[rows, :2 * hh, :2 * hw].reshape(len(rows), 2, hh, 2, hw)
    a = q - q.mean(axis=(2, 4), keepdims=True)
    return a, np.einsum("nyixj,nyixj->nyx", a, a)


def _quarter_gradient(win: np.ndarray, which) -> np.ndarray:
    """Mean absolute difference along each axis (between pixels of one quarter), summed, of every quarter of
    the windows ``which`` of a stack ``(N, 2 hh, 2 hw) -> (n, 4)`` (quarters in row order): differences of whole
    rows and columns summed per half (contiguous reductions), the pairs straddling the middle left out. A few
    windows at a time (:data:`QUARTER_BYTES`: the differences stay in cache, the windows taken there rather than
    in a copy of the stacks: twice as fast on 256-px windows as whole stacks; the same sums)."""
    n, (h2, w2) = which.size, win.shape[1:]
    hh, hw = h2 // 2, w2 // 2
    out = np.empty((n, 4), dtype=np.result_type(win.dtype, np.float32))
    every = n == win.shape[0] and np.array_equal(which, np.arange(n))   # views, no copies
    for sl in chunks(n, QUARTER_BYTES // (4 * h2 * w2)):
        c = win[sl] if every else win[which[sl]]
        m = c.shape[0]
        d = np.subtract(c[..., 1:], c[..., :-1])
        cx = np.abs(d, out=d).reshape(m, 2, hh, w2 - 1).sum(axis=2)     # (m, 2 halves in y, w2 - 1)
        gx = np.stack([cx[..., :hw - 1].sum(axis=-1), cx[..., hw:].sum(axis=-1)], axis=-1) / (hh * (hw - 1))
        d = np.subtract(c[..., 1:, :], c[..., :-1, :])
        ry = np.abs(d, out=d).reshape(m, h2 - 1, 2, hw).sum(axis=-1)    # (m, h2 - 1, 2 halves in x)
        gy = np.stack([ry[:, :hh - 1].sum(axis=1), ry[:, hh:].sum(axis=1)], axis=1) / ((hh - 1) * hw)
        out[sl] = (gx + gy).reshape(m, 4)
    return out


#: Bytes of float32 windows per chunk of :func:`_quarter_gradient` (about: :func:`.correlate.chunks`; as
#: :data:`.correlate._MEASURE_BYTES`).
QUARTER_BYTES = 1 << 20


def _predict_offsets(cp, dxp, dyp, resp, okp, cr, p):
    """Offsets of windows centred on ``cr`` predicted from pilot windows (centres ``cp``, measured offsets
    ``dxp, dyp``, correlation results ``resp``, usable ``okp``): an affine field of the window centres, or their
    median with fewer than 6 good pilots; None when fewer than 4 pilots are trustworthy or they disagree with the
    field by more than half a pixel (then every window simply starts at zero)."""
    r = resp
    good = np.flatnonzero(okp & (r["peak"] >= p["min_peak"]) & (r["peak_ratio"] >= p["min_peak_ratio"])
                          & (r["ncc"] >= p["min_ncc"]) & (np.abs(r["dx"]) <= 0.75) & (np.abs(r["dy"]) <= 0.75))
    if good.size < 4:
        return None
    d = np.column_stack([dxp[good], dyp[good]])
    if good.size >= 6:
        mu = cp[good].mean(axis=0)
        scale = max(float(np.ptp(cp[good])), 1.0)
        A = np.column_stack([np.ones(good.size), (cp[good] - mu) / scale])
        coef, *_ = np.linalg.lstsq(A, d, rcond=None)
        fit = A @ coef
        B = np.column_stack([np.ones(cr.shape[0]), (cr - mu) / scale])
        pred = B @ coef
    else:
        fit = np.broadcast_to(np.median(d, axis=0), d.shape)
        pred = np.broadcast_to(np.median(d, axis=0), (cr.shape[0], 2))
    if np.median(np.abs(d - fit)) > 0.5:
        return None
    return pred[:, 0], pred[:, 1]


def _window_corners(xs, ys, cs, cl, w: int):
    """From the reference pixel positions ``(xs, ys)`` of the corners ``(cs, cl)`` of the ``w x w`` windows (``(N,
    4)`` each): ``(xs, ys)``, the resampling margin (reference px: the anti-alias low-pass of a finer reference
    reaches ~3 of its pixels per image pixel) and whether the corners may be one whole-pixel translation of the raw
    image's (False: they are not, so neither are the windows' grids; unknown where a corner has no ground point)."""
    with np.errstate(invalid="ignore"):
        ratio = np.hypot(xs[:, 1] - xs[:, 0], ys[:, 1] - ys[:, 0]) / w
    known = np.isfinite(xs).all() and np.isfinite(ys).all()
    translated = not known or whole_pixel_shift(xs - cs, ys - cl) is not None
    return xs, ys, 8.0 + 3.0 * np.nan_to_num(ratio, nan=1.0), translated


def _raw_reference_footprint(ref: RawReference, out, status, corners, centre_px):
    """Raw reference: the homologous reference position of every window centre (``ref_sample, ref_line``:
    ``centre_px``) and status ``outside_image`` for windows whose footprint (``corners``: :func:`_window_corners`)
    is not wholly inside the reference raster, so only the overlap of two images is matched. Returns the windows
    within the resampling margin of its edge (no-data there means outside as well)."""
    out["ref_sample"], out["ref_line"] = (np.array(v, dtype=float) for v in centre_px)
    xs, ys, margin = corners[:3]
    inside = np.all(ref.inside(xs, ys), axis=1)
    status[(status == 0) & ~inside] = 5
    return ~np.all(ref.inside(xs, ys, margin[:, None]), axis=1)


def _ortho_footprint(ref: ReferenceImage, c, w: int, W: int, H: int, status, margin, centre_px) -> np.ndarray:
    """Ortho reference, before anything is read or resampled: status ``outside_image`` for windows whose centre
    (``centre_px`` in the reference) is not inside the reference raster (by the resampling ``margin``) or the ``W x
    H`` raw image, so they are never resampled nor correlated. Returns the largest window size (even, <= ``w``)
    centred on each window that the raw image holds."""
    xc, yc = centre_px
    r = np.minimum.reduce([c[:, 0], W - c[:, 0], c[:, 1], H - c[:, 1]])
    inside = ref.inside(xc, yc, margin) & (r > 0)
    status[(status == 0) & ~inside] = 5
    return np.minimum(np.maximum(2 * np.floor(np.nan_to_num(r)), 0), w).astype(int)


def _shrunk_sizes(ref_f: np.ndarray, fits: np.ndarray, w: int) -> np.ndarray:
    """Size of every window of the stack ``ref_f`` (its reference, ``NaN`` where it has no data): ``w``, or for a
    window crossing the reference's edge or no-data (or the raw image's edge: ``fits``) the largest centred square
    free of them, a multiple of ``max(16, w // 8)`` (few distinct FFT sizes) and at least ``max(32, w // 4)``
    (as AROSICS shrinks its windows at edges; the GCP stays the window centre); 0 when none is."""
    q = max(16, w // 8)
    # Pixel i is in the centred s x s square when |2 i - (w - 1)| <= s - 1: the square is free of NaN up to the
    # smallest such "ring" value over the window's NaN pixels, minus one.
    ring = np.abs(2 * np.arange(w) - (w - 1))
    ring = np.maximum(ring[:, None], ring[None, :]).astype(np.int32)
    nan = np.isnan(ref_f)
    cut = np.flatnonzero(nan.any(axis=(1, 2)))
    free = np.full(ref_f.shape[0], w)
    free[cut] = np.where(nan[cut], ring, w + 1).min(axis=(1, 2)) - 1
    size = np.minimum(free, fits)
    size = np.where(size >= w, w, size // q * q)
    return np.where(size >= min(w, max(32, w // 4)), size, 0)


@with_gdal_exceptions
def match_tile(spec: TileSpec) -> Dict[str, np.ndarray]:
    """Match every window of one tile (the unit of parallel work; see the module docstring).

    Returns a dict of arrays, one entry per window: ``center_sample, center_line`` (the RPC-predicted position
    of the ground point), ``lon, lat, h``, ``dsample, dline`` (offset ``matched - predicted``, px), ``peak,
    peak_ratio, ncc, precision_px, texture``, ``flat`` (flat share of the window's central half, the larger of
    the two images': water, flat cloud) and ``status`` (see :data:`STATUS`).
    """
    return match_tiles([spec])[0]


#: :func:`match_tile`'s float fields, filled per window.
_TILE_FIELDS = ("lon", "lat", "h", "dsample", "dline", "peak", "peak_ratio", "ncc", "precision_px", "texture",
                "flat")


@with_gdal_exceptions
def match_tiles(specs: Sequence[TileSpec]) -> List[Dict[str, np.ndarray]]:
    """:func:`match_tile` of every spec, the same numbers: tiles of one image over one reference at the same window
    centres, one per band (as :func:`~gdal_gf4cal.matching.raw.match_raw_bands` groups them). What does not depend
    on the band is done once: the windows' ground points, their footprints in the reference and the reference
    resampled onto them (a third of a tile's work)."""
    sp = specs[0]
    c = np.asarray(sp.centers, dtype=float).reshape(-1, 2)
    geo = {k: np.full(c.shape[0], np.nan) for k in _TILE_FIELDS}
    geo["center_sample"], geo["center_line"] = c[:, 0].copy(), c[:, 1].copy()
    geo["status"] = np.zeros(c.shape[0], dtype=np.int8)
    if c.shape[0] == 0:
        return [{k: v.copy() for k, v in geo.items()} for _ in specs]
    rpc, dem, ref = sp.rpc, _dem_from_spec(sp.dem), _tile_reference(sp)
    ds = _cached(("img",) + _file_key(sp.image), lambda: gdal.Open(sp.image))
    rows = _tile_rows(sp, c)
    _drop_held_blocks(rows)
    try:
        near_edge, fits, translated = _tile_footprint(sp, c, geo, rpc, dem, ref, ds)
        idx = np.flatnonzero(geo["status"] == 0)
        ref_f = _fine_reference(sp, c, idx, rpc, dem, ref, translated)
        last = len(specs) - 1
        # Several bands, full windows (a raw reference): the reference windows' texture measures once (panms3)
        ref_m = _reference_measures(ref_f) if last and fits is None and ref_f is not None else None
        # The fine passes take their reference windows over (zeroing those with no-data): a copy for every band
        # but the last.
        return [_match_band(s, c, {k: v.copy() for k, v in geo.items()}, rpc, dem, ref, ds, near_edge, fits, idx,
                            ref_f if ref_f is None or i == last else ref_f.copy(), ref_m) for i, s in enumerate(specs)]
    finally:
        _release_blocks((ds, ref._open()), rows)


#: Bytes of GDAL's block cache (the whole process's) up to which the threads of :func:`run_tiles` keep their
#: datasets' blocks from one tile to the next (see :func:`_release_blocks`).
KEEP_BLOCKS_BYTES = 64 << 20

#: Per thread: ``held`` (the dict of :func:`run_tiles`' threads keeping blocks between tiles), when it keeps them.
_BLOCKS = threading.local()


def _tile_rows(spec: TileSpec, c) -> Tuple[float, float]:
    """The raw image's rows a tile may read (its coarse footprints and fine windows at any offset), about."""
    w = int(spec.window_px)
    reach = w * max(int(spec.factor), 1) / 2.0 + w / 2.0 + float(spec.params.get("search_px", 0.0)) + 8.0
    return float(c[:, 1].min()) - reach, float(c[:, 1].max()) + reach


def _drop_held_blocks(rows) -> None:
    """Before a tile: this thread's datasets drop the blocks kept from its last tile unless the two tiles share
    rows (the next tile of a row of tiles, or of a band of centres: the same strips)."""
    held = getattr(_BLOCKS, "held", None)
    last = None if held is None else held.get(threading.get_ident())
    if last is not None and (last[1][1] < rows[0] or rows[1] < last[1][0]):
        for d in last[0]:
            d.FlushCache()
        del held[threading.get_ident()]


def _release_blocks(datasets, rows) -> None:
    """After a tile: its blocks leave GDAL's block cache (each thread's handles would otherwise keep up to
    GDAL_CACHEMAX of the scene), except on the threads of :func:`run_tiles` while the cache holds at most
    :data:`KEEP_BLOCKS_BYTES`: neighbouring tiles read the same strips of a striped file (each decompressed
    once per tile otherwise: twice in all on the Sentinel-2 pair at 256 px) and the windows of the tile rows they
    share. :func:`run_tiles` flushes what its threads kept when it ends. Values never depend on the cache."""
    held = getattr(_BLOCKS, "held", None)
    last = None if held is None else held.get(threading.get_ident())
    if last is not None and any(a is not b for a, b in zip(last[0], datasets)):   # handles of another tile's files
        for d in last[0]:
            d.FlushCache()
    if held is not None and gdal.GetCacheUsed() <= KEEP_BLOCKS_BYTES:
        held[threading.get_ident()] = (datasets, rows)
        return
    for d in datasets:
        d.FlushCache()
    if held is not None:
        held.pop(threading.get_ident(), None)


def _keeping_blocks(fn, held):
    """``fn`` of a tile on a thread of :func:`run_tiles` that keeps its blocks between tiles, noted in ``held``."""
    def run(spec):
        _BLOCKS.held = held
        try:
            return fn(spec)
        finally:
            _BLOCKS.held = None
    return run


def _tile_reference(spec: TileSpec):
    """The tile's reference (cached per thread): an ortho, or a raw image with its model."""
    if spec.reference_model is None:
        return _cached(("ref", spec.reference_band) + _file_key(spec.reference),
                       lambda: ReferenceImage(spec.reference, spec.reference_band))
    ref = _cached(("rawref", spec.reference_band) + _file_key(spec.reference),
                  lambda: RawReference(spec.reference, spec.reference_model, spec.reference_band))
    return ref.with_model(spec.reference_model)


def _tile_footprint(spec: TileSpec, c, out, rpc, dem, ref, ds):
    """The windows' ground points (``lon, lat, h`` into ``out``; status 1 where there is none) and their footprints
    in the reference: ``(near_edge, fits, translated)`` (a raw reference's windows near its edge; an ortho's: the
    size that fits in it, else None; whether the reference may be the raw grid moved by whole pixels). The centres
    and the windows' corners are localised in one call and mapped into the reference in one: a tile's two smallest
    kernel calls, each ~300 NumPy calls whatever its size (each handing the GIL over to a waiting thread)."""
    status = out["status"]
    w = int(spec.window_px)
    S = c[:, 0][:, None] + np.array([0.0, -w / 2.0, w / 2.0, -w / 2.0, w / 2.0])[None, :]
    L = c[:, 1][:, None] + np.array([0.0, -w / 2.0, -w / 2.0, w / 2.0, w / 2.0])[None, :]
    lon, lat, h = (np.asarray(v, dtype=float).reshape(S.shape) for v in rpc.localize_dem(S, L, dem))
    out["lon"], out["lat"], out["h"] = lon[:, 0].copy(), lat[:, 0].copy(), h[:, 0].copy()
    status[~np.isfinite(out["lon"]) | ~np.isfinite(out["h"])] = 1
    xs, ys = (np.asarray(v, dtype=float).reshape(S.shape) for v in ref.ground_to_pixel(lon, lat, h))
    corners = _window_corners(xs[:, 1:], ys[:, 1:], S[:, 1:], L[:, 1:], w)
    if isinstance(ref, RawReference):
        return _raw_reference_footprint(ref, out, status, corners, (xs[:, 0], ys[:, 0])), None, corners[3]
    fits = _ortho_footprint(ref, c, w, ds.RasterXSize, ds.RasterYSize, status, corners[2], (xs[:, 0], ys[:, 0]))
    return np.zeros(c.shape[0], dtype=bool), fits, corners[3]


def _fine_reference(spec: TileSpec, c, idx, rpc, dem, ref, translated: bool = True):
    """The reference resampled onto the fine windows ``idx`` (float32), None without any. Not ``translated``
    (the windows' corners are not one whole-pixel translation): no probe for one (a localisation saved)."""
    if idx.size == 0:
        return None
    w = int(spec.window_px)
    # Window corners: centres are placed so that c - w/2 is integer (see plan_tiles).
    wx0 = np.round(c[idx, 0] - w / 2).astype(int)
    wy0 = np.round(c[idx, 1] - w / 2).astype(int)
    return reference_on_grids(rpc, dem, ref, wx0, wy0, w, spacing=1.0,
                              geometry_step=int(spec.params.get("geometry_step", 4)), shared=True,
                              dtype=np.float32, probe=translated)


def _reference_measures(ref_f):
    """The reference windows' quantities that every band of a group (:func:`match_tiles`: one tile per band at the
    same windows) would compute alike (:class:`_GroupReference`)."""
    return _GroupReference(ref_f)


class _GroupReference:
    """Reference-side quantities of a tile's fine windows ``ref_f`` (full size), computed once for every band of a
    group instead of once per band: :func:`_flag_windows`' texture measures ``tex, flat`` and :func:`_quadrant_ok`'s
    quarter gradients ``grad`` and centred quarters (of the windows without no-data; NaN for the others), and the
    spectra of every chunk of the fine passes (:meth:`spectra`: the chunks' windows are the same for every band, the
    reference windows do not move). Each window's quantities depend on that window alone: the same bits as each
    band's own (tests/matching/test_matching_fine.py)."""

    def __init__(self, ref_f):
        m, w = ref_f.shape[0], ref_f.shape[-1]
        self.tex, self.flat = np.full(m, np.nan), np.full(m, np.nan)
        ok = np.flatnonzero(~np.isnan(ref_f).any(axis=(1, 2)))
        self.tex[ok], self.flat[ok] = window_measures(ref_f, _central_half(w), which=ok)
        self.grad = np.full((m, 4), np.nan, dtype=np.float32)
        self.grad[ok] = _quarter_gradient(ref_f[:, :w // 2 * 2, :w // 2 * 2], ok)
        a, va = _centred_quarters(ref_f, ok)
        self.quarters = np.zeros((m,) + a.shape[1:], dtype=a.dtype), np.full((m,) + va.shape[1:], np.nan, va.dtype)
        self.quarters[0][ok], self.quarters[1][ok] = a, va
        self._spectra: Dict[bytes, Any] = {}

    def spectra(self, a, rows):
        """:func:`.correlate.spectra` of the reference windows ``a[rows]`` (once per group and chunk)."""
        key = rows.tobytes()
        got = self._spectra.get(key)
        if got is None:
            got = self._spectra[key] = spectra(a[rows])
        return got


def _central_half(w: int):
    """The rows/columns ``(q0, q1)`` of a ``w`` px window's central half, where :func:`_flag_windows` measures
    the flat share: a GCP is the window centre."""
    return w // 4, w - w // 4


def _match_band(spec: TileSpec, c, out, rpc, dem, ref, ds, near_edge, fits, idx, ref_f, ref_m=None):
    """One band of :func:`match_tiles` on the tile's footprint (``out`` filled so far, the live windows ``idx`` and
    their reference windows ``ref_f``, their quantities shared by the bands of a group ``ref_m`` if known:
    :class:`_GroupReference`): coarse offsets, then the fine level, into ``out``."""
    if idx.size == 0:
        return out
    p = spec.params
    w = int(spec.window_px)
    status = out["status"]
    # ---- search range of the fine window (as when it was cut from one pre-read block per window): beyond it
    # the window is flagged, never read far away.
    lim = max(w * int(spec.factor) // 2, w // 2 + int(math.ceil(p["search_px"])) + 2) - w // 2
    wx0 = np.round(c[:, 0] - w / 2).astype(int)
    wy0 = np.round(c[:, 1] - w / 2).astype(int)
    shift_x, shift_y = _coarse_offsets(spec, ds, rpc, dem, ref, wx0, wy0, status == 0,
                                       int(p.get("geometry_step", 4)), p.get("sigma_px", 1.0))

    # ---- fine level: the reference window at c, the raw window at c + the integer offset found so far.
    size = np.full(idx.size, w) if fits is None else _shrunk_sizes(ref_f, fits[idx], w)
    # A window cut by the reference's edge or no-data is matched on the largest centred square inside them
    # (smaller stacks, starting at the full windows' offsets); one left with too little is no-data.
    status[idx[size == 0]] = 1
    guide = None
    for s in np.unique(size[size > 0])[::-1]:
        k = (w - s) // 2
        sel = size == s
        # The fine passes take their reference windows over (zeroing those with no-data): the whole stack when
        # every window has the full size, else a copy of those of this size.
        whole = s == w and sel.all()
        sub = ref_f if whole else ref_f[sel, k:k + s, k:k + s]
        guide = _fine_level(spec, ds, c, idx[sel], sub, shift_x, shift_y, lim, near_edge, out, guide,
                            ref_m if whole else None, nan_free=fits is not None)
    return out


def _fine_level(spec: TileSpec, ds, c, idx, ref_f, shift_x, shift_y, lim: int, near_edge, out, guide, ref_m=None,
                nan_free: bool = False):
    """Fine level of windows ``idx`` (their reference windows ``ref_f``, all of one size): the raw window at ``c``
    + the integer offset found so far; results and status into ``out``. ``guide`` (centres, offsets, results and
    usability of windows already matched, as returned) predicts where these windows start; without it, pilots
    do. Returns the guide for the next windows. ``nan_free``: the reference windows hold no no-data (an ortho's
    windows, cut to squares free of it)."""
    m, w = idx.size, ref_f.shape[-1]
    p = spec.params
    sigma = p.get("sigma_px", 1.0)
    status = out["status"]
    W, H = ds.RasterXSize, ds.RasterYSize
    wx0 = np.round(c[idx, 0] - w / 2).astype(int)
    wy0 = np.round(c[idx, 1] - w / 2).astype(int)
    fine = _FinePasses(spec, ds, ref_f, wx0, wy0, shift_x[idx], shift_y[idx], lim, sigma, nan_free, ref_m)
    if guide is not None:
        _start_at(fine, np.arange(m), _predict_offsets(*guide, c[idx], p))
        fine.passes(np.arange(m))
    elif int(spec.factor) == 1 and m >= 16:
        _pilot_passes(fine, c[idx], p)
    else:
        fine.passes(np.arange(m))
    ox, oy, res = fine.ox, fine.oy, fine.res
    okw = ~(fine.nan_ref | fine.nan_raw)
    fine.a[~okw] = 0.0
    st = status[idx]
    # Fine window beyond the raster: the ground point is (truly) not in the image.
    fx0, fy0 = wx0 + ox, wy0 + oy
    beyond = fine.outside | (fx0 < 0) | (fy0 < 0) | (fx0 + w > W) | (fy0 + w > H) | near_edge[idx]
    st[~okw] = np.where(beyond[~okw], 5, 1)
    tex, flat = _flag_windows(st, fine.a, fine.b, res, p, okw, ref_m)
    status[idx] = st
    out["dsample"][idx] = ox + res["dx"]
    out["dline"][idx] = oy + res["dy"]
    for k in ("peak", "peak_ratio", "ncc", "precision_px"):
        out[k][idx] = res[k]
    out["texture"][idx] = tex
    out["flat"][idx] = flat
    if guide is not None:
        return guide
    return c[idx], ox + res["dx"], oy + res["dy"], res, okw


def _start_at(fine, which, pred) -> None:
    """Windows ``which`` start at the predicted offsets ``pred`` (rounded, within the search range), if any."""
    if pred is not None:
        fine.ox[which] = np.minimum(np.maximum(np.round(pred[0]), -fine.lim), fine.lim).astype(int)
        fine.oy[which] = np.minimum(np.maximum(np.round(pred[1]), -fine.lim), fine.lim).astype(int)


def _pilot_passes(fine, c, p) -> None:
    """The fine passes of windows centred on ``c`` without a coarse level. Every window would start at offset 0
    and most would need a second pass once their offset is found. Pilots (every 4th window) go first; where they
    agree on a smooth (affine) offset field, the others start at its prediction and mostly finish in one pass.
    The pilots are first probed on 2 x 2 block means of their windows (:func:`_probe_pilots`: a quarter of the
    pixels): when the probes agree, every window, pilots included, starts at the prediction (the pilots' second
    passes of full size saved); else the pilots go through full passes first."""
    m = c.shape[0]
    # Probes are cheap: every other window of a small tile (at least 8 probes).
    pred = _probe_pilots(fine, np.arange(0, m, 2 if m < 32 else 4), c, p)
    if pred is not None:
        _start_at(fine, np.arange(m), pred)
        fine.passes(np.arange(m))
        return
    pilots = np.arange(0, m, 4)
    fine.passes(pilots)
    rest = np.setdiff1d(np.arange(m), pilots)
    res = {k: v[pilots] for k, v in fine.res.items()}
    _start_at(fine, rest, _predict_offsets(c[pilots], fine.ox[pilots] + res["dx"], fine.oy[pilots] + res["dy"],
                                           res, ~(fine.nan_ref | fine.nan_raw)[pilots], c[rest], p))
    fine.passes(rest)


#: Smallest window (px) whose pilots are probed on 2 x 2 block means (:func:`_probe_pilots`): 64-px probes.
PROBE_MIN_PX = 128


def _probe_pilots(fine, pilots, c, p):
    """Offsets of every window (centres ``c``) predicted from the ``pilots``' probes (:func:`_predict_offsets`), or
    None: each pilot's reference window and raw window at its starting offset, as 2 x 2 block means, phase-
    correlated. The probe only has to find the integer offset where the full-size pass starts (the prediction
    is rounded; a window that starts a pixel off takes a second pass, as without the probe): its measurements
    are never results."""
    w = fine.w
    if w < PROBE_MIN_PX:
        return None
    ox, oy, lim = fine.ox[pilots], fine.oy[pilots], fine.lim
    b = fine._read(fine.wx0[pilots] + np.minimum(np.maximum(ox, -lim), lim),
                   fine.wy0[pilots] + np.minimum(np.maximum(oy, -lim), lim))
    ok = ~(fine.nan_ref[pilots] | np.isnan(b).any(axis=(1, 2))) & (np.abs(ox) <= lim) & (np.abs(oy) <= lim)
    b[~ok] = 0.0
    a2, b2 = _means_2x2(fine.a[pilots]), _means_2x2(b)
    r = phase_correlate(a2, b2, sigma_px=fine.sigma)
    dx, dy = ox + 2.0 * r.dx, oy + 2.0 * r.dy
    res = dict(peak=r.peak, peak_ratio=r.peak_ratio, ncc=r.ncc, dx=dx - np.round(dx), dy=dy - np.round(dy))
    return _predict_offsets(c[pilots], dx, dy, res, ok, c, p)


def _means_2x2(v: np.ndarray) -> np.ndarray:
    """2 x 2 block means of a float32 stack ``(n, 2 h, 2 w)``: the bits of ``v.reshape(n, h, 2, w, 2).mean(axis=(2,
    4))`` (NumPy adds each block's two row pairs, then the pairs' sums; / 4 is exact) in four whole-stack additions,
    ten times faster than its reduction over two strided length-2 axes."""
    s = v[:, 0::2, 0::2] + v[:, 0::2, 1::2]
    s += v[:, 1::2, 0::2] + v[:, 1::2, 1::2]
    s *= np.float32(0.25)
    return s


def _coarse_offsets(spec: TileSpec, ds, rpc, dem, ref, wx0, wy0, live, step: int, sigma: float):
    """Coarse level (factor f > 1): offsets ``(shift_x, shift_y)`` up to ~ w f / 4 of the ``live`` windows, found
    on decimated reads; zero without a coarse level."""
    p = spec.params
    w = int(spec.window_px)
    f = int(spec.factor)
    n = wx0.size
    W, H = ds.RasterXSize, ds.RasterYSize
    shift_x = np.zeros(n)
    shift_y = np.zeros(n)
    if not (f > 1 and live.any()):
        return shift_x, shift_y
    cw = w * f
    # The coarse footprint is kept inside the image where possible (the error field is smooth, so the
    # offset found a little aside still guides the fine level); it can stick out of a small image. Its corner
    # is on the image's lattice of f x f blocks (at most f - 1 px aside): the windows of a tile are cells of
    # one coarse grid, resampled and read once for them all.
    cx0 = np.minimum(np.maximum(wx0 + w // 2 - cw // 2, 0), max(W - cw, 0))
    cy0 = np.minimum(np.maximum(wy0 + w // 2 - cw // 2, 0), max(H - cw, 0))
    cx0 -= cx0 % f
    cy0 -= cy0 % f
    idx = np.flatnonzero(live)
    # The coarse level only has to land within a few pixels: the reference is read decimated to about the
    # coarse spacing (4 times fewer pixels to read, filter and interpolate than the fine level's 2 per spacing)
    # and resampled once on the grid of the windows' union (shared: a window of the default 64-px grid every
    # 256 px covers 4 x 4 of its neighbours' coarse cells). float32, as the fine level (the correlation
    # transforms float32 anyway).
    ref_c = reference_on_grids(rpc, dem, ref, cx0[idx], cy0[idx], w, spacing=f, geometry_step=step,
                               oversample=1.0, shared=True, dtype=np.float32)
    # Decimated reads: GDAL averages f x f blocks while reading (or uses overviews), so the coarse level
    # holds w x w pixels per window, not the (w f)^2 full-resolution footprint; dense windows in one read.
    raw_c = _read_boxes(ds, spec.band, spec.image_nodata, cx0[idx], cy0[idx], cw, decimation=f)
    # The coarse level only has to land within a few pixels: fill small gaps instead of giving up.
    bad_ref = np.isnan(ref_c).mean(axis=(1, 2))
    bad_raw = np.isnan(raw_c).mean(axis=(1, 2))
    usable = (bad_ref < 0.5) & (bad_raw < 0.5)
    # Gaps are filled with the window mean in *both* images at the same places, so a no-data border does
    # not become a one-sided edge that would attract the peak.
    if bad_ref.any() or bad_raw.any():          # none in the usual tile: its whole-stack passes saved
        gaps = np.isnan(ref_c) | np.isnan(raw_c)
        cnt = (~gaps).sum(axis=(1, 2))
        for arr in (ref_c, raw_c):
            mean = np.where(gaps, 0.0, arr).sum(axis=(1, 2)) / np.maximum(cnt, 1)
            arr[gaps] = np.broadcast_to(mean[:, None, None], arr.shape)[gaps]
    rc = phase_correlate(ref_c, raw_c, sigma_px=sigma, full=False)   # the peak alone: no NCC nor precision
    good = usable & (rc.peak_ratio >= p["min_peak_ratio"]) & (rc.peak >= p["min_peak"])
    shift_x[idx] = np.where(usable, rc.dx * f, 0.0)
    shift_y[idx] = np.where(usable, rc.dy * f, 0.0)
    # Windows whose coarse match is ambiguous borrow the tile's median offset (errors are smooth).
    if good.any() and not good.all():
        shift_x[idx[~good]] = np.median(shift_x[idx[good]])
        shift_y[idx[~good]] = np.median(shift_y[idx[good]])
    return shift_x, shift_y


class _FinePasses:
    """The fine level's state over the ``m`` windows still matched: the reference windows ``a`` (one transform
    for every pass: they do not move), the raw windows ``b`` at the integer offsets ``ox, oy``, the correlation
    results ``res`` and the no-data / outside flags."""

    FIELDS = ("dx", "dy", "peak", "peak_ratio", "ncc", "precision_px")

    def __init__(self, spec: TileSpec, ds, ref_f, wx0, wy0, shift_x, shift_y, lim: int, sigma: float,
                 nan_free: bool = False, shared=None):
        m = wx0.size
        w = ref_f.shape[-1]
        self.spec, self.ds, self.wx0, self.wy0, self.lim, self.sigma, self.w = spec, ds, wx0, wy0, lim, sigma, w
        self.a = ref_f.astype(np.float32, copy=False)  # taken over from the caller (float32 already)
        # Windows of an ortho are cut to squares free of no-data (_shrunk_sizes): no pass over the stack for them.
        self.nan_ref = np.zeros(m, dtype=bool) if nan_free else np.isnan(self.a).any(axis=(1, 2))
        self.a[self.nan_ref] = 0.0
        self.ox = np.round(shift_x).astype(int)
        self.oy = np.round(shift_y).astype(int)
        self.block = self._union_block(m, w)
        self.b = np.zeros((m, w, w), dtype=np.float32)
        self.nan_raw = np.zeros(m, dtype=bool)
        self.outside = np.zeros(m, dtype=bool)
        self._res = np.full((len(self.FIELDS), m), np.nan)         # the results, one row per field
        self.res = dict(zip(self.FIELDS, self._res))
        self.shared = shared     # a _GroupReference: the reference windows' spectra once for the group's bands

    def _union_block(self, m: int, w: int):
        """``(x0, y0, pixels)`` of the raw block holding every window at every offset it may take (within
        ``lim``), read once when the windows are dense (overlapping windows of a tile: each strip or tile of the
        raw file decoded once instead of once per window and pass), else None."""
        lim = self.lim
        x0, y0 = int(self.wx0.min()) - lim, int(self.wy0.min()) - lim
        nx, ny = int(self.wx0.max()) + w + lim - x0, int(self.wy0.max()) + w + lim - y0
        if m < 2 or nx * ny > 0.8 * m * w * w:
            return None
        ds = self.ds
        return x0, y0, read_block(ds.GetRasterBand(self.spec.band), ds.RasterXSize, ds.RasterYSize,
                                  self.spec.image_nodata, x0, y0, nx, ny)

    def _read(self, x0, y0):
        """The raw windows with top-left corners ``x0, y0`` (:func:`_read_boxes`, or cut from the union block)."""
        w = self.w
        if self.block is None:
            return _read_boxes(self.ds, self.spec.band, self.spec.image_nodata, x0, y0, w)
        bx, by, pix = self.block
        return cut_boxes(pix, bx, by, x0, y0, w)

    def passes(self, active):
        """Up to three passes over windows ``active``, a few windows at a time (:data:`PASS_BYTES`): each chunk's
        spectra, cross-power spectra and surfaces stay in the CPU cache through its passes instead of streaming
        stacks of them through memory (1.5 times faster on 256-px windows). Every window's passes depend on that
        window alone, so the chunks do not change the results."""
        for sl in chunks(active.size, PASS_BYTES // (4 * self.w * self.w)):
            self._chunk_passes(active[sl])

    def _chunk_passes(self, active):
        """Up to three passes over windows ``active``: read the raw window at the current offset, correlate,
        move by the integer part of the residual; only windows still moving are re-read and re-correlated (the
        reference windows' spectra are computed once: they do not move). A window without a usable pair (no-data
        or outside the raster in either window) stops there with the results of a pair of zero windows
        (:func:`.correlate.null_result`), without being transformed, and is flagged in :func:`_fine_level`."""
        ox, oy, lim = self.ox, self.oy, self.lim
        rows = active[~self.nan_ref[active]]
        Fs = spectra(self.a[rows]) if self.shared is None else self.shared.spectra(self.a, rows)
        pos = np.cumsum(~self.nan_ref[active]) - 1   # of the windows still moving, in Fs (with a reference)
        for it in range(3):
            axo, ayo = ox[active], oy[active]
            out_a = (np.abs(axo) > lim) | (np.abs(ayo) > lim)
            raw_a = self._read(self.wx0[active] + np.minimum(np.maximum(axo, -lim), lim),
                               self.wy0[active] + np.minimum(np.maximum(ayo, -lim), lim))
            nan_a = np.isnan(raw_a).any(axis=(1, 2)) | out_a
            okw = ~(self.nan_ref[active] | nan_a)
            raw_a[~okw] = 0.0
            live = np.flatnonzero(okw)
            jump_x, jump_y = np.zeros(active.size, int), np.zeros(active.size, int)
            if live.size:
                # The chunk's spectra themselves while every window has a pair (one without is done)
                Fa = Fs if live.size == Fs.S.shape[0] else Fs.take(pos[live])
                Gs = spectra(raw_a if live.size == active.size else raw_a[live])
                pk = correlate_spectra(Fa, Gs, self.sigma)
                jump_x[live] = np.where(np.abs(pk.dx) > 0.5, np.round(pk.dx), 0)
                jump_y[live] = np.where(np.abs(pk.dy) > 0.5, np.round(pk.dy), 0)
            # The last pass must not move the raw window: the measurement (and a, b, outside) belong to the
            # alignment they were made at, and ox + dx is only right for that one. A window still oscillating
            # about a half pixel keeps its last |residual| <= 0.75 px (accepted, consistent) or is flagged weak.
            done = np.ones(active.size, bool) if it == 2 else ~((jump_x != 0) | (jump_y != 0))
            if live.size:
                self._store(active[done & okw], pk.quality(Fa, Gs, np.flatnonzero(done[live])))
            self._store(active[done & ~okw], null_result(raw_a.shape[1:], self.sigma))
            sel = active[done]
            self.b[sel] = raw_a if sel.size == active.size else raw_a[done]     # no copy of the chunk
            self.nan_raw[sel] = nan_a[done]
            self.outside[sel] = out_a[done]
            ox[active[~done]] += jump_x[~done]
            oy[active[~done]] += jump_y[~done]
            active, pos = active[~done], pos[~done]
            if active.size == 0:
                break

    def _store(self, sel, q) -> None:
        """Results ``q`` (a :class:`.correlate.CorrelationResult`) of the windows ``sel``."""
        self._res[:, sel] = np.array([getattr(q, k) for k in self.FIELDS])


#: Bytes of float32 windows per chunk of the fine passes (:meth:`_FinePasses.passes`): 4 windows of 256 px, 64 of
#: 64 px; their spectra and correlation surfaces (about 5 times as much) stay in a 1 MB L2 cache or close to it.
PASS_BYTES = 1 << 20


#: Window size (px) from which a low NCC alone does not reject a window with an unambiguous phase-correlation peak
#: (peak ratio at least twice ``min_peak_ratio``). The NCC weighs the windows' energy, which on two dates sits in
#: a few bright fields whose reflectance changed; the phase correlation weighs every frequency alike and keeps the
#: many edges that did not move. On small windows the NCC check is what stops chance peaks (the height of a peak
#: of random phases falls as 1/w: ~0.11 at 64 px, 0.03 at 256 px against ``min_peak`` 0.2). On the Sentinel-2
#: pair ten days apart (bench/bench_arosics.py) 35 of the 58 256-px windows rejected as weak had NCC < 0.3 with
#: peak ratios 4-20; their offsets agree with AROSICS's and with the pair's smooth offset field as the others do.
LARGE_WINDOW_PX = 128


def _flag_windows(st, a, b, res, p, okw, ref_m=None):
    """Status codes of the windows still 0 (2 flat, 3 weak peak, 4 quadrant check failed), in place; returns their
    texture and flat fraction. Windows without a usable pair (not ``okw``: zeroed) are not measured: texture 0
    and flat share 1, what the measures give on zero windows."""
    # Texture over the whole window, and no more than half of its central half flat: a GCP is the window centre,
    # so a window centred on water or on a flat cloud is skipped even when a shoreline elsewhere would correlate.
    w = a.shape[-1]
    q0, q1 = _central_half(w)
    tex, flat = np.zeros(okw.size), np.ones(okw.size)
    live = np.flatnonzero(okw)
    tex_a, flat_a = window_measures(a, (q0, q1), which=live) if ref_m is None else (ref_m.tex[live],
                                                                                    ref_m.flat[live])
    tex_b, flat_b = window_measures(b, (q0, q1), which=live)
    tex[live] = np.minimum(tex_a, tex_b)
    flat[live] = np.maximum(flat_a, flat_b)
    st[(st == 0) & ((tex < p["min_texture"]) | (flat > 0.5))] = 2
    # The NCC guards small windows against a peak that is chance or other ground; from LARGE_WINDOW_PX on, an
    # unambiguous peak (twice the ratio asked) is enough (see LARGE_WINDOW_PX).
    similar = (res["ncc"] >= p["min_ncc"]) | ((w >= LARGE_WINDOW_PX) & (res["peak_ratio"] >= 2 * p["min_peak_ratio"]))
    weak = (res["peak"] < p["min_peak"]) | (res["peak_ratio"] < p["min_peak_ratio"]) | ~similar | \
        (np.abs(res["dx"]) > 0.75) | (np.abs(res["dy"]) > 0.75)
    st[(st == 0) & weak] = 3
    # Quarter check at the integer alignment (the residual is < 1 px; the threshold is far from 1 anyway), on the
    # windows still accepted.
    live = np.flatnonzero(st == 0)
    st[live[~_quadrant_ok(a, b, p["min_quadrant_ncc"], which=live, shared=ref_m)]] = 4
    return tex, flat


# ---------------------------------------------------------------------------------------------- planning side
DEFAULTS = dict(min_peak=0.2, min_peak_ratio=2.0, min_ncc=0.3, min_texture=1.5, min_quadrant_ncc=0.2,
                sigma_px=1.0, geometry_step=4)


#: Grid step of the windows on a large image (px) and the fewest windows a default grid puts across the image's
#: shorter side (:func:`default_spacing`).
DEFAULT_SPACING_PX = 256
MIN_WINDOWS_ACROSS = 8


def default_spacing(width: int, height: int, window_px: int, margin_px: Optional[int] = None) -> int:
    """The grid step when none is given: :data:`DEFAULT_SPACING_PX`, or finer on a small image (a crop) so that
    :data:`MIN_WINDOWS_ACROSS` windows fit across its shorter side, never closer than a window (windows that
    overlap measure the same texture twice). 256 px on a 10,000 px scene, 128 px on 1024 px, 64 px on a 500 px crop
    (where 256 px gave 4 windows, and one or two GCPs)."""
    w = int(window_px)
    margin = w // 2 if margin_px is None else int(margin_px)
    span = min(width, height) - 2 * margin - w                # where window centres may lie
    return int(min(DEFAULT_SPACING_PX, max(w, span // (MIN_WINDOWS_ACROSS - 1))))


#: Fewest reference pixels a window should span: below it matches turn weak and imprecise (a rendered scene under a
#: reference 4x / 6x / 8x coarser than its pixels, 64-px windows: all kept, 0.31 px per axis / a third rejected,
#: ~1 px / 3 of 64 kept).
MIN_REFERENCE_PX_PER_WINDOW = 16


def reference_coarseness(model, reference, width: int, height: int) -> float:
    """Reference pixel size over the image's at the image centre (4.0: a 2 m reference under a 0.5 m image), from
    the image's sensor model at its height offset and the reference's own geometry; NaN when that geometry fails."""
    s = width / 2.0 + np.array([0.0, 1.0, 0.0])
    l = height / 2.0 + np.array([0.0, 0.0, 1.0])
    h = np.full(3, float(getattr(model, "height_off", 0.0)))
    try:
        lon, lat = model.localize(s, l, h)[:2]
        x, y = reference.ground_to_pixel(lon, lat, h)
    except Exception:                                # a diagnostic only: never the reason a run fails
        return float("nan")
    per_px = np.hypot(x[1:] - x[0], y[1:] - y[0])    # reference pixels per image pixel along sample, line
    return float(1.0 / np.mean(per_px)) if np.all(per_px > 0) else float("nan")


def coarse_reference_hint(coarseness: float, window_px: int) -> Optional[str]:
    """What to do when a window spans fewer than :data:`MIN_REFERENCE_PX_PER_WINDOW` reference pixels (None:
    enough)."""
    if not coarseness > 0 or window_px / coarseness >= MIN_REFERENCE_PX_PER_WINDOW:
        return None
    better = 2 * math.ceil(MIN_REFERENCE_PX_PER_WINDOW * coarseness / 2.0)
    return (f"the reference's pixels are {coarseness:.1f}x the image's: a {window_px}-px window spans "
            f"{window_px / coarseness:.0f} of them, too few for firm matches; use --window {better} or more, or a "
            "finer reference")


@with_gdal_exceptions
def _image_info(image, band: int):
    path = image.GetDescription() if hasattr(image, "GetDescription") else os.fspath(image)
    try:
        ds = gdal.Open(path)
    except RuntimeError as exc:
        raise Gf4calError(f"cannot open image {path}: {str(exc).splitlines()[0]}") from None
    if band < 1 or band > ds.RasterCount:
        raise Gf4calError(f"image {path} has no band {band}; choose a band from 1 to {ds.RasterCount}")
    return path, ds.RasterXSize, ds.RasterYSize, ds.GetRasterBand(band).GetNoDataValue()


def plan_tiles(image, rpc, reference, dem, spacing_px: Optional[int] = None, window_px: int = 64, *,
               search_px: float = 64, tile_windows: int = 64, band: int = 1, reference_band: int = 1,
               margin_px: Optional[int] = None, reference_model: Any = None,
               region: Optional[Sequence[float]] = None, **params) -> Tuple[List[TileSpec], Dict[str, Any]]:
    """The window grid and its tiles: ``(specs, context)`` for :func:`match_tile` and :func:`assemble_gcps`.

    Window centres form a regular grid of step ``spacing_px`` (default :func:`default_spacing`) kept
    ``margin_px`` (default half a window) from the image edges; they are grouped into square tiles of about
    ``tile_windows`` windows. ``region`` = ``(sample0, line0, sample1, line1)`` keeps only the centres inside that
    box (the grid itself does not move).
    ``reference_model`` (a sensor model) makes ``reference`` a raw image seen through it
    (:class:`.resample.RawReference`) instead of an orthophoto.
    """
    path, W, H, nodata = _image_info(image, band)
    if rpc is None:
        rpc = RPCModel.from_file(path)
    # Compute the RPC's derived matrices (least squares, matmul) once, here: they travel with the pickled spec,
    # so every worker process uses the same bits whatever its BLAS threads (bit-identical GCPs, issue 14).
    for model in (rpc, reference_model):
        if isinstance(model, RPCModel):
            model._approximate_inverse, model._coeffs_with_derivatives, model._coeffs  # noqa: B018
    w = int(window_px)
    if w < 16 or w % 2:
        raise Gf4calError(f"window must be an even number of pixels >= 16 (got {window_px})")
    spacing = default_spacing(W, H, w, margin_px) if spacing_px is None else int(spacing_px)
    if spacing < 1:
        raise Gf4calError(f"spacing must be a positive number of pixels (got {spacing_px})")
    ref_path = os.fspath(reference)
    if not os.path.exists(ref_path) and not ref_path.startswith("/vsi"):
        raise Gf4calError(f"reference not found: {ref_path}")
    # fail early with a clear message
    ref = (ReferenceImage(ref_path, reference_band) if reference_model is None
           else RawReference(ref_path, reference_model, reference_band))
    dem_spec = _dem_spec(dem)
    if dem_spec[0] == "file" and not os.path.exists(str(dem_spec[1])) and not str(dem_spec[1]).startswith("/vsi"):
        raise Gf4calError(f"DEM not found: {dem_spec[1]}")
    # Coarse factor: smallest power of two whose level sees offsets of search_px (a quarter of its footprint).
    f = 1
    while w * f / 4.0 < search_px and f < 64:
        f *= 2
    margin = w // 2 if margin_px is None else int(margin_px)
    xs = np.arange(margin + w / 2, W - margin - w / 2 + 1e-9, spacing)
    ys = np.arange(margin + w / 2, H - margin - w / 2 + 1e-9, spacing)
    if xs.size == 0 or ys.size == 0:
        raise Gf4calError(f"image {W}x{H} is too small for {w}-px windows; use a smaller --window")
    # Centre the grid; centres at integer + w/2 so that window corners are whole pixels.
    xs = np.floor(xs + (W - margin - w / 2 - xs[-1]) / 2 - w / 2) + w / 2
    ys = np.floor(ys + (H - margin - w / 2 - ys[-1]) / 2 - w / 2) + w / 2
    if region is not None:
        r0, r1, r2, r3 = (float(v) for v in region)
        xs = xs[(xs >= r0) & (xs <= r2)]
        ys = ys[(ys >= r1) & (ys <= r3)]
        if xs.size == 0 or ys.size == 0:
            raise Gf4calError(f"no {w}-px window of {path} fits in the region {tuple(region)}; enlarge the region "
                              "or use a smaller window")
    per_side = max(1, int(round(math.sqrt(tile_windows))))
    specs = []
    p = dict(DEFAULTS)
    p.update({k: v for k, v in params.items() if v is not None})
    p["search_px"] = float(search_px)
    for ty in range(0, ys.size, per_side):
        for tx in range(0, xs.size, per_side):
            gx, gy = np.meshgrid(xs[tx:tx + per_side], ys[ty:ty + per_side])
            centers = np.column_stack([gx.ravel(), gy.ravel()])
            specs.append(TileSpec(image=path, band=band, image_nodata=nodata, rpc=rpc, reference=ref_path,
                                  reference_band=reference_band, dem=dem_spec, centers=centers, window_px=w,
                                  factor=f, params=p, reference_model=reference_model))
    ctx = dict(rpc=rpc, image=path, reference=ref_path, n_windows=int(xs.size * ys.size), window_px=w,
               spacing_px=spacing, factor=f, reference_model=reference_model,
               reference_coarseness=reference_coarseness(rpc, ref, W, H))
    return specs, ctx


def assemble_gcps(results: Sequence[Dict[str, np.ndarray]], ctx: Dict[str, Any], *, outlier_model: str = "affine",
                  outlier_threshold_px: float = 3.0, seed: int = 0, min_sigma_px: float = 0.05):
    """Concatenate tile results, flag outliers (:func:`.filters.reject_outliers`) and build the GCP table.

    Returns a GeoDataFrame in the project's GCP schema (``id, lon, lat, h, sample, line, role, sigma``) plus
    ``peak, peak_ratio, ncc, precision_px, texture, dsample, dline, outlier`` for the accepted windows;
    ``gdf.attrs['windows']`` counts windows per status (:data:`STATUS`) and outliers.
    """
    keys = results[0].keys() if results else []
    allr = {k: np.concatenate([np.atleast_1d(r[k]) for r in results]) for k in keys}
    st = allr.get("status", np.zeros(0, dtype=np.int8))
    counts = {name: int(np.count_nonzero(st == code)) for code, name in STATUS.items()}
    acc = np.flatnonzero(st == 0)
    sel = {k: v[acc] for k, v in allr.items()}
    n = acc.size
    if n:
        # Row-major order of the grid (tiles come back in any order).
        order = np.lexsort((sel["center_sample"], sel["center_line"]))
        sel = {k: v[order] for k, v in sel.items()}
        flt = reject_outliers(sel["center_sample"], sel["center_line"], sel["dsample"], sel["dline"],
                              model=outlier_model, threshold_px=outlier_threshold_px, seed=seed)
        outlier = flt.outlier
    else:
        outlier = np.zeros(0, dtype=bool)
    counts["outliers"] = int(outlier.sum())
    counts["total"] = int(st.size)
    sample = sel.get("center_sample", np.zeros(0)) + sel.get("dsample", np.zeros(0))
    line = sel.get("center_line", np.zeros(0)) + sel.get("dline", np.zeros(0))
    prec = sel.get("precision_px", np.zeros(0))
    gdf = make_gcps(sel.get("lon", np.zeros(0)), sel.get("lat", np.zeros(0)), sel.get("h", np.zeros(0)), sample, line,
                    ids=[f"m{i + 1:05d}" for i in range(n)], role="control",
                    sigma=np.maximum(np.nan_to_num(prec, nan=1.0, posinf=1.0), min_sigma_px),
                    peak=sel.get("peak", np.zeros(0)), peak_ratio=sel.get("peak_ratio", np.zeros(0)),
                    ncc=sel.get("ncc", np.zeros(0)), precision_px=prec, texture=sel.get("texture", np.zeros(0)),
                    dsample=sel.get("dsample", np.zeros(0)), dline=sel.get("dline", np.zeros(0)),
                    outlier=np.asarray(outlier, dtype=bool))
    gdf.attrs["windows"] = counts
    gdf.attrs["spacing_px"] = int(ctx["spacing_px"])
    gdf.attrs["reference_coarseness"] = ctx["reference_coarseness"]
    gdf.attrs["window_px"] = int(ctx["window_px"])
    return gdf


def run_tiles(specs: Sequence[TileSpec], executor: Optional[cf.Executor] = None, *, workers: Optional[int] = None,
              progress=None, stop: float = 0.95, fn=None) -> List[Dict[str, np.ndarray]]:
    """:func:`match_tile` on every spec, results in submission order (deterministic whatever the executor).
    ``fn``: another function of a spec run the same way (serial kernels and BLAS inside; default
    :func:`match_tile`'s).

    Without ``executor``: a thread pool of ``workers`` threads (default: ``GF4CAL_NUM_THREADS``, or the caller's
    :func:`gdal_gf4cal.threads.limit`, else the machine's cores; 1 runs in the calling thread), each tile with
    serial point kernels (:func:`gdal_gf4cal.threads.serial`: the tiles are the parallel unit, no threads within
    threads). Tiles are fixed by the window grid, never by the threads: the GCPs are bit-identical whatever
    ``workers``.
    """
    own = None
    # Every tile with serial kernels and BLAS on its thread, on any executor (its numbers depend on BLAS's threads)
    fn = _match_tile_serial if fn is None else fn
    held: Dict[int, Any] = {}
    if executor is None:
        # Our own threads (or this one) keep their raster blocks from tile to tile (_release_blocks), flushed
        # below; another executor's workers flush after every tile.
        fn = _keeping_blocks(fn, held)
        nw = threads.pool_workers(workers, len(specs))
        if nw > 1:
            # Threads: every heavy step of match_tile (GDAL reads, FFTs, spline interpolation, NumPy on whole
            # stacks) releases the GIL, and threads share the datasets' block caches and start at once; a
            # process pool paid ~0.3 s of start-up and pickling on a 10240^2 scene for no gain in throughput.
            own = executor = cf.ThreadPoolExecutor(max_workers=nw, thread_name_prefix="gf4cal-tile")
    try:
        # Tile-sized arrays kept on this process's heap (keep_heap: no page faults and unmaps at every stack of
        # windows); results in submission order whatever the executor (gdal_gf4cal.executors, issue 14).
        keep_heap()
        return map_ordered(fn, specs, executor, progress=progress, stop=stop, label="tile")
    finally:
        if own is not None:
            own.shutdown(wait=True, cancel_futures=True)
        for datasets, _ in held.values():   # the threads are done with them
            for d in datasets:
                d.FlushCache()


def _match_tile_serial(spec: TileSpec) -> Dict[str, np.ndarray]:
    """:func:`match_tile` with serial point kernels and BLAS on the calling thread (:func:`threads.serial`: a tile of
    :func:`run_tiles`, on a pool thread or not)."""
    with threads.serial():
        return match_tile(spec)


def _match_tiles_serial(specs: Sequence[TileSpec]) -> List[Dict[str, np.ndarray]]:
    """:func:`match_tiles` as :func:`_match_tile_serial` runs one tile (the unit of a band group's work)."""
    with threads.serial():
        return match_tiles(specs)


@threads.blas_serial()     # BLAS on the calling thread, as in the CLI and QGIS (threads.py)
def collect_gcps(image, rpc, reference, dem, spacing_px: Optional[int] = None, window_px: int = 64, *,
                 workers: Optional[int] = None, executor: Optional[cf.Executor] = None, min_peak: float = 0.2,
                 min_peak_ratio: float = 2.0, min_ncc: float = 0.3, min_texture: float = 1.5,
                 search_px: float = 64, outlier_model: str = "affine", outlier_threshold_px: float = 3.0,
                 seed: int = 0, tile_windows: int = 64, band: int = 1, reference_band: int = 1,
                 geometry_step: int = 4, progress=None):
    """Collect GCPs by sub-pixel matching of a raw image against a reference orthophoto + DEM (issue 7).

    Parameters
    ----------
    image : path of the raw image (any GDAL raster) or an open dataset.
    rpc : its :class:`gdal_gf4cal.RPCModel` (possibly biased: that is what the GCPs measure), or ``None`` to read
        it from the image.
    reference : path of the reference orthophoto (any GDAL raster, any CRS, any resolution; overviews are used
        when it is much finer than the raw image).
    dem : :class:`gdal_gf4cal.DEM`, DEM path (ellipsoidal heights; give a ``DEM(geoid=...)`` otherwise) or a
        constant height in metres.
    spacing_px, window_px : grid step and (even) window size, raw pixels; the step by default
        :func:`default_spacing` (256 px, finer on images under ~1,900 px: eight windows across the shorter side).
    workers : parallel threads (default: ``GF4CAL_NUM_THREADS``, else the machine's cores; 1 runs in the calling
        thread). ``executor`` : any
        :class:`concurrent.futures.Executor` (process pool, ``distributed.Client.get_executor()``...) instead.
    min_peak, min_peak_ratio, min_ncc : correlation check (peak of the phase-correlation surface in [0, 1],
        peak over second peak, correlation coefficient at the sub-pixel shift; windows of
        :data:`LARGE_WINDOW_PX` px and more whose peak ratio is at least ``2 min_peak_ratio`` need no ``min_ncc``).
    min_texture : texture-to-noise ratio below which a window is featureless (:func:`.texture_strength`).
    search_px : largest initial offset to find (px); sets the coarse level (``>= 50`` px by default).
    outlier_model : ``'translation'``, ``'affine'``, ``'poly2'`` or ``'poly3'`` for the RANSAC + MAD filter;
        ``outlier_threshold_px`` its RANSAC inlier distance; ``seed`` its random seed.
    progress : ``callable(fraction, message)``; raise :class:`gdal_gf4cal.CancelledError` in it to cancel.

    Returns
    -------
    geopandas.GeoDataFrame in the GCP schema (DESIGN.md): ``id, lon, lat, h`` (the ground point, from the RPC and
    the DEM at the window centre), ``sample, line`` (where the raw image truly shows it, GDAL convention),
    ``role='control'``, ``sigma`` (= estimated precision, px) plus ``peak, peak_ratio, ncc, precision_px,
    texture, dsample, dline`` (offset measured - RPC-predicted) and ``outlier``. Only windows that passed the
    checks are rows; ``gdf.attrs['windows']`` counts all windows by outcome.
    """
    specs, ctx = plan_tiles(image, rpc, reference, dem, spacing_px, window_px, search_px=search_px,
                            tile_windows=tile_windows, band=band, reference_band=reference_band,
                            min_peak=min_peak, min_peak_ratio=min_peak_ratio, min_ncc=min_ncc,
                            min_texture=min_texture, geometry_step=geometry_step)
    hint = coarse_reference_hint(ctx["reference_coarseness"], ctx["window_px"])
    if hint:
        warnings.warn(hint, stacklevel=2)
    report(progress, 0.0, f"matching {ctx['n_windows']} windows in {len(specs)} tiles")
    results = run_tiles(specs, executor, workers=workers, progress=progress)
    gdf = assemble_gcps(results, ctx, outlier_model=outlier_model, outlier_threshold_px=outlier_threshold_px,
                        seed=seed)
    report(progress, 1.0, f"{len(gdf)} GCPs ({gdf.attrs['windows']['outliers']} outliers)")
    return gdf
