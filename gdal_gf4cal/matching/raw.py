"""Raw-to-raw matching through two sensor models and the DEM: CCD overlaps, band to band, pan to MS (METHODS §8, §9).

The matcher of :mod:`.collect` with a raw image as the reference (:class:`.resample.RawReference`): for each window
of a regular grid over ``image`` (GDAL pixel convention),

1. its centre ``c`` is localised on the DEM with ``model``: ground point ``X = (lon, lat, h)``;
2. the reference raw image is resampled into ``image``'s geometry around ``c``: node ``u`` of the window shows the
   reference at ``reference_model.project(model.localize_dem(u))`` (decimated and low-passed when the reference is
   finer, e.g. pan for an MS image);
3. phase correlation finds where ``image`` truly shows what the reference shows at ``X``: ``c + d``.

So the reference point ``p = reference_model.project(X)`` (``ref_sample, ref_line``) and the image point
``c + d`` (``sample, line``) are homologous, ``pred_sample, pred_line = c`` is where ``p`` localised on the DEM with
``reference_model`` and projected with ``model`` falls, and ``d = (sample, line) - (pred_sample, pred_line)``.
With ``image`` = MS and reference = pan that is exactly METHODS §9's ``∇ = p' - p''`` (MS pixels).

Windows whose footprint is not wholly inside the reference are ``outside_image`` (status 5), and the window grid is
first restricted to the part of ``image`` the reference covers, so only the overlap of two CCDs is ever read.

- :func:`match_raw` one row per window (DataFrame); :func:`match_raw_bands` the same for several bands at once
  (their tiles in one queue of the pool);
- :func:`match_ties` tie points between two images in the long observation table (:mod:`gdal_gf4cal.observations`);
- :func:`pan_ms_cells` dense pan-MS matches averaged robustly on a regular MS grid (METHODS §9 observations).
"""
from __future__ import annotations

import math
import os
from typing import Any, Dict, Optional, Sequence, Tuple, Union

import numpy as np
import pandas as pd

from .. import threads
from ..dem import DEM
from ..errors import Gf4calError
from ..progress import report
from ..rpc import RPCModel
from ..stats import grouped_trimmed_mean
from .collect import (STATUS, TileSpec, _dem_from_spec, _dem_spec, _image_info, _match_tiles_serial, plan_tiles,
                      run_tiles)
from .filters import reject_outliers
from .resample import RawReference

__all__ = ["match_raw", "match_raw_bands", "match_ties", "pan_ms_cells", "cells_from_matches", "cell_edges",
           "overlap_region", "thread_dem", "RAW_COLUMNS", "CELL_COLUMNS"]

#: Columns of :func:`match_raw`'s table, in order.
RAW_COLUMNS = ("sample", "line", "pred_sample", "pred_line", "ref_sample", "ref_line", "lon", "lat", "h",
               "d_sample", "d_line", "sigma", "score", "peak", "peak_ratio", "ncc", "texture", "flat", "status",
               "outlier")

#: Columns of :func:`pan_ms_cells`'s table, in order.
CELL_COLUMNS = ("cell_id", "col", "row", "sample", "line", "d_sample", "d_line", "sigma_sample", "sigma_line", "n",
                "n_windows", "accepted_fraction", "clear_fraction", "usable")

#: Smallest precision reported for one window, px: the estimate of a noise-free window tends to 0 while resampling
#: and rendering leave a few hundredths of a pixel (as :func:`.collect.assemble_gcps`).
MIN_SIGMA_PX = 0.05


def _model_or_rpc(model, path: str, what: str):
    if model is not None:
        return model
    try:
        return RPCModel.from_file(path)
    except Gf4calError as exc:
        raise Gf4calError(f"{what} {path}: no sensor model given and {exc}") from None


def thread_dem(dem):
    """``dem`` (a :class:`~gdal_gf4cal.DEM` or a path, opened with its own geoid and no-data policy, band 1) as the
    matcher's cache holds it (:func:`match_raw_bands` uses it, on every thread: a DEM opens a GDAL handle per thread
    itself): a caller that works with the DEM before matching (the pan-MS geometry) reads it once instead of once
    more per pool thread, and a long-lived process (QGIS) once per version of the file.
    Anything else (a constant height, another band) as it is."""
    if not isinstance(dem, DEM) or dem.is_constant or dem.path is None or getattr(dem, "_band_index", 1) != 1:
        return dem
    return _dem_from_spec(_dem_spec(dem))


