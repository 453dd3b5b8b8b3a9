"""``gf4cal register-pan-ms`` / QGIS "Register MS to pan": the file job of METHODS §9 (seed 004, Gaofen-7).

Each image's RPC (:func:`gdal_gf4cal.crop.image_rpc`: own, given, or a ``.geom`` beside it; crops shifted) ->
:func:`pair_geometry` (ratio, overlap, line-of-sight angle from the RPCs) -> dense window matches of every MS band
against the pan (``matching.raw.match_raw_bands``: all bands' tiles in one queue of the pool) -> sub-CCD edges
(options, or ``panms.detect_breaks``) -> cells of a size from the data (:func:`choose_cell`) ->
:func:`gdal_gf4cal.panms.estimate` on the reference band, every other band compared with it (:func:`_every_band`)
-> every output under one :class:`~gdal_gf4cal.outputs.OutputSet` (all or nothing).
"""
from __future__ import annotations

import copy
import functools
import math
import os
import time
from dataclasses import dataclass, field
from typing import Any, Dict, Optional, Tuple

import numpy as np
import pandas as pd
from osgeo import gdal
from scipy import stats

from .. import panms, threads
from .. import progress as _progress
from .._gdal import open_raster
from ..crop import crop_origin, image_rpc, sidecar_rpc
from ..dem import DEM
from ..errors import Gf4calError
from ..estimation import weighted_lsq
from ..geodesy import metres_per_degree
from ..matching import cells_from_matches, pan_ms_cells
from ..matching.raw import cell_edges, match_raw_bands, thread_dem
from ..outputs import OutputSet, check_raster, check_vector
from ..panms import LINEAR_ORDER, PanMSError, linear_design, residual_spectrum, row_means, step_residuals
from ..report import write_report_json, write_residuals_gpkg
from ..report.plot import plot_line_profiles, plot_spectrum, plot_step_residual_maps
from ..rpc_io import write_rpb
from ..stats import axis_stats, share_within
from ._common import cancel_check, collect_warnings, finish_report

#: Output file names in ``out``.
OUTPUT_NAMES = {"correction": "correction.tif", "ms_on_pan": "ms_on_pan.tif", "model": "model.json",
                "ms_rpc": "ms_approx.RPB", "report": "report.json", "cells": "cells.gpkg",
                "residual_maps": "residual_maps.png", "line_profile": "residual_along_line.png",
                "spectrum": "spectrum.png"}
#: Reuse mode: at most this many sparse matches (one window per cell, METHODS §9 eq. 17).
REUSE_MAX_MATCHES = 200


def _size(path):
    ds = open_raster(os.fspath(path), what="image")
    return (ds.RasterXSize, ds.RasterYSize), ds.RasterCount


def _parse_breaks(breaks) -> Optional[list]:
    """``--breaks``: MS columns and/or the words ``ms`` (the MS band's equal sub-CCD edges) and ``pan`` (the pan's
    equal sub-CCD edges mapped into the MS through the RPCs and the DEM), e.g. ``2560,5120`` or ``ms,pan``."""
    if breaks is None:
        return None
    items = list(breaks) if isinstance(breaks, (list, tuple)) else [b for b in str(breaks).split(",") if b.strip()]
    out: list = []
    for b in items:
        word = str(b).strip().lower()
        if word in ("ms", "pan"):
            out.append(word)
            continue
        try:
            out.append(float(b))
        except ValueError:
            raise PanMSError(f"--breaks {breaks!r}: give MS columns and/or the words ms, pan separated by commas, "
                             "e.g. 2560,5120 or ms,pan") from None
    return out


#: Matching windows (MS px) and the cell sizes tried when ``cell`` is not given, largest first.
WINDOW_PX = 32
#: Matching windows per tile (a unit of the thread pool). Larger tiles, fewer and longer NumPy calls: fewer GIL
#: hand-offs between the threads. Issue 23, AVX-512 2-core VM: 1024 against 384 on the 4096-px GF7 crop, 1 thread
#: 7.8-8.2 -> 6.4-6.9 s, 2 threads 5.7-6.0 -> 4.3-4.8 s, context switches 34,000 -> 18,500 (2048: no fewer);
#: the full GF7 scene 82-88 -> 72 s at 2 threads (2 threads / 1: 1.62x), the correction against the truth
#: 0.013 / 0.017 px RMS either way; the 1024-px crop unchanged (its few tiles). It changes which windows pass near a
#: crop's edges (a tile's ground points, footprints and resampled reference are computed per tile), so the numbers
#: differ from 384's a little (the 4096-px crop: 0.021 / 0.016 -> 0.017 / 0.013 px RMS, no spurious sub-CCD edge).
TILE_WINDOWS = 1024
AUTO_CELLS = (64, 48, 32, 24, 16, 12, 8, 6, 4)
#: A cell size is enough when every sub-CCD piece has usable cells in this many columns (a quartic and its check)
#: and the image in this many rows.
MIN_CELL_COLUMNS = 8
MIN_CELL_ROWS = 6
#: Windows matched per band at most (the spacing grows with the MS size up to 16 px).
TARGET_WINDOWS = 20000
#: A band whose matches correlate with the pan below this (median NCC) does not resemble the pan: what remains of
#: it is spectral, not geometric.
SPECTRAL_NCC = 0.75
#: Band-to-band: a band's own linear correction is applied when it differs from the reference band's with this
#: false-alarm probability and by more than this many MS px somewhere in the image.
BAND_FAP = 1e-3
BAND_MIN_PX = 0.02
#: Share of the clear, textured windows that must match for the pan and MS to show the same ground.
MIN_MATCH_SHARE = 0.1
#: Same acquisition: the pan's and the MS's lines of sight are within this angle (GF7 0.094 deg, Pleiades less).
MAX_RAY_ANGLE_DEG = 2.0


