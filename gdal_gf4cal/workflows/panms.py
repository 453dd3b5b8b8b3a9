"""``gf4cal register-pan-ms`` / QGIS "Register MS to pan": the file job of METHODS §9 (seed 004, Gaofen-7).

Dense pan-MS cells (``matching.pan_ms_cells``) -> :func:`gdal_gf4cal.panms.estimate` -> every output under one
:class:`~gdal_gf4cal.outputs.OutputSet` (all or nothing).
"""
from __future__ import annotations

import math
import os
from typing import Any, Dict, Optional

import numpy as np

from ..crop import image_rpc
from ..outputs import OutputSet, check_raster, check_vector
from ._common import cancel_check, collect_warnings, finish_report

#: Output file names in ``out``.
OUTPUT_NAMES = {"correction": "correction.tif", "ms_on_pan": "ms_on_pan.tif", "model": "model.json",
                "ms_rpc": "ms_approx.RPB", "report": "report.json", "cells": "cells.gpkg",
                "residual_maps": "residual_maps.png", "line_profile": "residual_along_line.png",
                "spectrum": "spectrum.png"}
#: Reuse mode: at most this many sparse matches (one window per cell, METHODS §9 eq. 17).
REUSE_MAX_MATCHES = 200


def _size(path):
    from .._gdal import open_raster
    ds = open_raster(os.fspath(path), what="image")
    return (ds.RasterXSize, ds.RasterYSize), ds.RasterCount


def check_overlap(pan_rpc, ms_rpc, pan_size, ms_size, dem, n: int = 7) -> float:
    """Share of an ``n x n`` MS grid that the pan sees (MS RPC on the DEM -> pan RPC); refuses < 25 %."""
    from ..panms import PanMSError
    W, H = ms_size
    s, l = np.meshgrid((np.arange(n) + 0.5) * W / n, (np.arange(n) + 0.5) * H / n)
    with np.errstate(all="ignore"):
        lon, lat, h = ms_rpc.localize_dem(s.ravel(), l.ravel(), dem)
        ps, pl = pan_rpc.project(lon, lat, h)
    ps, pl = np.asarray(ps), np.asarray(pl)
    inside = np.isfinite(ps) & np.isfinite(pl) & (ps >= 0) & (ps <= pan_size[0]) & (pl >= 0) & (pl <= pan_size[1])
    share = float(np.mean(inside))
    if share < 0.25:
        raise PanMSError(f"the pan and MS images hardly overlap ({100 * share:.0f} % of the MS seen by the pan "
                         "through their RPCs): give the pan and MS images of the same scene")
    return share


def _parse_breaks(breaks) -> Optional[list]:
    """``--breaks``: MS columns and/or the words ``ms`` (the MS band's equal sub-CCD edges) and ``pan`` (the pan's
    equal sub-CCD edges mapped into the MS through the RPCs and the DEM), e.g. ``2560,5120`` or ``ms,pan``."""
    from ..panms import PanMSError
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


def _resolve_breaks(spec, *, n_sub_ccds, pan_rpc, ms_rpc, dem, pan_size, ms_size) -> list:
    """MS columns of the sub-CCD edges from a parsed ``--breaks`` (numbers, ``ms``, ``pan``)."""
    from .. import panms
    n = 3 if n_sub_ccds is None else n_sub_ccds
    cols = [b for b in spec if not isinstance(b, str)]
    if "ms" in spec:
        cols += panms.default_breaks(ms_size[0], n)
    if "pan" in spec:
        cols += panms.pan_edges_in_ms(pan_rpc, ms_rpc, dem, pan_size, n)
    if all(isinstance(b, str) for b in spec) or "ms" in spec or "pan" in spec:
        return panms.merge_breaks(cols, width=ms_size[0])
    return [float(b) for b in cols]