def overlap_region(image, model, reference, reference_model, dem, *, band: int = 1, reference_band: int = 1,
                   step_px: float = 32.0) -> Tuple[Tuple[float, float, float, float], float]:
    """Part of ``image`` that ``reference`` also shows: ``((sample0, line0, sample1, line1), scale)``.

    Nodes every ``step_px`` over ``image`` are localised on the DEM with ``model`` and projected into the reference
    with ``reference_model``; the box bounds those landing inside the reference (plus one step), and ``scale`` is
    the median number of reference pixels per image pixel there. Raises :class:`Gf4calError` when none does.
    """
    path, W, H, _ = _image_info(image, band)
    ref = RawReference(os.fspath(reference), reference_model, reference_band)
    dem_ = _dem_from_spec(_dem_spec(dem))
    step = max(float(step_px), 1.0)
    xs = np.append(np.arange(0.0, W, step), float(W))
    ys = np.append(np.arange(0.0, H, step), float(H))
    S, L = np.meshgrid(xs, ys)
    lon, lat, h = model.localize_dem(S, L, dem_)
    if not np.isfinite(np.asarray(h, dtype=float)).any():
        raise Gf4calError(f"the DEM gives no height under {os.path.basename(path)}; give a DEM that covers the "
                          "scene (or a constant height)")
    rs, rl = ref.ground_to_pixel(lon, lat, h)
    inside = ref.inside(rs, rl)
    if not inside.any():
        raise Gf4calError(f"{os.path.basename(path)} and {os.path.basename(ref.path)} do not overlap on the ground "
                          "(through their sensor models and the DEM); give images that see common ground")
    box = (max(float(S[inside].min()) - step, 0.0), max(float(L[inside].min()) - step, 0.0),
           min(float(S[inside].max()) + step, float(W)), min(float(L[inside].max()) + step, float(H)))
    with np.errstate(invalid="ignore"):
        ds = np.hypot(np.diff(rs, axis=1), np.diff(rl, axis=1)) / np.diff(xs)[None, :]
    ok = np.isfinite(ds) & inside[:, 1:]
    scale = float(np.median(ds[ok])) if ok.any() else 1.0
    return box, scale


def match_raw(image, model, reference_image, reference_model, dem, *, spacing_px: int = 64, window_px: int = 32,
              search_px: float = 8, band: int = 1, reference_band: int = 1, region: Optional[Sequence[float]] = None,
              executor=None, workers: Optional[int] = None, progress=None, tile_windows: int = 256,
              outlier_model: Optional[str] = "affine", outlier_threshold_px: float = 3.0, seed: int = 0,
              margin_px: Optional[int] = None, min_sigma_px: float = MIN_SIGMA_PX, **params):
    """Match ``image`` against another raw image through both sensor models and the DEM (module docstring).

    Parameters
    ----------
    image, reference_image : paths of two raw images (any GDAL raster); ``band``, ``reference_band`` the bands.
    model, reference_model : their sensor models (:class:`~gdal_gf4cal.RPCModel` or any model on the sensor
        contract); ``None`` reads the image's RPC.
    dem : :class:`~gdal_gf4cal.DEM`, DEM path (ellipsoidal heights) or a constant height (m).
    spacing_px, window_px : grid step and (even) window size, pixels of ``image``.
    search_px : largest offset to find (px of ``image``); beyond ~``window_px / 4`` a coarse level is used.
    region : ``(sample0, line0, sample1, line1)`` box of ``image`` to match in (default all); it is always
        intersected with the overlap of the two images (:func:`overlap_region`). ``margin_px``: distance of the
        window centres' grid from the image edges (default half a window).
    executor, workers : as :func:`.collect.collect_gcps` (tiles of ``tile_windows`` windows).
    outlier_model, outlier_threshold_px, seed : RANSAC + MAD consistency check of the accepted offsets
        (:func:`.filters.reject_outliers`; ``None`` skips it): ``outlier`` column.
    params : matcher thresholds (``min_peak, min_peak_ratio, min_ncc, min_texture, sigma_px, geometry_step``).

    Returns
    -------
    pandas.DataFrame, one row per window (row-major), columns :data:`RAW_COLUMNS`: ``sample, line`` measured
    position in ``image``; ``pred_sample, pred_line`` window centre (where the reference point, the DEM and
    ``model`` predict it); ``ref_sample, ref_line`` the homologous reference position; ``lon, lat, h`` the ground
    point (``model`` on the DEM at the centre); ``d_sample, d_line`` = measured - predicted (px of ``image``;
    METHODS §9's ∇ for image = MS, reference = pan); ``sigma`` the matcher's precision estimate (px, floored at
    ``min_sigma_px``); ``score`` (= ``ncc``), ``peak, peak_ratio, ncc, texture``, ``flat`` (flat share of the
    window's central half: water, flat cloud); ``status`` (:data:`.collect.STATUS`; only 0 is a match) and
    ``outlier``. ``df.attrs``: ``windows`` (counts by status), ``scale`` (reference px per image px), ``region``
    (the box matched).
    """
    return match_raw_bands(image, model, reference_image, reference_model, dem, bands=[band], spacing_px=spacing_px,
                           window_px=window_px, search_px=search_px, reference_band=reference_band, region=region,
                           executor=executor, workers=workers, progress=progress, tile_windows=tile_windows,
                           outlier_model=outlier_model, outlier_threshold_px=outlier_threshold_px, seed=seed,
                           margin_px=margin_px, min_sigma_px=min_sigma_px, **params)[band]