def pair_geometry(pan_rpc, ms_rpc, pan_size, ms_size, dem, n: int = 9) -> Dict[str, float]:
    """How the pan and MS relate through their RPCs and the DEM: ``overlap`` (share of an ``n x n`` MS grid the
    pan sees), ``scale`` (pan px per MS px, the square root of the MS-to-pan Jacobian's determinant, median over
    the overlap) and ``ray_angle_deg`` (angle between the pan's and the MS's lines of sight: moving 500 m down the
    pan's ray moves the MS point by the parallax; < 0.5 deg for one acquisition). Refuses images that hardly
    overlap or see the ground from other directions (other acquisitions)."""
    W, H = ms_size
    s, l = np.meshgrid((np.arange(n) + 0.5) * W / n, (np.arange(n) + 0.5) * H / n)
    s, l = s.ravel(), l.ravel()
    with np.errstate(all="ignore"):
        lon, lat, h = ms_rpc.localize_dem(s, l, dem)
        ps, pl = (np.asarray(v, float) for v in pan_rpc.project(lon, lat, h))
        inside = np.isfinite(ps) & np.isfinite(pl) & (ps >= 0) & (ps <= pan_size[0]) & (pl >= 0) & (pl <= pan_size[1])
        share = float(np.mean(inside))
        if share == 0.0 or not inside.any():
            ok = np.isfinite(ps) & np.isfinite(pl)
        else:
            ok = inside
        if not ok.any():
            raise PanMSError("the pan and MS images do not overlap through their RPCs and the DEM: give the pan and "
                             "MS images of the same scene")
        d = 0.5
        lo1, la1, h1 = ms_rpc.localize_dem(s[ok] + d, l[ok], dem)
        lo2, la2, h2 = ms_rpc.localize_dem(s[ok], l[ok] + d, dem)
        s1, l1 = pan_rpc.project(lo1, la1, h1)
        s2, l2 = pan_rpc.project(lo2, la2, h2)
        det = np.abs((np.asarray(s1) - ps[ok]) * (np.asarray(l2) - pl[ok])
                     - (np.asarray(s2) - ps[ok]) * (np.asarray(l1) - pl[ok])) / (d * d)
        scale = float(np.sqrt(np.nanmedian(det)))
        # parallax: two points on the pan's ray, 500 m apart in height, seen by the MS
        k = int(np.flatnonzero(ok)[np.argmin(np.abs(np.flatnonzero(ok) - s.size // 2))])
        dh = 500.0
        hs = np.array([h[k], h[k] + dh])
        glon, glat = pan_rpc.localize(np.full(2, ps[k]), np.full(2, pl[k]), hs)
        ms_s, ms_l = ms_rpc.project(glon, glat, hs)
        par_px = float(np.hypot(np.diff(ms_s), np.diff(ms_l))[0])
        # MS pixel size on the ground (m)
        glon2, glat2 = ms_rpc.localize(np.array([s[k], s[k] + 1.0]), np.array([l[k], l[k]]), np.full(2, h[k]))
        mx, my = metres_per_degree(glat2[0])
        gsd = float(np.hypot((glon2[1] - glon2[0]) * mx, (glat2[1] - glat2[0]) * my))
    angle = float(np.degrees(np.arctan2(par_px * gsd, dh)))
    if not np.isfinite(scale) or scale <= 0:
        raise PanMSError("cannot relate the pan's and the MS's pixels through their RPCs and the DEM: check the RPCs")
    if share < 0.25:
        raise PanMSError(f"the pan and MS images hardly overlap ({100 * share:.0f} % of the MS seen by the pan "
                         "through their RPCs): give the pan and MS images of the same scene")
    if scale < 1.0 / 1.5:
        raise PanMSError(f"the first image has pixels {1 / scale:.2f} times coarser than the second's (through their "
                         "RPCs): the inputs are swapped; give the pan (the finer image) first, then the MS")
    if scale < 1.5:
        raise PanMSError(f"the two images have the same pixel size through their RPCs (ratio {scale:.2f}): give a "
                         "pan and the MS image of the same acquisition, the pan first")
    if np.isfinite(angle) and angle > MAX_RAY_ANGLE_DEG:
        raise PanMSError(f"the pan and MS see the ground from directions {angle:.1f} deg apart (one acquisition: "
                         f"< {MAX_RAY_ANGLE_DEG:g} deg): they are images of different acquisitions; give the MS taken "
                         "with this pan")
    return {"overlap": share, "scale": scale, "ray_angle_deg": angle, "ms_gsd_m": gsd}


def _product_breaks(spec, n_sub_ccds, ms_rpc, ms_size, origin, pan_rpc, dem, pan_size):
    """``--breaks`` / ``--sub-ccds`` in this image's columns: equal pieces and listed columns are of the full
    product when the crop's place in it is known (``origin``), else of the image as given."""
    x0 = origin[0] if origin else 0.0
    width = float(ms_rpc.image_size[0]) + x0 if origin else float(ms_size[0])
    width = max(width, float(ms_size[0]))
    if spec is None:
        spec = ["ms"]
    n = 3 if n_sub_ccds is None else int(n_sub_ccds)
    if ("ms" in spec or "pan" in spec) and width / n < WINDOW_PX:
        raise panms.PanMSError(f"{n} sub-CCDs make pieces {width / n:.1f} MS px wide (the product is {width:.0f} px "
                               f"wide), narrower than one {WINDOW_PX} px matching window: such pieces cannot be "
                               "measured; give the number of sub-CCDs of the camera (GF7: 3) or their --breaks")
    cols = [float(b) - x0 for b in spec if not isinstance(b, str)]
    if "ms" in spec:
        cols += [b - x0 for b in panms.default_breaks(width, n)]
    if "pan" in spec:
        cols += panms.pan_edges_in_ms(pan_rpc, ms_rpc, dem, pan_size, n)
    return panms.merge_breaks(cols, width=ms_size[0], tol_px=1e-6 if not ({"ms", "pan"} & set(
        b for b in spec if isinstance(b, str))) else 1.0)


def _check_pieces(breaks, spec, ms_width, window_px) -> None:
    """Refuse sub-CCD pieces narrower than one matching window (they cannot be measured)."""
    if spec is not None:
        nums = [float(b) for b in spec if not isinstance(b, str)]
        dup = sorted({b for b in nums if nums.count(b) > 1})
        if dup:
            raise PanMSError(f"--breaks lists {', '.join(f'{b:g}' for b in dup)} more than once: give each sub-CCD "
                             "edge once")
    # between two edges (a piece cut by the image's side is only partly seen: its terms are dropped if need be)
    widths = np.diff(np.asarray(breaks, float))
    if widths.size and widths.min() < window_px:
        k = int(np.argmin(widths))
        raise PanMSError(f"a sub-CCD piece only {widths.min():.1f} MS px wide (between columns {breaks[k]:g} and "
                         f"{breaks[k + 1]:g}), narrower than one {window_px} px matching window: such pieces cannot "
                         "be measured; check --breaks / --sub-ccds (the sub-CCDs of the product, not of this crop)")


def _spacing(ms_size, cell=None) -> int:
    """Matching grid step (MS px): ~TARGET_WINDOWS windows per band, 4..16 px, at most the cell size."""
    sp = int(np.clip(round(math.sqrt(ms_size[0] * ms_size[1] / TARGET_WINDOWS)), 4, 16))
    return max(1, min(sp, int(cell))) if cell else sp


def _cells(matches, ms_size, cell, spacing, breaks):
    cells = cells_from_matches(matches, ms_size[0], ms_size[1], cell_px=int(cell),
                               min_matches=int(np.clip((cell / spacing) ** 2, 1, 4)),
                               independent_fraction=min(1.0, (float(spacing) / WINDOW_PX) ** 2), breaks=breaks)
    cells.attrs.update(matches=matches, windows=matches.attrs.get("windows"), cell_px=int(cell))
    return cells


def choose_cell(matches, ms_size, spacing, breaks):
    """The largest of :data:`AUTO_CELLS` (>= the matching step) whose usable cells fill every sub-CCD piece in
    >= MIN_CELL_COLUMNS columns and the image in >= MIN_CELL_ROWS rows; else the one with the most columns in its
    poorest piece. Returns ``(cell, cells)``. A size whose grid itself has too few columns in a piece or rows
    (:func:`_grid_can_fill`: a crop's large sizes) is measured only when no size passes."""
    sizes = [c for c in AUTO_CELLS if c >= spacing] or [spacing]
    tried = {}
    for cell in sizes:
        if not _grid_can_fill(ms_size, cell, breaks):
            continue
        cells, fill = tried[cell] = _cell_fill(matches, ms_size, cell, spacing, breaks)
        if fill[0] >= MIN_CELL_COLUMNS and fill[1] >= MIN_CELL_ROWS:
            return cell, cells
    best = None
    for cell in sizes:                  # none passes: the fullest of every size, in the same order
        cells, fill = tried[cell] if cell in tried else _cell_fill(matches, ms_size, cell, spacing, breaks)
        if best is None or fill > best[0]:
            best = (fill, cell, cells)
    return best[1], best[2]


def _cell_fill(matches, ms_size, cell, spacing, breaks):
    """The cells of size ``cell`` and ``(columns, rows)``: the usable cells' distinct columns in the poorest sub-CCD
    piece and distinct rows."""
    cells = _cells(matches, ms_size, cell, spacing, breaks)
    u = np.asarray(cells["usable"], bool)
    s = np.asarray(cells["sample"], float)[u]
    piece = np.searchsorted(np.asarray(breaks, float), s, side="right")
    cols = min(np.unique(s[piece == k]).size for k in range(len(breaks) + 1))
    rows = np.unique(np.asarray(cells["line"], float)[u]).size
    return cells, (cols, rows)


def _grid_can_fill(ms_size, cell, breaks) -> bool:
    """Whether the cell grid of size ``cell`` (:func:`~gdal_gf4cal.matching.raw.cell_edges`) has MIN_CELL_COLUMNS
    column centres in every sub-CCD piece and MIN_CELL_ROWS rows: its usable cells cannot do better."""
    xe = cell_edges(ms_size[0], int(cell), breaks)
    piece = np.searchsorted(np.asarray(breaks, float), (xe[:-1] + xe[1:]) / 2.0, side="right")
    cols = np.bincount(piece, minlength=len(breaks) + 1).min()
    return cols >= MIN_CELL_COLUMNS and -(-int(ms_size[1]) // int(cell)) >= MIN_CELL_ROWS


def _no_cell_message(matches, n_cells) -> str:
    """Why no cell is usable: clouds/water/texture-less, or images that do not show the same ground."""
    w = matches.attrs.get("windows", {})
    counted = max(1, w.get("total", 0) - w.get("outside_image", 0) - w.get("nodata", 0))
    textured = counted - w.get("featureless", 0)
    flat = float(np.nanmean(np.asarray(matches["flat"], float))) if len(matches) else 1.0
    if textured >= 0.5 * counted and flat < 0.5 or _unrelated(matches):
        return (f"the MS does not show what the pan shows: {w.get('accepted', 0)} of {textured} textured windows "
                "match the pan at the places the RPCs predict (the rest do not correlate): images of different "
                "acquisitions or footprints, or RPCs far off; give the MS taken with this pan")
    return (f"no usable cell: all {n_cells} cells are cloud, water or texture-less; register a clearer scene of the "
            "same camera and use --reuse MODEL.json")


def _screen(matches) -> None:
    """Flag the blunders among the accepted window matches in place (``outlier``; :func:`panms.screen_matches`:
    within each column, so that the smaller side of a sub-CCD jump is kept for the edge test)."""
    acc = matches["status"].to_numpy() == 0
    out = np.zeros(len(matches), bool)
    out[acc] = panms.screen_matches(matches["pred_sample"].to_numpy(float)[acc],
                                    matches["pred_line"].to_numpy(float)[acc], matches["d_sample"].to_numpy(float)[acc],
                                    matches["d_line"].to_numpy(float)[acc], spacing_px=matches.attrs["spacing_px"])
    matches["outlier"] = out
    matches.attrs["windows"]["outliers"] = int(out.sum())


def _unrelated(matches) -> bool:
    """True when the MS does not show what the pan shows: fewer than MIN_MATCH_SHARE of the windows with texture
    and no flat area (cloud, water) match."""
    st = matches["status"].to_numpy()
    flat = np.nan_to_num(matches["flat"].to_numpy(float), nan=1.0)
    clear = (st != 5) & (st != 1) & (st != 2) & (flat < 0.5)
    acc = (st == 0) & ~matches["outlier"].to_numpy(bool)
    return bool(clear.sum() >= 20 and acc[clear].mean() < MIN_MATCH_SHARE)


#: Pleiades and SPOT 6/7 spectral band ids (DIMAP ``BAND_ID``, OSSIM ``support_data.band_name_list``).
PRODUCT_BAND_IDS = {"B0": "blue", "B1": "green", "B2": "red", "B3": "nir"}


def _product_band_names(ms_path, rpc_path=None):
    """The product's band names in file order from its OSSIM ``.geom`` (``support_data.band_name_list``, e.g.
    ``"B2 B1 B0 B3"`` -> red, green, blue, nir), the one given or the one beside the image; ``[]`` when unknown."""
    geom = rpc_path if isinstance(rpc_path, (str, os.PathLike)) else sidecar_rpc(ms_path)
    if geom is None or not os.fspath(geom).lower().endswith(".geom"):
        return []
    with open(geom, encoding="utf-8", errors="replace") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key.strip() == "support_data.band_name_list":
                ids = value.replace('"', " ").split()
                return [PRODUCT_BAND_IDS.get(i.upper(), "") for i in ids]
    return []


def _band_names(ms_path, n_bands, rpc_path=None):
    """Per band ``(name, GDAL colour interpretation)`` from the product: band descriptions naming a colour, else
    the product's band list (:func:`_product_band_names`), else the file's colour interpretation (Alpha never: an
    MS band is a measurement, e.g. NIR -> Undefined)."""
    ds = open_raster(os.fspath(ms_path), what="MS image")
    words = {"red": gdal.GCI_RedBand, "green": gdal.GCI_GreenBand, "blue": gdal.GCI_BlueBand}
    product = _product_band_names(ms_path, rpc_path)
    out = []
    for b in range(1, n_bands + 1):
        band = ds.GetRasterBand(b)
        desc = (band.GetDescription() or "").strip()
        if not desc and len(product) == n_bands:
            desc = product[b - 1]
        ci = band.GetColorInterpretation()
        low = desc.lower()
        hit = [v for k, v in words.items() if k in low.split() or low == k or low.startswith(k)]
        if "nir" in low or "infrared" in low:
            ci = gdal.GCI_Undefined
        elif hit:
            ci = hit[0]
        elif ci in (gdal.GCI_AlphaBand, gdal.GCI_GrayIndex, gdal.GCI_PaletteIndex) and n_bands > 1:
            ci = gdal.GCI_Undefined
        if not desc:
            desc = gdal.GetColorInterpretationName(ci).lower() if ci not in (gdal.GCI_Undefined,) else f"band {b}"
        out.append((desc, ci))
    return out


def _band_to_band(ref_cells, cells, model):
    """The band's misregistration minus the reference band's, per cell usable in both: its linear fit (6
    parameters, as the model's linear term), whether it is significant (chi-square of the fit at BAND_FAP and
    > BAND_MIN_PX somewhere), the mean offset per axis."""
    u = np.asarray(ref_cells["usable"], bool) & np.asarray(cells["usable"], bool)
    d = np.stack([np.asarray(cells["d_sample"], float) - np.asarray(ref_cells["d_sample"], float),
                  np.asarray(cells["d_line"], float) - np.asarray(ref_cells["d_line"], float)], axis=1)[u]
    if u.sum() < 4:
        return None
    sig2 = np.stack([np.asarray(cells[f"sigma_{a}"], float) ** 2 + np.asarray(ref_cells[f"sigma_{a}"], float) ** 2
                     for a in ("sample", "line")], axis=1)[u]
    med = np.nanmedian(sig2) if np.isfinite(sig2).any() else 1e-4
    w = 1.0 / np.where(np.isfinite(sig2) & (sig2 > 0), np.maximum(sig2, 0.25 * med), med)
    sn, ln = model.normalise(np.asarray(cells["sample"], float)[u], np.asarray(cells["line"], float)[u])
    a = linear_design(sn, ln)
    est = weighted_lsq(a.reshape(-1, 6), d.ravel(), w.ravel(), hint=" (band-to-band)")
    lin = np.zeros(6)
    lin[LINEAR_ORDER] = est.x
    cov = est.cov
    try:
        chi2 = float(est.x @ np.linalg.solve(cov, est.x))
    except np.linalg.LinAlgError:
        chi2 = 0.0
    fap = float(stats.chi2.sf(chi2, 6))
    corners = np.abs(np.array([[lin[0] + lin[1] * x + lin[2] * y, lin[3] + lin[4] * x + lin[5] * y]
                               for x in (-1, 1) for y in (-1, 1)]))
    return {"linear": lin, "fap": fap, "max_px": float(corners.max()),
            "mean_sample_px": float(np.mean(d[:, 0])), "mean_line_px": float(np.mean(d[:, 1])),
            "n_cells": int(u.sum()), "significant": bool(fap < BAND_FAP and corners.max() > BAND_MIN_PX)}


def _check_options(pan, ms, breaks, n_sub_ccds, jitter, cell):
    """The options checked before anything is read: ``(breaks spec, jitter)``; :class:`PanMSError` naming the
    option."""
    if os.path.realpath(os.fspath(pan)) == os.path.realpath(os.fspath(ms)):
        raise panms.PanMSError("the same image was given as pan and as MS: give the pan first, then the MS image "
                               "of the same acquisition")
    spec = _parse_breaks(breaks)
    if n_sub_ccds is not None and spec is not None and not ({"ms", "pan"} & set(b for b in spec
                                                                               if isinstance(b, str))):
        raise panms.PanMSError("give either --sub-ccds or --breaks with MS columns, not both")
    if n_sub_ccds is not None and int(n_sub_ccds) < 1:
        raise panms.PanMSError(f"--sub-ccds must be at least 1 (got {n_sub_ccds})")
    if str(jitter) not in ("auto", "none"):
        try:
            jitter = int(jitter)
        except ValueError:
            raise panms.PanMSError(f"--jitter {jitter!r}: give auto, none or a number of components") from None
        if jitter < 0:
            raise panms.PanMSError("--jitter must be auto, none or a non-negative number")
    if cell is not None and int(cell) < 4:
        raise panms.PanMSError(f"--cell {cell}: cells must be at least 4 MS px")
    return spec, jitter


def _match_every_band(pan, ms, pan_model, ms_model, dem_obj, ms_size, n_bands, cell, user_breaks, notes,
                      workers, progress):
    """Dense window matches of every MS band against the pan, the reference band (the best correlated), the
    sub-CCD edges (``user_breaks``, else from the data, with a note) and the cells of every band:
    ``(band_matches, ref, n_matches, breaks, cell_px, cells of ref, {band: cells})``."""
    mw, mh = ms_size
    spacing = _spacing((mw, mh), cell)
    # a large image (step at its 16 px cap): the other bands at twice the step (their difference from the first
    # is smooth), a quarter of the windows; every band's tiles in one queue of the pool
    band_matches = match_raw_bands(ms, ms_model, pan, pan_model, dem_obj, bands=range(1, n_bands + 1),
                                   spacing_px=[spacing if b == 1 or spacing < 16 else 2 * spacing
                                               for b in range(1, n_bands + 1)],
                                   window_px=WINDOW_PX, search_px=8, reference_band=1, workers=workers, margin_px=4,
                                   tile_windows=TILE_WINDOWS,
                                   outlier_model=None, progress=_progress.scaled(progress, 0.02, 0.5))
    threads.run_tasks([functools.partial(_screen, t) for t in band_matches.values()])    # each band's in place
    # the reference band: the one whose matches correlate best with the pan
    nccs = {b: _median_ncc(t) for b, t in band_matches.items()}
    ref = max(nccs, key=lambda b: (nccs[b], -b))
    t = band_matches[ref]
    n_matches = len(t)
    acc = (t["status"].to_numpy() == 0) & ~t["outlier"].to_numpy(bool)
    if user_breaks is not None:
        breaks_ = user_breaks
    else:
        breaks_, jumps = panms.detect_breaks(t["pred_sample"][acc], t["pred_line"][acc], t["d_sample"][acc],
                                             t["d_line"][acc], width=mw, window_px=WINDOW_PX,
                                             spacing_px=t.attrs["spacing_px"])
        notes.append(("sub-CCD edges found in the data at MS columns " + ", ".join(
            f"{j['edge_ms_px']:.1f}" for j in jumps)) if jumps else
            "no jump in the per-column residual passes the test: one sub-CCD piece (give --breaks or "
            "--sub-ccds to set the edges)")
    if cell:
        cell_used = int(cell)
        cells = _cells(t, (mw, mh), cell_used, t.attrs["spacing_px"], breaks_)
    else:
        cell_used, cells = choose_cell(t, (mw, mh), t.attrs["spacing_px"], breaks_)
    others = [b for b in band_matches if b != ref]
    band_cells = dict(zip(others, threads.run_tasks([functools.partial(
        _cells, band_matches[b], (mw, mh), cell_used, band_matches[b].attrs["spacing_px"], breaks_) for b in others])))
    band_cells[ref] = cells
    band_cells = {b: band_cells[b] for b in band_matches}
    return band_matches, ref, n_matches, breaks_, cell_used, cells, band_cells


def _approximate_ms_rpc(model, ms_model):
    """``panms.approximate_rpc`` of the full model (its numerators refitted: the same design whatever the
    terms, so no smaller model to fall back to); :class:`PanMSError` when the grid does not determine it."""
    try:
        return panms.approximate_rpc(model, ms_model)
    except Gf4calError as exc:
        raise panms.PanMSError(f"the approximate MS RPC could not be fitted ({exc}); the other outputs "
                               "need it too: check the MS RPC") from None


@dataclass
class _Pair:
    """The opened pan and MS: sizes, band count, RPCs (:func:`gdal_gf4cal.crop.image_rpc`), DEM, their geometry
    (:func:`pair_geometry`) and the pixel ratio; ``ms_rpc`` as given (the product's band list)."""

    pan: Any
    ms: Any
    pan_size: Tuple[int, int]
    ms_size: Tuple[int, int]
    n_bands: int
    pan_model: Any
    ms_model: Any
    dem: Any
    geo: Dict[str, float]
    ratio: int
    ms_rpc: Any


def _open_pair(pan, ms, *, dem, geoid, pan_rpc, ms_rpc, notes) -> _Pair:
    """Read the sizes and RPCs, relate the two images through them and the DEM (refusing other acquisitions)."""
    pan_size, _ = _size(pan)
    ms_size, n_bands = _size(ms)
    pan_model, note_p = image_rpc(pan, pan_rpc)
    ms_model, note_m = image_rpc(ms, ms_rpc)
    notes += [n for n in (note_p, note_m) if n]
    dem_obj = thread_dem(DEM.from_user_input(dem, geoid=geoid))     # the matcher's, on this thread
    geo = pair_geometry(pan_model, ms_model, pan_size, ms_size, dem_obj)
    ratio = int(round(geo["scale"]))
    if abs(geo["scale"] - ratio) > 0.05 * ratio:
        notes.append(f"pan/MS pixel ratio {geo['scale']:.3f} through the RPCs: ms_on_pan.tif at 1/{ratio} of "
                     "the pan")
    return _Pair(pan, ms, pan_size, ms_size, n_bands, pan_model, ms_model, dem_obj, geo, ratio, ms_rpc)


@dataclass
class _Measured:
    """The cells the model is solved from (of the reference band ``ref``), the sub-CCD edges, the cell size, and
    per band the window matches and cells (every-band mode only)."""

    cells: Any
    breaks: list
    cell_px: Optional[int]
    ref: int = 1
    n_matches: int = 0
    band_matches: Dict[int, Any] = field(default_factory=dict)
    band_cells: Dict[int, Any] = field(default_factory=dict)


def _measure(pair: _Pair, *, user_breaks, reuse_model, cells, cell, notes, workers, progress) -> _Measured:
    """The cells: a table already measured (``cells``), sparse matches of the reused model's band (reuse mode:
    one window per cell, <= :data:`REUSE_MAX_MATCHES`), or dense matches of every band (:func:`_match_every_band`);
    refused when no cell is usable or the MS does not show what the pan shows."""
    mw, mh = pair.ms_size
    if cells is not None:
        meas = _Measured(cells.reset_index(drop=True), user_breaks or [], int(cell) if cell else None)
    elif reuse_model is not None:
        c = int(max(8, math.ceil(math.sqrt(mw * mh / REUSE_MAX_MATCHES))))
        ref = int(reuse_model.info.get("reference_band", 1))     # the band the reused model was solved on
        ref = ref if 1 <= ref <= pair.n_bands else 1
        cells = pan_ms_cells(pair.pan, pair.ms, pair.dem, pan_model=pair.pan_model, ms_model=pair.ms_model,
                             cell_px=c, spacing_px=c, min_matches=1, workers=workers,
                             progress=_progress.scaled(progress, 0.02, 0.5), band=ref)
        meas = _Measured(cells, list(reuse_model.breaks), c, ref, len(cells.attrs.get("matches", ())))
    else:
        band_matches, ref, n_matches, breaks_, cell_used, cells, band_cells = _match_every_band(
            pair.pan, pair.ms, pair.pan_model, pair.ms_model, pair.dem, pair.ms_size, pair.n_bands, cell,
            user_breaks, notes, workers, progress)
        meas = _Measured(cells, breaks_, cell_used, ref, n_matches, band_matches, band_cells)
    meas.cells = meas.cells.reset_index(drop=True)
    _check_cells(meas)
    return meas


def _check_cells(meas: _Measured) -> None:
    """:class:`PanMSError` when the MS does not show what the pan shows or no cell is usable (why, in words)."""
    cells, mt = meas.cells, meas.band_matches.get(meas.ref)
    if mt is not None and _unrelated(mt):
        raise PanMSError(_no_cell_message(mt, len(cells)))
    if len(cells) == 0 or not np.asarray(cells["usable"], bool).any():
        mt = mt if meas.band_matches else cells.attrs.get("matches")
        raise PanMSError(_no_cell_message(mt, len(cells)) if mt is not None else
                         f"no usable cell: all {len(cells)} cells are cloud, water or texture-less; register a "
                         "clearer scene of the same camera and use --reuse MODEL.json")


def _write_products(outs, pair: _Pair, meas: _Measured, model, band_models, bands, notes, clock, progress):
    """model.json, correction.tif (a pair of bands more per band with its own correction), ms_on_pan.tif, the
    approximate MS RPC, cells.gpkg and the plots into the OutputSet's temporary paths; the RPC refit's errors.

    The plots (matplotlib: they hold the GIL) are begun on the pool (:func:`gdal_gf4cal.threads.start`) and drawn
    while this thread writes the rest. Work that releases the GIL often waits for it beside them (a convoy): what
    hides behind the plots is put there (correction.tif, the RPC, cells.gpkg, and ms_on_pan.tif when it is one
    round of tiles); a larger ms_on_pan.tif is written first, on every thread (:func:`_ms_on_pan_first`)."""
    first = _ms_on_pan_first(pair)
    if first:
        _write_ms_on_pan(outs, pair, model, band_models, progress)
    joins = [threads.start(task) for task in _plot_tasks(meas.cells, model, outs)]
    try:
        if not first:
            _write_ms_on_pan(outs, pair, model, band_models, progress)
        approx_err = _write_rest(outs, pair, meas, model, band_models, bands, clock, progress)
    except BaseException:
        for join in joins:          # nothing left writing into the outputs being removed
            try:
                join()
            except BaseException:   # noqa: BLE001 - the first error is the one raised
                pass
        raise
    for join in reversed(joins):    # those no pool thread took yet run here, then the running ones are awaited
        join()
    clock.lap("rpc_cells_plots")
    return approx_err


def _ms_on_pan_first(pair: _Pair) -> bool:
    """Whether ms_on_pan.tif is written before the plots begin: when it has more tiles than one round of the pool
    (:func:`gdal_gf4cal.threads.rounds`). Beside the plots its tiles wait for the GIL: on a 4096-px GF7 pan crop
    at 2 threads (4 tiles) it took 0.50 s there, 0.35-0.40 s first; one round (the 1024-px bench crop, one tile)
    ends behind the plots, where first it would add its time to theirs."""
    (pw, ph), r = pair.pan_size, pair.ratio
    tiles = -(-pw // (r * panms.TILE_PX)) * -(-ph // (r * panms.TILE_PX))
    return tiles > threads.num_threads()


def _write_ms_on_pan(outs, pair: _Pair, model, band_models, progress) -> None:
    n_bands = pair.n_bands
    _progress.report(progress, 0.6, "pan-MS: writing ms_on_pan.tif")
    panms.resample_ms_on_pan([band_models.get(b, model) for b in range(1, n_bands + 1)], pair.pan, pair.ms,
                             outs.tmp("ms_on_pan"), pan_rpc=pair.pan_model, ms_rpc=pair.ms_model, dem=pair.dem,
                             ratio=pair.ratio, progress=_progress.scaled(progress, 0.6, 0.85),
                             band_names=_band_names(pair.ms, n_bands, pair.ms_rpc))
    outs.set_check("ms_on_pan", check_raster(n_bands))


def _write_rest(outs, pair: _Pair, meas: _Measured, model, band_models, bands, clock, progress):
    """Every output but ms_on_pan.tif and the plots (:func:`_write_products`); the RPC refit's errors."""
    _progress.report(progress, 0.85, "pan-MS: writing correction.tif")
    model.to_json(outs.tmp("model"))
    own = {b: m for b, m in band_models.items() if m is not model}
    panms.write_correction(model, outs.tmp("correction"), progress=_progress.scaled(progress, 0.85, 0.9),
                           rpc=pair.ms_model, band_models={f"band {b} ({bands[b - 1]['name']})": m
                                                           for b, m in own.items()})
    outs.set_check("correction", check_raster(2 + 2 * len(own)))
    clock.lap("correction_and_ms_on_pan")
    _progress.report(progress, 0.9, "pan-MS: refitting the MS RPC, cells and plots")
    approx_err = _write_ms_rpc(model, pair.ms_model, outs.tmp("ms_rpc"))
    n_cells = _write_cells(meas.cells, model, pair.ms_model, pair.dem, outs.tmp("cells"))
    outs.set_check("cells", check_vector({"gcps": n_cells}))
    return approx_err


def _write_ms_rpc(model, ms_model, path):
    """ms_approx.RPB (:func:`_approximate_ms_rpc`); its errors against the full model."""
    approx, approx_err = _approximate_ms_rpc(model, ms_model)
    write_rpb(approx, path, overwrite=True)
    return approx_err


def _report(inputs, pair: _Pair, meas: _Measured, model, bands, breaks_from: str, approx_err, clock, outs,
            notes) -> Dict[str, Any]:
    """report.json's content (before the warnings). ``n_usable``: the cells usable for the fit, the outliers among
    them included (model.json's ``info.n_usable``); ``n_outliers``: those of them the robust fit rejected
    (``info.n_outliers``; cells.gpkg's ``outlier``); the steps' statistics are over the rest."""
    (pw, ph), ratio = pair.pan_size, pair.ratio
    return {"command": "register-pan-ms", "inputs": inputs,
            "sizes": {"pan": [pw, ph], "ms": list(pair.ms_size), "ratio": ratio,
                      "ms_on_pan": [-(-pw // ratio), -(-ph // ratio)]},
            "geometry": pair.geo, "overlap_share": pair.geo["overlap"], "mode": model.mode,
            "breaks_ms_px": list(model.breaks), "breaks_from": breaks_from,
            "cell_px": meas.cell_px, "n_cells": int(len(meas.cells)), "n_matches": int(meas.n_matches),
            "timings_s": clock.laps, "n_usable": int(np.asarray(meas.cells["usable"], bool).sum()),
            "n_outliers": model.info.get("n_outliers", 0), "noise_floor_px": model.info.get("noise_floor_px"),
            "piece_orders": model.info.get("piece_orders"),
            "steps": model.steps, "jitter": model.jitter, "linear": model.to_dict()["linear"],
            "reference_band": meas.ref, "bands": bands,
            "ms_approx_rpc": approx_err, "outputs": outs.paths, "notes": notes}


def _inputs_entry(pan, ms, dem, geoid, reuse, pan_rpc, ms_rpc) -> Dict[str, Any]:
    return {"pan": os.fspath(pan), "ms": os.fspath(ms), "dem": _as_text(dem), "geoid": _as_text(geoid),
            "reuse": _as_text(reuse) if not isinstance(reuse, panms.PanMSModel) else "model",
            "pan_rpc": _as_text(pan_rpc) if not hasattr(pan_rpc, "project") else "model",
            "ms_rpc": _as_text(ms_rpc) if not hasattr(ms_rpc, "project") else "model"}


def _output_set(inputs, out: str, overwrite: bool, progress) -> OutputSet:
    """Every output under ``out``, declared with its check (all written together or none)."""
    outs = OutputSet(inputs, overwrite=overwrite, cancelled=cancel_check(progress))
    for key, name in OUTPUT_NAMES.items():
        check = {"correction": check_raster(2), "ms_on_pan": check_raster(), "cells": check_vector()}.get(key)
        outs.declare(key, os.path.join(out, name), check=check)
    return outs


def _path_or_none(x):
    return x if isinstance(x, (str, os.PathLike)) else None


def _user_breaks(pair: _Pair, spec, n_sub_ccds) -> Optional[list]:
    """The sub-CCD edges the options give (in this image's columns, checked), None when they give none."""
    if spec is None and n_sub_ccds is None:
        return None
    origin = crop_origin(pair.ms)        # the crop's place in the MS product, when the file states it
    br = _product_breaks(spec, n_sub_ccds, pair.ms_model, pair.ms_size, origin, pair.pan_model, pair.dem,
                         pair.pan_size)
    _check_pieces(br, spec, pair.ms_size[0], WINDOW_PX)
    return br


@threads.blas_serial()     # BLAS on the calling thread, as in the CLI and QGIS (threads.py)
def register_pan_ms(pan, ms, *, dem, out, geoid=None, n_sub_ccds: Optional[int] = None, breaks=None,
                    cell: Optional[int] = None, jitter="auto", reuse=None, overwrite: bool = False, cells=None,
                    workers: Optional[int] = None, progress=None, pan_rpc=None, ms_rpc=None) -> Dict[str, Any]:
    """Register an MS image to its pan (METHODS §9) and write, in ``out``: ``correction.tif`` (delta sample /
    delta line at every MS pixel centre, on the MS grid as given, with the MS RPC: GDAL and QGIS place it; a pair
    more per band whose own correction differs), ``ms_on_pan.tif`` (every MS band resampled onto the pan's raw
    grid at MS resolution over the pan's extent, for ``gdal_pansharpen.py PAN ms_on_pan.tif fused.tif``, band
    colours from the product), ``model.json`` (loadable with ``reuse``), ``ms_approx.RPB`` (refitted MS RPC, a
    smooth approximation; its error in the report), ``report.json`` (per step RMS per axis, P(<= 0.25 px),
    spectrum peaks, jitter; per band its residual field and its registration to the reference band), ``cells.gpkg``
    (cells with residuals before/after each step, styled arrows) and the plots.

    Inputs as they come: any pan and MS of one acquisition that overlap, cropped or not (``pan_rpc`` / ``ms_rpc``,
    or each image's own RPC, or a ``.geom`` named like it beside it; a crop stating its origin in the product gets
    the product's RPC shifted). The pixel ratio and the relative position come from the RPCs, not the sizes.

    ``n_sub_ccds`` / ``breaks`` (MS columns, a list or "S1,S2", and/or the words ``ms`` / ``pan``): the sub-CCD
    edges, counted on the full product when the crop's place in it is known; neither: edges found in the data
    (jumps of the per-column residual that pass a test), else one piece. ``cell``: cell size (MS px, >= 4;
    default from the MS size and texture: enough usable cells per piece for every term); ``jitter``: ``auto`` |
    ``none`` | N; ``reuse``: a ``model.json`` of another scene of the same camera: only the linear term is solved,
    from <= 200 sparse matches. ``cells``: a cell table already measured (skips the matching; one band). Returns
    the report dict.
    """
    spec, jitter = _check_options(pan, ms, breaks, n_sub_ccds, jitter, cell)
    outs = _output_set([pan, ms, _path_or_none(dem), geoid, _path_or_none(reuse), _path_or_none(pan_rpc),
                        _path_or_none(ms_rpc)], os.fspath(out), overwrite, progress)
    warns: list = []
    notes: list = []
    clock = _Clock()
    with outs, collect_warnings(warns):
        pair = _open_pair(pan, ms, dem=dem, geoid=geoid, pan_rpc=pan_rpc, ms_rpc=ms_rpc, notes=notes)
        user_breaks = _user_breaks(pair, spec, n_sub_ccds)
        reuse_model = None
        if reuse is not None:
            reuse_model = reuse if isinstance(reuse, panms.PanMSModel) else panms.PanMSModel.from_json(reuse)
            reuse_model.compatible_with(pair.ms_size, user_breaks)
        _progress.report(progress, 0.02, "pan-MS: matching")
        meas = _measure(pair, user_breaks=user_breaks, reuse_model=reuse_model, cells=cells, cell=cell, notes=notes,
                        workers=workers, progress=progress)
        clock.lap("matching")
        model = panms.estimate(meas.cells, ms_size=pair.ms_size, breaks=meas.breaks, jitter=jitter,
                               reuse=reuse_model, progress=_progress.scaled(progress, 0.5, 0.6))
        notes += list(model.info.get("notes", []))
        model.info.update(source={"pan": os.fspath(pan), "ms": os.fspath(ms)}, ratio=pair.ratio,
                          reference_band=meas.ref)
        bands, band_models = _every_band(meas.band_cells, meas.ref, model,
                                         _band_names(ms, pair.n_bands, ms_rpc), notes)
        clock.lap("estimate")
        approx_err = _write_products(outs, pair, meas, model, band_models, bands, notes, clock, progress)
        breaks_from = ("options" if user_breaks is not None else "reuse model" if reuse_model is not None
                       else "data")
        rep = _report(_inputs_entry(pan, ms, dem, geoid, reuse, pan_rpc, ms_rpc), pair, meas, model, bands,
                      breaks_from, approx_err, clock, outs, notes)
        finish_report(rep, warns)
        write_report_json(rep, outs.tmp("report"))
    finish_report(rep, warns)
    _progress.report(progress, 1.0, "done")
    return rep


def _median_ncc(t) -> float:
    acc = t["status"].to_numpy() == 0
    return float(np.median(t["ncc"].to_numpy(float)[acc])) if acc.any() else -1.0


def _every_band(band_cells, ref, model, names, notes):
    """Every MS band against the pan: its residual field under the model it gets, its registration to the reference
    band, and its own correction (the reference model plus the linear difference) where that differs
    significantly; a band that does not resemble the pan keeps the reference correction (what remains of it is
    spectral). Returns ``(report rows, {band: model})``."""
    rows, models = [], {}
    for b in sorted(band_cells) or [ref]:
        name = names[b - 1][0] if b - 1 < len(names) else f"band {b}"
        row: Dict[str, Any] = {"band": b, "name": name, "reference": b == ref}
        models[b] = model
        if b in band_cells:
            c = band_cells[b]
            u = np.asarray(c["usable"], bool)
            row["n_usable"] = int(u.sum())
            if b != ref:
                bb = _band_to_band(band_cells[ref], c, model)
                m_ncc = _median_ncc_cells(band_cells, b)
                row["median_ncc"] = m_ncc
                if bb is not None:
                    row["to_reference"] = {k: (v.tolist() if hasattr(v, "tolist") else v) for k, v in bb.items()}
                    spectral = m_ncc is not None and m_ncc < SPECTRAL_NCC
                    row["spectral"] = bool(spectral)
                    if spectral:
                        notes.append(f"band {b} ({name}) does not resemble the pan (median correlation {m_ncc:.2f}): "
                                     f"what remains of it ({bb['max_px']:.2f} px against band {ref}) is spectral, not "
                                     "geometric; it gets the reference band's correction")
                    elif bb["significant"]:
                        mb = copy.deepcopy(model)
                        mb.linear = model.linear + np.asarray(bb["linear"])
                        models[b] = mb
                        row["own_correction"] = True
                        notes.append(f"band {b} ({name}) is registered to band {ref} within {bb['max_px']:.3f} MS px "
                                     "only: it gets its own correction")
            else:
                row["median_ncc"] = _median_ncc_cells(band_cells, b)
            ps, pl = models[b].predict(np.asarray(c["sample"], float), np.asarray(c["line"], float))
            rs, rl = np.asarray(c["d_sample"], float) - ps, np.asarray(c["d_line"], float) - pl
            ok = u & np.isfinite(rs) & np.isfinite(rl)
            row["residual"] = {"rms_sample_px": axis_stats(rs[ok])["rms"], "rms_line_px": axis_stats(rl[ok])["rms"],
                               "p_le_0.25": share_within(rs[ok], rl[ok], 0.25)}
            b0s, b0l = np.asarray(c["d_sample"], float)[ok], np.asarray(c["d_line"], float)[ok]
            row["before"] = {"rms_sample_px": axis_stats(b0s)["rms"], "rms_line_px": axis_stats(b0l)["rms"]}
        rows.append(row)
    return rows, models


def _median_ncc_cells(band_cells, b):
    t = band_cells[b].attrs.get("matches")
    return None if t is None else _median_ncc(t)


class _Clock:
    def __init__(self):
        self._time = time.perf_counter
        self._t = self._time()
        self.laps: Dict[str, float] = {}

    def lap(self, name: str) -> None:
        t = self._time()
        self.laps[name] = round(t - self._t, 3)
        self._t = t


def _as_text(x):
    return None if x is None else os.fspath(x) if isinstance(x, (str, os.PathLike)) else str(x)


def _write_cells(cells, model, ms_rpc, dem, path) -> int:
    """cells.gpkg: one point per cell on the ground (MS RPC on the DEM), residuals before (nabla) and after the
    full model as the standard fields, after each step as ``res_sample_<step>``/``res_line_<step>``, arrows."""
    s, l = np.asarray(cells["sample"], float), np.asarray(cells["line"], float)
    lon, lat, h = ms_rpc.localize_dem(s, l, dem)
    t = pd.DataFrame({"id": [f"c{i}" for i in range(len(cells))], "lon": lon, "lat": lat, "h": h,
                      "sample": s, "line": l})
    usable = np.asarray(cells["usable"], bool)
    t["role"] = np.where(usable, "control", "check")
    t["sigma"] = np.hypot(np.asarray(cells.get("sigma_sample", np.nan), float),
                          np.asarray(cells.get("sigma_line", np.nan), float))
    outlier = model.cell_outlier if model.cell_outlier is not None else np.zeros(len(cells), bool)
    t["outlier"] = np.asarray(outlier, bool) & usable
    for col in ("n", "n_windows", "clear_fraction", "usable"):
        if col in cells:
            t[col] = np.asarray(cells[col])
    t["usable"] = usable.astype(int)
    last = None
    for snap in model.snapshots:
        rs, rl = step_residuals(model, snap, s, l, cells["d_sample"], cells["d_line"])
        name = snap["name"].split(" ")[0]
        t[f"res_sample_{name}"], t[f"res_line_{name}"] = np.asarray(rs), np.asarray(rl)
        last = name
    write_residuals_gpkg(t, path, before=("res_sample_before", "res_line_before"),
                         after=(f"res_sample_{last}", f"res_line_{last}"), overwrite=True,
                         title="Pan-MS registration cells (MS px)",
                         points_title="pan-MS cells: misregistration before/after (MS px)",
                         concurrent=True)    # written while the plots draw: rows bound in C (GIL)
    return len(t)


def _plot_tasks(cells, model, outs) -> list:
    """The three plots (residual maps per step, row means along the line, spectrum) as tasks for
    :func:`gdal_gf4cal.threads.run_tasks` (each its own matplotlib Figure); the residuals computed here. The
    cells the plots show (usable, not outliers) are their own array: cells.gpkg and the report read the cells'
    ``usable`` column (outliers included) after them."""
    s, l = np.asarray(cells["sample"], float), np.asarray(cells["line"], float)
    used = np.array(cells["usable"], bool)          # a copy: ``&=`` on asarray's view rewrote the cells' column
    if model.cell_outlier is not None:
        used &= ~model.cell_outlier
    res = {}
    panels = []
    for snap, st in zip(model.snapshots, model.steps):
        rs, rl = (np.asarray(v, float) for v in step_residuals(model, snap, s, l, cells["d_sample"], cells["d_line"]))
        res[snap["name"]] = (rs, rl)
        panels.append((snap["name"], rs, rl, st["rms_sample_px"], st["rms_line_px"], st["p_le_0.25"]))
    names = [sn["name"] for sn in model.snapshots]
    pre = "piecewise" if "piecewise" in names else names[-1]
    pick = {f"after {pre}": res[pre]}
    if "jitter" in res:
        pick["after jitter"] = res["jitter"]
    return [lambda: plot_step_residual_maps(s, l, panels, outs.tmp("residual_maps"), image_size=model.ms_size,
                                            used=used, title="pan-MS residuals per step (MS px)"),
            lambda: _plot_line_profile(l, used, pick, outs.tmp("line_profile")),
            lambda: _plot_spectrum(l, used, res[pre], pre, model, outs.tmp("spectrum"))]


def _plot_line_profile(l, used, pick, path) -> None:
    series = {}
    for label, (rs, rl) in pick.items():
        rs_m, rl_m = np.where(used, rs, np.nan), np.where(used, rl, np.nan)
        lc, ys = row_means(l, rs_m)
        lc2, yl = row_means(l, rl_m)
        if lc.size == lc2.size:
            series[label] = (lc, ys, yl)
    plot_line_profiles(series, path, title="pan-MS residual along the MS line (row means)")


def _plot_spectrum(l, used, residual, pre, model, path) -> None:
    lt = model.info.get("line_time_s")
    rs, rl = residual
    amps = {ax: residual_spectrum(l, np.where(used, r, np.nan), line_time_s=lt) for ax, r in (("sample", rs),
                                                                                            ("line", rl))}
    chosen = {ax: [c.get("frequency_hz", c["frequency_cycles_per_line"]) for c in model.jitter[ax]["components"]]
              for ax in ("sample", "line")}
    plot_spectrum(amps, path, chosen=chosen, unit="Hz" if lt else "cycles per MS line",
                  title=f"spectrum of the residual after the {pre} term")
