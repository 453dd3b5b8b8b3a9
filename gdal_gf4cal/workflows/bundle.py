"""``gf4cal bundle-adjust`` / QGIS ``gf4cal:bundleadjust``: separate views (stereo, tri-stereo, multi-date) brought
into one frame from tie points alone, each keeping its own RPC plus an image-space correction (METHODS §11; engine
:mod:`gdal_gf4cal.bundle`). All outputs together or none.

Views are named by a **key**, as block-adjust names its images: the file name without extension (``left.tif``,
``left.geom`` and ``left_RPC.TXT`` -> ``left``), or the folder name when file names repeat. A view is an image with
its RPC (its own, the RPC file named like it beside it, or ``--rpc IMAGE=RPC``; a crop's origin is applied,
:func:`gdal_gf4cal.crop.image_rpc`) or, with ``--ties``, an RPC file alone (OSSIM ``.geom``, ``.RPB``,
``_RPC.TXT``, DIMAP). Tie points come from ``--ties`` (the long observation table, any number of views per point)
and/or ``--match-ties`` (raw-to-raw matching, :func:`gdal_gf4cal.matching.match_ties`, on the overlapping pairs:
a spanning set that connects every view first, then the largest other overlaps, up to ``max_pairs``).

Outputs in ``out``: ``<key>.RPB`` per view (the corrected model refitted as an RPC, METHODS §3) and, when the view is
an image, ``<key>.vrt`` over the untouched image carrying that RPC (``gdalwarp -rpc <key>.vrt ...``);
``report.json`` (tie reprojection before/after per view and per pair, corrections with sigmas, each view's
correction relative to the first view's, datum drift, precision, the RPC refit errors), ``residuals.gpkg`` (per view
its ties with before/after residual vectors, styled, and the tie points' adjusted ground), ``ties.png``, and with
``--match-ties`` the matched ties as ``ties.csv`` (an observation table ``--ties`` reads back).

Refused with one line, nothing written: fewer than two views, no tie source, ties naming images not given, a tie
seen by one view only, ``--match-ties`` on an RPC file alone, a view overlapping no other (matching); the engine
refuses tie measurements outside their image and a view sharing no tie with the others
(:mod:`gdal_gf4cal.bundle.inputs`).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..crop import image_rpc, paired_rpc_files
from ..errors import Gf4calError, GCPError
from ..observations import write_observations
from ..outputs import OutputSet
from ..rpc import RPCModel
from ..threads import blas_serial
from . import block as _block
from ._common import _open_image, cancel_check, collect_warnings, declare_report_outputs, finish_report

__all__ = ["MODELS", "PRIOR_SIGMA", "Views", "bundle_adjust", "choose_pairs", "load_views", "match_pair",
           "match_view_ties", "parse_prior_sigma", "relative_corrections"]

#: Correction models per view (METHODS §11, the bases of §4), in the CLI's order.
MODELS = ("translation", "shift-drift", "affine")

#: Matching windows aimed at per pair (the grid spacing follows the overlap's area, 16 to 128 px).
TIES_PER_PAIR = 300
#: The coarse passes of every pair, (window, search) px, tried in turn until one finds :data:`COARSE_MIN_WINDOWS`
#: matches: they measure the pair's offset (vendor RPCs of two views disagree by up to tens of pixels; the matcher's
#: search cannot exceed its window); the fine pass then matches with that offset taken out.
COARSE_PASSES = ((64, 64), (96, 96))
COARSE_MIN_WINDOWS = 5


@dataclass
class Views:
    """The views of one adjustment: ``keys`` in the order given, ``paths``, ``models`` (key -> RPCModel of the
    view's own pixels), ``sizes`` (key -> (W, H), None for an RPC file alone), the input files and the notes."""
    keys: List[str]
    paths: List[str]
    models: Dict[str, RPCModel]
    sizes: Dict[str, Optional[Tuple[int, int]]]
    inputs: List[str] = field(default_factory=list)
    notes: List[str] = field(default_factory=list)
    prior: Any = None
    flat_height: Optional[float] = None

    def path(self, key: str) -> str:
        return self.paths[self.keys.index(key)]

    def is_image(self, key: str) -> bool:
        return self.sizes.get(key) is not None

    def extent(self, key: str) -> Tuple[float, float]:
        """(W, H) of the view: the image's, else the one its RPC's domain implies."""
        size = self.sizes.get(key)
        return tuple(float(v) for v in (size if size is not None else self.models[key].image_size))


def _check_options(paths: Sequence[str], ties, match_ties: bool, model: str, max_pairs, dem_sigma_m=None) -> None:
    if len(paths) < 2:
        raise GCPError(f"bundle adjustment needs at least two views; {len(paths)} given: give two or more images "
                       "(or, with --ties, RPC files) of the same ground")
    if model not in MODELS:
        raise GCPError(f"model {model!r} unknown; choose {', '.join(MODELS)}")
    if not (ties or match_ties):
        raise GCPError("no tie points: give --ties OBS (the observation table) or --match-ties")
    if max_pairs is not None and int(max_pairs) < 1:
        raise GCPError(f"--max-pairs {max_pairs}: give at least 1 (pairs of views to match)")
    if dem_sigma_m is not None and not (np.isfinite(float(dem_sigma_m)) and float(dem_sigma_m) > 0):
        raise GCPError(f"--dem-sigma {dem_sigma_m}: give the DEM's height accuracy as a positive number of metres")


def load_views(images: Sequence, rpcs=None, *, need_images: bool = False) -> Views:
    """Every view's RPC in its own pixels (:func:`gdal_gf4cal.crop.image_rpc`), keyed as the module docstring says.
    ``need_images``: refuse an RPC file alone (matching needs pixels)."""
    paths = [os.fspath(p) for p in images]
    keys = _block.image_keys(paths)
    given = paired_rpc_files(paths, rpcs or (), what=_block.RPC_PAIRS)
    views = Views(keys=keys, paths=paths, models={}, sizes={}, inputs=[r for r in given if r])
    for p, k, rpc in zip(paths, keys, given):
        if not os.path.exists(p) and not p.startswith("/vsi"):
            raise GCPError(f"view {p}: file not found")
        size, files = _open_image(p)
        views.inputs += files
        if size is None:
            if need_images:
                raise GCPError(f"{os.path.basename(p)} is an RPC file, not an image: --match-ties needs every view's "
                               "pixels; give the image, or tie points with --ties")
            model, note = RPCModel.from_file(p), None
        else:
            model, note = image_rpc(p, rpc)
        if not isinstance(model, RPCModel):
            raise GCPError(f"{os.path.basename(p)}: its sensor model is not an RPC; give the view's RPC")
        views.models[k], views.sizes[k] = model, size
        views.notes += [f"{k}: {note}"] if note else []
    return views


def _overlaps(views: Views, dem) -> List[Tuple[float, str, str]]:
    """``(share, a, b)`` for every pair of views that see common ground: ``share`` = the part of ``a``'s image that
    ``b`` also shows (``overlap_region``'s box over ``a``'s size); pairs that do not overlap are left out."""
    from ..matching.raw import overlap_region
    out = []
    for i, a in enumerate(views.keys):
        for b in views.keys[i + 1:]:
            try:
                box, _ = overlap_region(views.path(a), views.models[a], views.path(b), views.models[b], dem)
            except Gf4calError:
                continue
            W, H = views.extent(a)
            out.append((float((box[2] - box[0]) * (box[3] - box[1]) / (W * H)), a, b))
    return out


def choose_pairs(overlaps: Sequence[Tuple[float, str, str]], keys: Sequence[str],
                 max_pairs: Optional[int] = None) -> List[Tuple[str, str]]:
    """The pairs to match: first a maximum spanning tree over the overlaps (every view joined to the others by the
    largest overlaps available), then the largest remaining overlaps, at most ``max_pairs`` in all (default every
    overlapping pair; never fewer than the spanning tree needs). A view that overlaps none is refused."""
    root = {k: k for k in keys}

    def find(k):
        while root[k] != k:
            root[k] = root[root[k]]
            k = root[k]
        return k

    ranked = sorted(overlaps, key=lambda o: (-o[0], o[1], o[2]))
    tree, rest = [], []
    for share, a, b in ranked:
        ra, rb = find(a), find(b)
        if ra != rb:
            root[ra] = rb
            tree.append((a, b))
        else:
            rest.append((a, b))
    groups: Dict[str, List[str]] = {}
    for k in keys:
        groups.setdefault(find(k), []).append(k)
    if len(groups) > 1:
        apart = min(groups.values(), key=len)
        if len(apart) == 1:
            raise GCPError(f"view {apart[0]} overlaps no other view on the ground (through the RPCs and the DEM), so "
                           "no tie can join it to the others; drop it, give views of the same ground, or give --ties")
        raise GCPError(f"the views fall into {len(groups)} groups that overlap nowhere on the ground ("
                       + " | ".join(", ".join(g) for g in groups.values())
                       + "), so no tie can join them; adjust each group apart, or give --ties")
    n = len(tree) + len(rest) if max_pairs is None else max(int(max_pairs), len(tree))
    return tree + rest[:max(0, n - len(tree))]


def _pair_offset(path_a, model_a, path_b, model_b, dem, area: float) -> Tuple[Tuple[float, float], int]:
    """The offset (px of ``a``, measured - predicted) of the pair's RPCs: the median of the accepted windows of
    the first of :data:`COARSE_PASSES` that finds :data:`COARSE_MIN_WINDOWS` (else (0, 0)), and their count."""
    from ..matching import match_raw
    best = ((0.0, 0.0), 0)
    for window, search in COARSE_PASSES:
        t = match_raw(path_a, model_a, path_b, model_b, dem, window_px=window, search_px=search,
                      spacing_px=int(np.clip(np.sqrt(area / 100), 32, 512)))
        ok = (t["status"].to_numpy() == 0) & ~t["outlier"].to_numpy(bool)
        if ok.sum() >= max(COARSE_MIN_WINDOWS, best[1] + 1):
            best = ((float(np.median(t["d_sample"][ok])), float(np.median(t["d_line"][ok]))), int(ok.sum()))
            break
    return best


def match_pair(path_a, model_a, path_b, model_b, dem, *, ids: Tuple[str, str], ties_per_pair: int = TIES_PER_PAIR,
               progress=None):
    """Tie points between two views (:func:`gdal_gf4cal.matching.match_ties`) in two passes: a coarse pass with
    large windows and a wide search measures the pair's offset (:func:`_pair_offset`), the fine pass matches with
    ``model_a`` shifted by it. The ties are homologous pixels of the two images whatever model found them.
    Returns ``(table, info)``: the long table (``kind='tie'``) and ``{pair, n_ties, offset_px, ...}``."""
    from ..matching import match_ties
    from ..matching.raw import overlap_region
    box, _ = overlap_region(path_a, model_a, path_b, model_b, dem)
    area = max(box[2] - box[0], 1.0) * max(box[3] - box[1], 1.0)
    offset, n_coarse = _pair_offset(path_a, model_a, path_b, model_b, dem, area)
    shifted = model_a.with_image_affine(*offset) if isinstance(model_a, RPCModel) else model_a
    if n_coarse:
        box, _ = overlap_region(path_a, shifted, path_b, model_b, dem)
        area = max(box[2] - box[0], 1.0) * max(box[3] - box[1], 1.0)
    spacing = int(np.clip(np.sqrt(area / ties_per_pair), 16, 128))
    # No affine consistency cut on the offsets: between views of different angles they hold the parallax of the
    # DEM's errors (a Pleiades pair at B/H 0.5: 0.7 px per metre), so it would reject good ties; blunders are left
    # to the adjustment's robust weights on whole tie rays.
    t = match_ties(path_a, shifted, path_b, model_b, dem, ids=ids, spacing_px=spacing, window_px=32,
                   search_px=16, progress=progress, outlier_model=None)
    info = {"pair": list(ids), "n_ties": int(len(t) // 2), "offset_px": list(offset),
            "coarse_windows_accepted": n_coarse, "spacing_px": spacing, "windows": t.attrs.get("windows")}
    return t, info


def match_view_ties(views: Views, dem, *, max_pairs: Optional[int] = None, progress=None):
    """Tie points by raw-to-raw matching on the pairs :func:`choose_pairs` picks (:func:`match_pair` each):
    ``(table, [info per pair])``. A pair without any tie is reported and left out; the views must stay joined."""
    import pandas as pd
    from .. import progress as _progress
    _progress.report(progress, 0.0, "finding the overlapping views")
    flat = "" if views.flat_height is None else (
        f" (without a DEM the views were placed at a constant {views.flat_height:.0f} m: give --dem)")
    try:
        pairs = choose_pairs(_overlaps(views, dem), views.keys, max_pairs)
    except GCPError as exc:
        raise GCPError(f"{exc}{flat}") from None
    tables, infos = [], []
    for i, (a, b) in enumerate(pairs):
        sub = _progress.scaled(progress, 0.1 + 0.9 * i / len(pairs), 0.1 + 0.9 * (i + 1) / len(pairs))
        try:
            t, info = match_pair(views.path(a), views.models[a], views.path(b), views.models[b], dem, ids=(a, b),
                                 progress=sub)
        except Gf4calError as exc:        # the matcher's own advice names options this command does not have
            infos.append({"pair": [a, b], "n_ties": 0, "error": str(exc).splitlines()[0].split("; check")[0]})
            continue
        tables.append(t)
        infos.append(info)
    linked = {k for inf in infos if inf["n_ties"] for k in inf["pair"]}
    missing = [k for k in views.keys if k not in linked]
    if missing:
        why = "; ".join(f"{i['error']}" for i in infos if i.get("error"))
        raise GCPError(f"raw-to-raw matching found no tie point joining view {missing[0]} to the others"
                       f"{' (' + why + ')' if why else ''}{flat}; check the views overlap with texture, or give "
                       "--ties")
    tab = pd.concat(tables, ignore_index=True)
    return tab.drop(columns=[c for c in ("score", "status") if c in tab.columns]), infos


#: How messages name the prior option (QGIS: ``(PRIOR_SIGMA)``).
PRIOR_SIGMA = "prior sigma (--prior-sigma)"


def parse_prior_sigma(items, views: Views):
    """``--prior-sigma [VIEW=]PX ...`` (or a number, or ``{view: px}``) -> what the engine takes: ``None``, one
    number for every view, or ``{view key: px}`` (views not named keep the engine's default: the RPC's ERR_BIAS,
    else a few pixels). A bare number and VIEW=PX items may be mixed: the number is then every other view's."""
    if items is None or isinstance(items, (int, float)):
        return None if items is None else float(items)
    pairs = items.items() if isinstance(items, dict) else [
        tuple(str(i).split("=", 1)) if "=" in str(i) else (None, i) for i in items]
    out: Dict[Optional[str], float] = {}
    for view, value in pairs:
        try:
            px = float(value)
        except (TypeError, ValueError):
            raise GCPError(f"{PRIOR_SIGMA} {value!r}: give pixels, e.g. 3 or right=100") from None
        if not np.isfinite(px) or px <= 0:
            raise GCPError(f"{PRIOR_SIGMA} {value!r}: give a positive number of pixels")
        key = None if view is None else _block._resolve(view, views.paths, views.keys, PRIOR_SIGMA)
        out[key] = px
    if not out:
        return None
    if set(out) == {None}:
        return out[None]
    every = out.pop(None, None)
    return {k: out.get(k, every) for k in views.keys if out.get(k, every) is not None}


def _observations(views: Views, ties, gcps, dem, warns: List[str]):
    """The tie and GCP files read and merged, image names resolved to view keys (as block-adjust reads them: a
    tie naming an image not given is refused, GCPs of other images are left out with a warning); None without
    files."""
    files = list(dict.fromkeys(os.fspath(f) for f in (gcps, ties) if f))
    if not files:
        return None
    return _block._read_obs(views.paths, views.keys, files, dem, gcp_files=[os.fspath(gcps)] if gcps else [],
                            warns=warns)


def _prepare(images, *, ties, gcps, match_ties, dem, geoid, rpcs, prior_sigma_px, check_plausibility, warns):
    """Everything read and checked before any output is declared: ``(views, dem, table)``."""
    from ..dem import DEM
    views = load_views(images, rpcs, need_images=match_ties)
    dem_obj = DEM.from_user_input(dem, geoid=geoid) if dem is not None else None
    if dem_obj is None and match_ties:
        h = views.flat_height = float(np.mean([m.height_off for m in views.models.values()]))
        dem_obj = DEM.constant(h)
        warns.append(f"no DEM: views matched on a constant height of {h:.0f} m (the RPCs' mean height offset); give "
                     "--dem for terrain with relief")
    views.prior = parse_prior_sigma(prior_sigma_px, views)
    tab = _observations(views, ties, gcps, dem_obj, warns)
    if tab is not None:
        if check_plausibility and (tab["kind"] == "gcp").any():
            with collect_warnings(warns):
                _block.check_observations(tab[tab["kind"] == "gcp"], views.models,
                                          {k: v for k, v in views.sizes.items() if v}, dem_obj)
    views.inputs += [os.fspath(f) for f in (ties, gcps, dem) if isinstance(f, (str, os.PathLike))]
    return views, dem_obj, tab


def _declare(views: Views, out, overwrite: bool, progress, matched: bool) -> OutputSet:
    """Every output declared before any work (module docstring)."""
    outd = os.fspath(out)
    outs = OutputSet(views.inputs, overwrite=overwrite, cancelled=cancel_check(progress))
    if matched:
        outs.declare("ties", os.path.join(outd, "ties.csv"))
    for k in views.keys:
        outs.declare(f"rpb:{k}", os.path.join(outd, f"{k}.RPB"))
        if views.is_image(k):
            outs.declare(f"vrt:{k}", os.path.join(outd, f"{k}.vrt"))
    declare_report_outputs(outs, residuals=os.path.join(outd, "residuals.gpkg"),
                           plot=os.path.join(outd, "ties.png"), report=os.path.join(outd, "report.json"))
    return outs


@blas_serial()     # BLAS on the calling thread, as in the CLI and QGIS (threads.py)
def bundle_adjust(images: Sequence, *, out, ties=None, match_ties: bool = False, dem=None, geoid=None, gcps=None,
                  model: str = "affine", max_pairs: Optional[int] = None, rpcs=None,
                  prior_sigma_px: Optional[float] = None, dem_sigma_m: Optional[float] = None,
                  overwrite: bool = False, progress=None, check_plausibility: bool = True) -> Dict[str, Any]:
    """Bundle adjustment of separate views from files (METHODS §11); see the module docstring for names, outputs
    and refusals.

    Parameters
    ----------
    images : the views: images with their RPCs, or (with ``ties``) RPC files alone.
    out : output folder.
    ties : tie-point observation file (CSV/GeoPackage, long format ``point_id, image, sample, line[, sigma]``).
    match_ties : find tie points by raw-to-raw matching (every view must then be an image).
    dem : DEM path or constant height (m): starting heights and every tie's height prior ``DEM ± dem_sigma_m``
        (it fixes the along-epipolar part of the views' relative bias, which ties alone cannot see); ``geoid`` its
        vertical datum. Without it matching uses the RPCs' mean height offset (a warning says so) and the ties get
        no height prior.
    dem_sigma_m : σ (m) of the DEM's height prior (CLI ``--dem-sigma``; default
        :data:`gdal_gf4cal.bundle.DEFAULT_DEM_SIGMA_M`, a global DEM's typical absolute accuracy).
    gcps : GCP observation file (``point_id, image, sample, line, lon, lat, h[, role][, sigma]``), optional.
    model : per-view correction, ``translation``, ``shift-drift`` or ``affine`` (falls back where ties do not
        support it, with a note).
    max_pairs : at most this many pairs matched (default every overlapping pair).
    rpcs : ``["IMAGE=RPC", ...]`` or ``{image: rpc}``: an image's RPC given apart (a crop's product RPC).
    prior_sigma_px : σ (px) of the datum prior on each view's correction parameters: a number for every view,
        ``{view: px}`` or ``["PX", "VIEW=PX", ...]`` (CLI ``--prior-sigma``); default the RPC's stated bias error
        (ERR_BIAS), else 5 m on the ground over the view's pixel size. A view known to be far off (a deliberately biased RPC) needs a wide one.
    check_plausibility : check GCPs as ``refine`` does (``False``: experts).

    Returns
    -------
    dict: the report written as ``report.json`` (+ ``outputs``, ``notes``, ``warnings``).
    """
    from .. import progress as _progress
    paths = [os.fspath(p) for p in images]
    _check_options(paths, ties, match_ties, model, max_pairs, dem_sigma_m)
    warns: List[str] = []
    views, dem_obj, tab = _prepare(paths, ties=ties, gcps=gcps, match_ties=match_ties, dem=dem, geoid=geoid,
                                   rpcs=rpcs, prior_sigma_px=prior_sigma_px,
                                   check_plausibility=check_plausibility, warns=warns)
    outs = _declare(views, out, overwrite, progress, match_ties)
    with outs, collect_warnings(warns):
        pairs_info = []
        if match_ties:
            matched, pairs_info = match_view_ties(views, dem_obj, max_pairs=max_pairs,
                                                  progress=_progress.scaled(progress, 0.0, 0.4))
            tab = _merge(tab, matched)
            write_observations(matched, outs.tmp("ties"), overwrite=True)
        est, after = _adjust(views, tab, dem_obj if dem is not None else None, model, views.prior,
                             _progress.scaled(progress, 0.4, 0.8), dem_sigma_m)
        rep = _report(views, est, after, model, pairs_info, outs, ties_source=_tie_source(ties, match_ties))
        _write_outputs(views, est, after, rep, outs, _progress.scaled(progress, 0.8, 1.0))
        finish_report(rep, warns)
        from ..report import write_report_json
        write_report_json(rep, outs.tmp("report"))
    finish_report(rep, warns)
    _progress.report(progress, 1.0, "done")
    return rep


def _merge(tab, matched):
    import pandas as pd
    if tab is None:
        return matched.reset_index(drop=True)
    return pd.concat([tab, matched], ignore_index=True).drop_duplicates(["point_id", "image_id"]) \
        .reset_index(drop=True)


def _tie_source(ties, match_ties) -> str:
    return " and ".join(([f"file {os.path.basename(os.fspath(ties))}"] if ties else [])
                        + (["raw-to-raw matching"] if match_ties else []))


def _adjust(views: Views, tab, dem, model: str, prior_sigma_px, progress, dem_sigma_m=None):
    """The engine (:func:`gdal_gf4cal.bundle.adjust_views`) and each view's corrected RPC
    (:func:`gdal_gf4cal.compensation.apply_compensation`: folded, or refitted over the view with its error):
    ``(estimate, {view: AppliedCompensation})``."""
    from ..bundle import DEFAULT_DEM_SIGMA_M, adjust_views
    from ..compensation import apply_compensation
    if tab is None or not (tab["kind"] == "tie").any():
        raise GCPError("no tie points: the observation files hold none; give tie rows (point_id seen in two or "
                       "more images) or --match-ties")
    est = adjust_views(tab, views.models, dem=dem, model=model, sizes={k: v for k, v in views.sizes.items() if v},
                       prior_sigma_px=prior_sigma_px, robust=True, progress=progress,
                       dem_sigma_m=DEFAULT_DEM_SIGMA_M if dem_sigma_m is None else float(dem_sigma_m))
    after = {k: apply_compensation(views.models[k], est.corrections[k], image_size=views.sizes.get(k))
             for k in views.keys}
    return est, after


def relative_corrections(est, reference: str) -> Dict[str, Dict[str, float]]:
    """Each view's correction at its image centre relative to ``reference``'s (px; the constant terms of the
    corrections in their centred frames), with the standard deviation of the difference from the full covariance
    (the datum prior correlates the views): what two tools' adjustments of the same ties must agree on."""
    idx = {n: i for i, n in enumerate(est.names)}
    out = {}
    for k in est.views:
        ent = {}
        for axis in ("sample", "line"):
            a, b = idx.get(f"{k}:{axis}_1"), idx.get(f"{reference}:{axis}_1")
            if a is None or b is None:
                continue
            var = est.cov[a, a] + est.cov[b, b] - 2.0 * est.cov[a, b]
            ent[axis] = float(est.x[a] - est.x[b])
            ent[f"{axis}_std"] = float(np.sqrt(max(var, 0.0)))
        out[k] = ent
    return out


def _view_report(views: Views, k: str, est, applied, outs) -> Dict[str, Any]:
    from ..plausibility import correction_precision
    corr = est.corrections[k]
    rows = est.table[(est.table["image_id"] == k) & (est.table["kind"] == "tie")]
    rep = {"input": views.path(k), "image_size": list(views.sizes[k]) if views.is_image(k) else None,
           "model_used": est.model_used.get(k),
           "correction": {"parameters_px": corr.parameters, "parameter_std_px": corr.parameter_std,
                          "frame": list(corr.frame)},
           "precision_px": correction_precision(corr, views.extent(k)),
           "reprojection_px": {w: est.reprojection[w]["per_view"].get(k) for w in ("before", "after")},
           "n_tie_observations": int(len(rows)), "n_outliers": int(rows["outlier"].to_numpy(bool).sum()),
           "rpc": applied.to_dict(), "rpb": outs.path(f"rpb:{k}")}
    if f"vrt:{k}" in outs:
        rep["vrt"] = outs.path(f"vrt:{k}")
    return rep


def _report(views: Views, est, after, model: str, pairs_info, outs, *, ties_source: str) -> Dict[str, Any]:
    """``report.json`` (module docstring)."""
    t = est.table
    ties = t[t["kind"] == "tie"]
    rep: Dict[str, Any] = {
        "command": "bundle-adjust",
        "method": "METHODS §11 bundle adjustment of separate views on their RPCs (Grodecki & Dial 2003)",
        "model": model, "model_used": dict(est.model_used),
        "ties": {"source": ties_source, "n_points": int(ties["point_id"].nunique()),
                 "n_observations": int(len(ties)), "n_gcps": int(t.loc[t["kind"] == "gcp", "point_id"].nunique()),
                 "pairs_matched": pairs_info},
        "views": {k: _view_report(views, k, est, after[k], outs) for k in views.keys},
        "relative_to_first_view_px": {"reference": views.keys[0],
                                      "views": relative_corrections(est, views.keys[0])},
        "reprojection_px": est.reprojection,
        "datum_drift_m": float(est.datum_drift_m),
        "datum_drift_enu_m": [float(v) for v in getattr(est, "datum_drift_enu_m", ())],
        "estimate": {"sigma0": float(est.sigma0), "dof": int(est.dof), "iterations": int(est.iterations),
                     "converged": bool(getattr(est, "converged", True)),
                     "reduced_system_size": int(getattr(est, "reduced_size", len(est.x))),
                     "condition_number": float(est.condition_number)},
        "n_outliers": int(t["outlier"].to_numpy(bool).sum()),
        "outliers": [{"point_id": str(r.point_id), "image": str(r.image_id)}
                     for r in t[t["outlier"].to_numpy(bool)].itertuples()][:1000],
        "notes": list(views.notes) + list(est.notes), "warnings": list(est.warnings), "outputs": outs.paths}
    return rep


def _residual_rows(est, k: str):
    """The view's rows of the residual table with each point's adjusted ground (lon, lat, h) and the GCP schema's
    names (``id``), for :func:`gdal_gf4cal.report.write_residuals_gpkg`."""
    rows = est.table[est.table["image_id"] == k].drop(columns=["lon", "lat", "h"], errors="ignore")
    pts = est.points[["point_id", "lon", "lat", "h"]]
    rows = rows.merge(pts, on="point_id", how="left").rename(columns={"point_id": "id"})
    rows = rows[np.isfinite(rows["lon"].to_numpy(float)) & np.isfinite(rows["lat"].to_numpy(float))]
    return rows.drop(columns=["image_id"])


def _write_outputs(views: Views, est, after, rep, outs, progress) -> None:
    """The RPCs (and VRTs), the residual GeoPackage and the plot, to the output set's temporaries."""
    from .. import progress as _progress
    from ..report import write_points_layer, write_residuals_gpkg
    from ..report.plot import plot_tie_residuals
    from ..rpc_io import write_rpb, write_rpc_vrt
    for i, k in enumerate(views.keys):
        _progress.report(progress, 0.5 * i / len(views.keys), f"writing the RPC of {k}")
        write_rpb(after[k].rpc, outs.tmp(f"rpb:{k}"), overwrite=True)
        if f"vrt:{k}" in outs:
            write_rpc_vrt(views.path(k), after[k].rpc, outs.tmp(f"vrt:{k}"), overwrite=True)
    gp = outs.tmp("residuals")
    for k in views.keys:
        rows = _residual_rows(est, k)
        if len(rows):
            write_residuals_gpkg(rows, gp, layer_prefix=f"{k}_", append=True, overwrite=True,
                                 title=f"{k} tie residuals", points_title=f"{k} ties",
                                 cancelled=outs.cancelled)
    p = est.points[np.isfinite(est.points["lon"].to_numpy(float))]
    cols = {c: (p[c].astype(str).to_numpy(object) if p[c].dtype == object else p[c].to_numpy())
            for c in p.columns if c not in ("lon", "lat")}
    write_points_layer(gp, "tie_points", cols, p["lon"].to_numpy(float), p["lat"].to_numpy(float),
                       description="one feature per tie point at its adjusted ground position: height, number of "
                                   "views, ground precision (m) and its position before the adjustment")
    _progress.report(progress, 0.8, "plotting the tie residuals")
    plot_tie_residuals(est.table, outs.tmp("plot"), sizes={k: views.extent(k) for k in views.keys},
                       title=f"Tie residuals per view ({rep['ties']['n_points']} ties)")