def match_raw_bands(image, model, reference_image, reference_model, dem, *, bands: Sequence[int],
                    spacing_px: Union[int, Sequence[int]] = 64, window_px: int = 32, search_px: float = 8,
                    reference_band: int = 1, region: Optional[Sequence[float]] = None, executor=None,
                    workers: Optional[int] = None, progress=None, tile_windows: int = 256,
                    outlier_model: Optional[str] = "affine", outlier_threshold_px: float = 3.0, seed: int = 0,
                    margin_px: Optional[int] = None, min_sigma_px: float = MIN_SIGMA_PX, **params) -> Dict[int, Any]:
    """:func:`match_raw` of several bands of ``image`` against one reference band: ``{band: table}``, each table
    the one :func:`match_raw` gives for that band (``spacing_px``: one step, or one per band).

    The tiles of every band go into one queue of the pool (:func:`.collect.run_tiles`): the threads never wait at
    the end of a band for its last tile, and the overlap with the reference is found once. The tiles of every band
    at the same windows are one unit of the queue (:func:`.collect.match_tiles`: their ground points, footprints
    and resampled reference once) when there are at least two such units per thread. Tiles are fixed by each band's window grid,
    never by the threads: the same numbers as band after band, whatever the threads.
    """
    bands = [int(b) for b in bands]
    path = _image_info(image, bands[0])[0]
    for b in bands[1:]:
        _image_info(path, b)                                  # refused here when the image has no such band
    steps = [int(spacing_px)] * len(bands) if np.ndim(spacing_px) == 0 else [int(v) for v in spacing_px]
    ref_path = os.fspath(reference_image)
    if not os.path.exists(ref_path) and not ref_path.startswith("/vsi"):
        raise Gf4calError(f"reference image not found: {ref_path}")
    model = _model_or_rpc(model, path, "image")
    reference_model = _model_or_rpc(reference_model, ref_path, "reference image")
    box, scale = overlap_region(path, model, ref_path, reference_model, dem, band=bands[0],
                                reference_band=reference_band, step_px=max(16, min(int(window_px), 64)))
    box = _within_region(box, region, path, ref_path)
    plans = [plan_tiles(path, model, ref_path, dem, step, window_px, search_px=search_px, tile_windows=tile_windows,
                        band=b, reference_band=reference_band, reference_model=reference_model, region=box,
                        margin_px=margin_px, **params) for b, step in zip(bands, steps)]
    specs = [spec for band_specs, _ in plans for spec in band_specs]
    report(progress, 0.0, f"matching {sum(ctx['n_windows'] for _, ctx in plans)} windows in {len(specs)} tiles")
    groups = _same_windows(specs)
    if executor is None and len(groups) < 2 * threads.pool_workers(workers, len(specs)):
        # too few groups to keep the threads busy (a small crop): every tile its own unit (the same bits)
        groups = [_TileGroup([sp], [i]) for i, sp in enumerate(specs)]
    # the largest units first (a grid's edge tiles are smaller): the threads end together; each unit's results go
    # to its tiles' places, so the order changes no number
    groups.sort(key=lambda g: -len(g) * len(g[0].centers))
    done = run_tiles(groups, executor, workers=workers, progress=progress, stop=0.97, fn=_match_tiles_serial)
    results = [None] * len(specs)
    for group, res in zip(groups, done):
        for i, r in zip(group.index, res):
            results[i] = r
    tables, k = {}, 0
    for b, step, (band_specs, _) in zip(bands, steps, plans):
        t = _raw_table(results[k:k + len(band_specs)], outlier_model, outlier_threshold_px, seed, min_sigma_px)
        k += len(band_specs)
        t.attrs.update(scale=scale, region=tuple(box), image=path, reference=ref_path, window_px=int(window_px),
                       spacing_px=step)
        tables[b] = t
    counts = [t.attrs["windows"] for t in tables.values()]
    report(progress, 1.0, f"{sum(c['accepted'] for c in counts)} matches of {sum(c['total'] for c in counts)} windows "
           f"({sum(c['outliers'] for c in counts)} outliers)")
    return tables