def register_pan_ms(pan, ms, *, dem, out, geoid=None, n_sub_ccds: Optional[int] = None, breaks=None,
                    cell: int = 64, jitter="auto", reuse=None, overwrite: bool = False, cells=None,
                    workers: Optional[int] = None, progress=None) -> Dict[str, Any]:
    """Register an MS image to its pan (METHODS §9) and write, in ``out``: ``correction.tif`` (delta sample /
    delta line at every MS pixel centre), ``ms_on_pan.tif`` (the MS resampled onto the pan's raw grid at MS
    resolution, for ``gdal_pansharpen.py PAN ms_on_pan.tif fused.tif``), ``model.json`` (loadable with
    ``reuse``), ``ms_approx.RPB`` (refitted MS RPC, a smooth approximation; its error in the report),
    ``report.json`` (per step RMS per axis, P(<= 0.25 px), spectrum peaks; jitter components), ``cells.gpkg``
    (cells with residuals before/after each step, styled arrows) and the plots (``residual_maps.png``,
    ``residual_along_line.png``, ``spectrum.png``).

    ``n_sub_ccds`` / ``breaks`` (MS columns, a list or "S1,S2", and/or the words ``ms`` / ``pan``: the MS band's
    equal sub-CCD edges / the pan's mapped into the MS): the sub-CCD edges (default ``ms``, 3 equal pieces);
    ``cell``: cell size (MS px); ``jitter``: ``auto`` | ``none`` | N; ``reuse``: a ``model.json`` of another
    scene of the same camera: only the linear term is solved, from <= 200 sparse matches. ``cells``: a cell
    table already measured (skips the matching). Returns the report dict.
    """
    from .. import panms, progress as _progress
    from ..dem import DEM
    from ..errors import Gf4calError
    from ..report import write_report_json
    from ..rpc_io import write_rpb

    breaks = _parse_breaks(breaks)
    if n_sub_ccds is not None and breaks is not None and not ({"ms", "pan"} & set(b for b in breaks
                                                                                 if isinstance(b, str))):
        raise panms.PanMSError("give either --sub-ccds or --breaks with MS columns, not both")
    if str(jitter) not in ("auto", "none"):
        try:
            jitter = int(jitter)
        except ValueError:
            raise panms.PanMSError(f"--jitter {jitter!r}: give auto, none or a number of components") from None
        if jitter < 0:
            raise panms.PanMSError("--jitter must be auto, none or a non-negative number")
    if int(cell) < 8:
        raise panms.PanMSError(f"--cell {cell}: cells must be at least 8 MS px")
    out = os.fspath(out)
    outs = OutputSet([pan, ms, dem if isinstance(dem, (str, os.PathLike)) else None, geoid,
                      reuse if isinstance(reuse, (str, os.PathLike)) else None],
                     overwrite=overwrite, cancelled=cancel_check(progress))
    for key, name in OUTPUT_NAMES.items():
        check = {"correction": check_raster(2), "ms_on_pan": check_raster(), "cells": check_vector()}.get(key)
        outs.declare(key, os.path.join(out, name), check=check)
    warns: list = []
    clock = _Clock()
    with outs, collect_warnings(warns):
        (pw, ph), _ = _size(pan)
        (mw, mh), n_bands = _size(ms)
        ratio = panms.check_sizes((pw, ph), (mw, mh))
        (pan_rpc, _), (ms_rpc, _) = image_rpc(pan), image_rpc(ms)
        dem_obj = DEM.from_user_input(dem, geoid=geoid)
        overlap = check_overlap(pan_rpc, ms_rpc, (pw, ph), (mw, mh), dem_obj)
        if breaks is not None:
            breaks = _resolve_breaks(breaks, n_sub_ccds=n_sub_ccds, pan_rpc=pan_rpc, ms_rpc=ms_rpc, dem=dem_obj,
                                     pan_size=(pw, ph), ms_size=(mw, mh))
        reuse_model = None
        if reuse is not None:
            reuse_model = reuse if isinstance(reuse, panms.PanMSModel) else panms.PanMSModel.from_json(reuse)
            reuse_model.compatible_with((mw, mh), breaks if breaks is not None else (
                panms.default_breaks(mw, n_sub_ccds) if n_sub_ccds is not None else None))
        elif breaks is None:
            breaks = panms.default_breaks(mw, 3 if n_sub_ccds is None else n_sub_ccds)
        _progress.report(progress, 0.02, "pan-MS: matching")
        if cells is None:
            from ..matching import pan_ms_cells
            # >= 16 matching windows per cell (16 px apart for the default 64 px cells)
            kw: Dict[str, Any] = {"cell_px": int(cell), "spacing_px": int(max(4, min(16, int(cell) // 4))),
                                  "progress": _progress.scaled(progress, 0.02, 0.5)}
            if workers is not None:
                kw["workers"] = workers
            if reuse_model is not None:         # sparse: one window per cell, <= 200 cells
                c = int(max(8, math.ceil(math.sqrt(mw * mh / REUSE_MAX_MATCHES))))
                kw.update(cell_px=c, spacing_px=c, min_matches=1)
            cells = pan_ms_cells(pan, ms, dem_obj, pan_model=pan_rpc, ms_model=ms_rpc, **kw)
        n_matches = len(cells.attrs.get("matches", ())) if hasattr(cells, "attrs") else 0
        clock.lap("matching")
        cells = cells.reset_index(drop=True)
        if len(cells) == 0 or not np.asarray(cells["usable"], bool).any():
            raise panms.PanMSError(f"no usable cell: all {len(cells)} cells are cloud, water or texture-less; "
                                   "register a clearer scene of the same camera and use --reuse MODEL.json")
        model = panms.estimate(cells, ms_size=(mw, mh), breaks=breaks, jitter=jitter, reuse=reuse_model,
                               progress=_progress.scaled(progress, 0.5, 0.6))
        model.info["source"] = {"pan": os.fspath(pan), "ms": os.fspath(ms)}
        model.info["ratio"] = ratio
        clock.lap("estimate")
        _progress.report(progress, 0.6, "pan-MS: writing correction.tif")
        model.to_json(outs.tmp("model"))
        panms.write_correction(model, outs.tmp("correction"), progress=_progress.scaled(progress, 0.6, 0.65))
        panms.resample_ms_on_pan(model, pan, ms, outs.tmp("ms_on_pan"), pan_rpc=pan_rpc, ms_rpc=ms_rpc, dem=dem_obj,
                                 ratio=ratio, progress=_progress.scaled(progress, 0.65, 0.9))
        outs.set_check("ms_on_pan", check_raster(n_bands))
        clock.lap("correction_and_ms_on_pan")
        _progress.report(progress, 0.9, "pan-MS: refitting the MS RPC")
        try:
            approx, approx_err = panms.approximate_rpc(model, ms_rpc)
            write_rpb(approx, outs.tmp("ms_rpc"), overwrite=True)
        except Gf4calError as exc:
            raise panms.PanMSError(f"the approximate MS RPC could not be fitted ({exc}); the other outputs need "
                                   "it too: check the MS RPC") from None
        n_cells = _write_cells(cells, model, ms_rpc, dem_obj, outs.tmp("cells"))
        outs.set_check("cells", check_vector({"gcps": n_cells}))
        _write_plots(cells, model, outs)
        clock.lap("rpc_cells_plots")
        rep = {"command": "register-pan-ms",
               "inputs": {"pan": os.fspath(pan), "ms": os.fspath(ms), "dem": _as_text(dem), "geoid": _as_text(geoid),
                          "reuse": _as_text(reuse) if not isinstance(reuse, panms.PanMSModel) else "model"},
               "sizes": {"pan": [pw, ph], "ms": [mw, mh], "ratio": ratio, "ms_on_pan": [pw // ratio, ph // ratio]},
               "overlap_share": overlap, "mode": model.mode, "breaks_ms_px": list(model.breaks),
               "n_cells": int(len(cells)), "n_matches": int(n_matches), "timings_s": clock.laps, "n_usable": int(np.asarray(cells["usable"], bool).sum()),
               "n_outliers": model.info.get("n_outliers", 0), "noise_floor_px": model.info.get("noise_floor_px"),
               "steps": model.steps, "jitter": model.jitter, "linear": model.to_dict()["linear"],
               "ms_approx_rpc": approx_err, "outputs": outs.paths}
        finish_report(rep, warns)
        write_report_json(rep, outs.tmp("report"))
    finish_report(rep, warns)
    _progress.report(progress, 1.0, "done")
    return rep


class _Clock:
    def __init__(self):
        import time
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
    import pandas as pd
    from ..panms import step_residuals
    from ..report import write_residuals_gpkg
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
                         title="Pan-MS registration cells (MS px)")
    return len(t)


def _write_plots(cells, model, outs) -> None:
    from ..panms import residual_spectrum, row_means, step_residuals
    from ..report.plot import plot_line_profiles, plot_spectrum, plot_step_residual_maps
    s, l = np.asarray(cells["sample"], float), np.asarray(cells["line"], float)
    used = np.asarray(cells["usable"], bool)
    if model.cell_outlier is not None:
        used &= ~model.cell_outlier
    res = {}
    panels = []
    for snap, st in zip(model.snapshots, model.steps):
        rs, rl = (np.asarray(v, float) for v in step_residuals(model, snap, s, l, cells["d_sample"], cells["d_line"]))
        res[snap["name"]] = (rs, rl)
        panels.append((snap["name"], rs, rl, st["rms_sample_px"], st["rms_line_px"], st["p_le_0.25"]))
    plot_step_residual_maps(s, l, panels, outs.tmp("residual_maps"), image_size=model.ms_size, used=used,
                            title="pan-MS residuals per step (MS px)")
    names = [sn["name"] for sn in model.snapshots]
    pre = "piecewise" if "piecewise" in names else names[-1]
    pick = {f"after {pre}": res[pre]}
    if "jitter" in res:
        pick["after jitter"] = res["jitter"]
    series = {}
    for label, (rs, rl) in pick.items():
        rs_m, rl_m = np.where(used, rs, np.nan), np.where(used, rl, np.nan)
        lc, ys = row_means(l, rs_m)
        lc2, yl = row_means(l, rl_m)
        if lc.size == lc2.size:
            series[label] = (lc, ys, yl)
    plot_line_profiles(series, outs.tmp("line_profile"), title="pan-MS residual along the MS line (row means)")
    lt = model.info.get("line_time_s")
    rs, rl = res[pre]
    amps = {ax: residual_spectrum(l, np.where(used, r, np.nan), line_time_s=lt) for ax, r in (("sample", rs),
                                                                                            ("line", rl))}
    chosen = {ax: [c.get("frequency_hz", c["frequency_cycles_per_line"]) for c in model.jitter[ax]["components"]]
              for ax in ("sample", "line")}
    plot_spectrum(amps, outs.tmp("spectrum"), chosen=chosen, unit="Hz" if lt else "cycles per MS line",
                  title=f"spectrum of the residual after the {pre} term")