class _TileGroup(tuple):
    """Tiles of one image at the same window centres, one per band (``index``: their places in the list of
    tiles): the unit of work of :func:`match_raw_bands`."""

    def __new__(cls, specs, index):
        obj = super().__new__(cls, specs)
        obj.index = tuple(index)
        return obj

    def __reduce__(self):
        return _TileGroup, (tuple(self), self.index)


def _same_windows(specs: Sequence[TileSpec]):
    """The tiles grouped by their windows (centres and everything but the band), in the order of their first."""
    keys: Dict[Any, list] = {}
    for i, sp in enumerate(specs):
        key = (np.asarray(sp.centers, float).tobytes(), sp.image, sp.window_px, sp.factor,
               tuple(sorted(sp.params.items())), sp.dem, sp.reference, sp.reference_band, id(sp.rpc),
               id(sp.reference_model))
        keys.setdefault(key, []).append(i)
    return [_TileGroup([specs[i] for i in idx], idx) for idx in keys.values()]


def _raw_table(results, outlier_model: Optional[str], outlier_threshold_px: float, seed: int, min_sigma_px: float):
    """The tiles' results of one band as :func:`match_raw`'s table (row-major; outliers flagged; counts in
    ``attrs['windows']``)."""
    r = {k: np.concatenate([np.atleast_1d(t[k]) for t in results]) for k in results[0]}
    order = np.lexsort((r["center_sample"], r["center_line"]))
    r = {k: v[order] for k, v in r.items()}
    st = r["status"].astype(np.int8)
    acc = st == 0
    outlier = _outliers(r, acc, outlier_model, outlier_threshold_px, seed)
    d_s = np.where(acc, r["dsample"], np.nan)
    d_l = np.where(acc, r["dline"], np.nan)
    prec = np.where(acc, np.maximum(np.nan_to_num(r["precision_px"], nan=np.inf), min_sigma_px), np.nan)
    df = pd.DataFrame({
        "sample": r["center_sample"] + d_s, "line": r["center_line"] + d_l,
        "pred_sample": r["center_sample"], "pred_line": r["center_line"],
        "ref_sample": r["ref_sample"], "ref_line": r["ref_line"],
        "lon": r["lon"], "lat": r["lat"], "h": r["h"], "d_sample": d_s, "d_line": d_l,
        "sigma": prec, "score": r["ncc"], "peak": r["peak"], "peak_ratio": r["peak_ratio"], "ncc": r["ncc"],
        "texture": r["texture"], "flat": r["flat"], "status": st, "outlier": outlier})
    counts = {name: int(np.count_nonzero(st == code)) for code, name in STATUS.items()}
    counts["outliers"] = int(outlier.sum())
    counts["total"] = int(st.size)
    df.attrs.update(windows=counts)
    return df


def _within_region(box, region, path: str, ref_path: str):
    """The overlap ``box`` cut to ``region`` (if given); refused when they do not meet."""
    if region is None:
        return box
    r = [float(v) for v in region]
    box = (max(box[0], r[0]), max(box[1], r[1]), min(box[2], r[2]), min(box[3], r[3]))
    if box[2] <= box[0] or box[3] <= box[1]:
        raise Gf4calError(f"region {tuple(region)} of {os.path.basename(path)} is outside its overlap with "
                          f"{os.path.basename(ref_path)}; give a region inside the overlap")
    return box


def _outliers(r, acc, outlier_model: Optional[str], threshold_px: float, seed: int) -> np.ndarray:
    """Outlier flags of the accepted offsets (RANSAC + MAD, :func:`.filters.reject_outliers`; with >= 8 of them)."""
    outlier = np.zeros(acc.size, dtype=bool)
    if outlier_model is not None and acc.sum() >= 8:
        flt = reject_outliers(r["center_sample"][acc], r["center_line"][acc], r["dsample"][acc], r["dline"][acc],
                              model=outlier_model, threshold_px=threshold_px, seed=seed)
        outlier[np.flatnonzero(acc)] = flt.outlier
    return outlier


def match_ties(image_a, model_a, image_b, model_b, dem, *, ids: Tuple[str, str] = ("a", "b"), spacing_px: int = 64,
               window_px: int = 32, search_px: float = 16, band_a: int = 1, band_b: int = 1, region=None,
               executor=None, workers: Optional[int] = None, progress=None, **params):
    """Tie points between two raw images in their overlap (METHODS §8), as a long observation table.

    :func:`match_raw` of ``image_a`` against ``image_b`` (restricted to their overlap automatically; windows are
    laid out over ``image_a``); every accepted, consistent window gives two rows with one ``point_id``:
    ``image_id = ids[0]`` at the measured position in ``a`` and ``ids[1]`` at the homologous position in ``b``
    (GDAL convention), ``kind='tie'``, ``role='control'``, ``sigma`` = the matcher's precision of the offset split
    evenly between the two images (``sigma / sqrt(2)``, in each image's pixels), ``lon, lat, h`` approximate (the
    ground point of the window centre through ``model_a`` on the DEM). Also ``score`` and ``status``.
    ``search_px`` (default 16: seams of a few pixels between CCDs, band offsets) sets the coarse level.
    Raises :class:`Gf4calError` when the images do not overlap or no window in the overlap matches.
    """
    t = match_raw(image_a, model_a, image_b, model_b, dem, spacing_px=spacing_px, window_px=window_px,
                  search_px=search_px, band=band_a, reference_band=band_b, region=region, executor=executor,
                  workers=workers, progress=progress, **params)
    ok = (t["status"].to_numpy() == 0) & ~t["outlier"].to_numpy()
    if not ok.any():
        w = t.attrs["windows"]
        raise Gf4calError(f"no tie point between {ids[0]} and {ids[1]} ({w['total']} windows in the overlap: "
                          + ", ".join(f"{v} {k}" for k, v in w.items() if v and k != "total")
                          + "); check the images overlap with texture, or use a larger --search/--window")
    g = t[ok]
    n = len(g)
    pid = np.array([f"{ids[0]}~{ids[1]}~{k + 1:05d}" for k in range(n)], dtype=object)
    sig = g["sigma"].to_numpy() / math.sqrt(2.0)
    scale = float(t.attrs.get("scale", 1.0))
    common = dict(kind="tie", role="control", lon=g["lon"].to_numpy(), lat=g["lat"].to_numpy(),
                  h=g["h"].to_numpy(), score=g["score"].to_numpy(), status=g["status"].to_numpy())
    a = pd.DataFrame(dict(point_id=pid, image_id=ids[0], sample=g["sample"].to_numpy(), line=g["line"].to_numpy(),
                          sigma=sig, **common))
    b = pd.DataFrame(dict(point_id=pid, image_id=ids[1], sample=g["ref_sample"].to_numpy(),
                          line=g["ref_line"].to_numpy(), sigma=sig * scale, **common))
    out = pd.concat([a, b], ignore_index=True)
    # Rows of one point together: a, b, a, b, ...
    out = out.iloc[np.argsort(np.r_[np.arange(n) * 2, np.arange(n) * 2 + 1], kind="stable")].reset_index(drop=True)
    cols = ["point_id", "image_id", "kind", "sample", "line", "sigma", "role", "lon", "lat", "h", "score", "status"]
    out = out[cols]
    out.attrs.update(windows=t.attrs["windows"], scale=scale, region=t.attrs["region"])
    return out


def cell_edges(width: int, cell_px: int, breaks: Optional[Sequence[float]] = None) -> np.ndarray:
    """Column edges of the cell grid over ``width`` image columns: every ``cell_px`` from 0, restarted at each
    sub-CCD edge of ``breaks`` (so that no cell straddles a jump, METHODS §9); a piece's last cell narrower than
    half a cell joins the one before it."""
    ends = [0.0] + sorted(float(b) for b in (breaks or ()) if 0.0 < float(b) < float(width)) + [float(width)]
    edges = []
    for a, b in zip(ends[:-1], ends[1:]):
        e = list(np.arange(a, b, float(cell_px)))
        if len(e) > 1 and b - e[-1] < 0.5 * cell_px:
            e.pop()
        edges.extend(e)
    return np.asarray(edges + [float(width)], float)


def cells_from_matches(matches, width: int, height: int, *, cell_px: int = 64, min_matches: int = 4,
                       min_accepted_fraction: float = 0.5, trim_k: float = 3.0, independent_fraction: float = 1.0,
                       breaks: Optional[Sequence[float]] = None, window_px: Optional[int] = None):
    """Robust per-cell means of window offsets on a regular grid (METHODS §9 observations).

    ``matches``: :func:`match_raw`'s table. Cell ``(col, row)`` covers image pixels ``[col * cell_px, (col + 1) *
    cell_px) x [row * cell_px, ...)`` (the last ones clipped to the image); a window belongs to the cell holding
    its centre (``pred_sample, pred_line``); with ``breaks`` the columns restart at each edge (:func:`cell_edges`).
    Windows ``outside_image`` do not count. Per cell and axis the mean is
    the **MAD-trimmed mean about the median** (:func:`gdal_gf4cal.stats.grouped_trimmed_mean`: accepted, non-outlier
    matches within ``trim_k`` robust standard deviations of the median on both axes), ``sigma_*`` its standard
    error (spread of the kept matches over sqrt(n); a lone match: its own ``sigma``), where overlapping
    windows count as ``n * independent_fraction`` independent ones (:func:`pan_ms_cells` gives ``(spacing /
    window)^2``: windows sharing pixels share their noise). ``breaks``: image columns where the offset field jumps
    (sub-CCD edges, METHODS §9); windows whose footprint (``window_px``, default ``matches.attrs['window_px']``)
    straddles one mix both sides and are left out of every count.
    ``clear_fraction`` = 1 - the mean ``flat`` share of the central halves of the cell's windows (which about
    tile the cell): the share of the cell that is neither cloud nor water nor texture-less. ``usable`` is False
    when fewer than ``min_matches`` are kept, the accepted share of the cell's windows is below
    ``min_accepted_fraction`` or ``clear_fraction`` is below 0.5 (a cell mostly cloud / water / texture-less).
    """
    cell = int(cell_px)
    if cell < 1:
        raise Gf4calError(f"cell size must be a positive number of pixels (got {cell_px})")
    xe = cell_edges(width, cell, breaks)
    ncol, nrow = xe.size - 1, -(-int(height) // cell)
    ncell = ncol * nrow
    if breaks is not None and len(breaks):
        w = float(window_px if window_px is not None else matches.attrs.get("window_px", 0))
        ps = matches["pred_sample"].to_numpy(float)
        straddle = np.any(np.abs(ps[:, None] - np.asarray(breaks, dtype=float)[None, :]) < w / 2.0, axis=1)
        matches = matches[~straddle]
    st = matches["status"].to_numpy()
    ps, pl = matches["pred_sample"].to_numpy(float), matches["pred_line"].to_numpy(float)
    col = np.clip(np.searchsorted(xe, ps, side="right") - 1, 0, ncol - 1)
    row = np.clip(np.floor(pl / cell).astype(int), 0, nrow - 1)
    cid = row * ncol + col
    counted = st != 5
    n_windows = np.bincount(cid[counted], minlength=ncell)
    n_acc = np.bincount(cid[st == 0], minlength=ncell)
    flat = matches["flat"].to_numpy(float)
    has_flat = counted & np.isfinite(flat)
    n_flat = np.bincount(cid[has_flat], minlength=ncell)
    sum_flat = np.bincount(cid[has_flat], flat[has_flat], minlength=ncell)
    good = (st == 0) & ~matches["outlier"].to_numpy(bool)
    m = grouped_trimmed_mean(cid[good], np.column_stack([matches["d_sample"].to_numpy(float)[good],
                                                         matches["d_line"].to_numpy(float)[good]]), ncell, k=trim_k)
    sig_s, sig_l = m.sigma[:, 0], m.sigma[:, 1]
    if independent_fraction < 1.0:
        n_eff = np.maximum(m.n * float(independent_fraction), 1.0)
        sig_s, sig_l = sig_s * np.sqrt(m.n / n_eff), sig_l * np.sqrt(m.n / n_eff)
    # A single match: its own precision estimate.
    one = np.bincount(cid[good], np.nan_to_num(matches["sigma"].to_numpy(float)[good]), minlength=ncell)
    sig_s = np.where(m.n == 1, one, sig_s)
    sig_l = np.where(m.n == 1, one, sig_l)
    with np.errstate(invalid="ignore", divide="ignore"):
        acc_frac = np.where(n_windows > 0, n_acc / np.maximum(n_windows, 1), 0.0)
        clear = np.where(n_flat > 0, 1.0 - sum_flat / np.maximum(n_flat, 1), 0.0)
    cc, rr = np.meshgrid(np.arange(ncol), np.arange(nrow))
    cc, rr = cc.ravel(), rr.ravel()
    y0 = rr * cell
    sample = (xe[cc] + xe[cc + 1]) / 2.0
    line = (y0 + np.minimum(y0 + cell, height)) / 2.0
    usable = (m.n >= int(min_matches)) & (acc_frac >= float(min_accepted_fraction)) & (clear >= 0.5)
    df = pd.DataFrame({"cell_id": np.arange(ncell), "col": cc, "row": rr, "sample": sample, "line": line,
                       "d_sample": m.mean[:, 0], "d_line": m.mean[:, 1], "sigma_sample": sig_s,
                       "sigma_line": sig_l, "n": m.n, "n_windows": n_windows,
                       "accepted_fraction": acc_frac, "clear_fraction": clear, "usable": usable})
    return df


def pan_ms_cells(pan, ms, dem, *, pan_model=None, ms_model=None, cell_px: int = 64, window_px: int = 32,
                 spacing_px: int = 16, search_px: float = 8, band: int = 1, pan_band: int = 1, min_matches: int = 4,
                 region=None, executor=None, workers: Optional[int] = None, progress=None, margin_px: int = 4,
                 breaks: Optional[Sequence[float]] = None, **params):
    """Pan-to-MS misregistration per cell of a regular MS grid (METHODS §9 observations, eq. 13).

    Dense :func:`match_raw` of the MS (band ``band``) against the pan (``pan_band``) through their models (default:
    the images' RPCs) and the DEM: windows of ``window_px`` MS px every ``spacing_px`` (several per cell; their
    centres from ``margin_px + window_px / 2`` of the edges, so edge cells are measured too); each
    gives ``∇ = p' - p''`` (MS px). :func:`cells_from_matches` averages them per ``cell_px`` cell (median +
    MAD-trimmed mean; ``breaks``: MS columns of sub-CCD edges, windows straddling one are left out). Returns a
    DataFrame (:data:`CELL_COLUMNS`): ``sample, line`` cell centre (MS px, GDAL),
    ``d_sample, d_line`` the cell's ∇, ``sigma_sample, sigma_line`` its precision, ``n`` accepted matches,
    ``n_windows``, ``usable`` (False for cells mostly cloud / water / texture-less: fewer than ``min_matches``
    matches or an accepted share < 0.5), ``clear_fraction``; ``attrs['matches']`` holds the window table.
    Memory is bounded by tiles (:func:`.collect.plan_tiles`), work runs on ``executor`` (gdal_gf4cal.executors).
    """
    t = match_raw(ms, ms_model, pan, pan_model, dem, spacing_px=spacing_px, window_px=window_px,
                  search_px=search_px, band=band, reference_band=pan_band, region=region, executor=executor,
                  workers=workers, progress=progress, margin_px=margin_px, **params)
    _, W, H, _ = _image_info(ms, band)
    cells = cells_from_matches(t, W, H, cell_px=cell_px, min_matches=min_matches,
                               independent_fraction=min(1.0, (float(spacing_px) / float(window_px)) ** 2),
                               breaks=breaks)
    cells.attrs.update(matches=t, windows=t.attrs["windows"], scale=t.attrs["scale"], cell_px=int(cell_px))
    return cells
