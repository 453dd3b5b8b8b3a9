"""``gf4cal block-adjust`` / QGIS ``gf4cal:blockadjust``: multi-CCD / band-to-band block calibration of one group
from its RPC images (METHODS §8; engine :mod:`gdal_gf4cal.block`). All outputs together or none.

Images are named by a **key**: the file name without extension when those are unique, else the image's folder name
(simulated groups: ``ccd1/scene.tif`` -> ``ccd1``). The observation files' ``image`` column names images by key,
file name or path. Outputs in ``out``: ``<key>.RPB`` per image (refit, METHODS §3, error reported),
``calibration.json`` (the group's exterior and every image's interior, for ``apply-calibration``), ``report.json``,
``residuals.gpkg`` (layers ``<key>_gcps`` / ``<key>_residual_vectors`` per image and ``seams``) and ``seams.png``.
"""
from __future__ import annotations

import os
from typing import Any, Dict, List, Mapping, Sequence, Union

import numpy as np

from ..block import BlockError
from ..crop import image_and_rpc, image_rpc
from ..outputs import OutputSet, check_vector
from ._common import _open_image, cancel_check, collect_warnings, finish_report

__all__ = ["block_adjust", "check_observations", "image_keys", "parse_bands_of"]


def image_keys(paths: Sequence) -> List[str]:
    """Keys of images (module docstring): file stems when unique, else folder names; unique or an error."""
    from ..outputs import scene_stem
    stems = [scene_stem(p) for p in paths]
    if len(set(s.casefold() for s in stems)) == len(stems):
        return stems
    folders = [os.path.basename(os.path.dirname(os.path.abspath(os.fspath(p)))) for p in paths]
    if len(set(f.casefold() for f in folders)) == len(folders):
        return folders
    raise BlockError("two images have the same file name and folder name; give each image of the group a distinct "
                     "name")


def _resolve(name: str, paths: Sequence[str], keys: Sequence[str], what: str) -> str:
    """The key of the image ``name`` (a key, file name, path or stem)."""
    from ..outputs import scene_stem
    name = str(name).strip()
    low = name.casefold()
    for p, k in zip(paths, keys):
        if low in (k.casefold(), os.path.basename(p).casefold(), scene_stem(p).casefold()) and \
                sum(low in (kk.casefold(), os.path.basename(pp).casefold()) for pp, kk in zip(paths, keys)) <= 1:
            return k
        if os.path.abspath(name) == os.path.abspath(p):
            return k
    raise BlockError(f"{what} names image {name!r}, which is not among the images given "
                     f"({', '.join(keys[:6])}{', ...' if len(keys) > 6 else ''}); give that image or fix the name")


#: How messages name the bands-of option; the QGIS provider words ``(--bands-of)`` as ``(BANDS_OF)``.
BANDS_OF = "bands of (--bands-of)"


#: How messages name the RPC pairs option (QGIS: ``(RPCS)``).
RPC_PAIRS = "RPC pairs (--rpc)"


def parse_rpc_pairs(items: Union[None, Mapping[str, str], Sequence[str]]) -> Dict[str, str]:
    """``["IMAGE=RPC", ...]`` (CLI/QGIS) or a mapping -> ``{image: RPC file}``."""
    if not items:
        return {}
    if isinstance(items, Mapping):
        return {str(a): os.fspath(b) for a, b in items.items()}
    pairs = {}
    for entry in items:
        image, rpc = image_and_rpc(entry)
        if rpc is None or not image or not rpc:
            raise BlockError(f"{RPC_PAIRS}: {entry!r} is not IMAGE=RPC; give each image whose RPC is a separate "
                             "file with that file, e.g. left.tif=left.geom")
        pairs[image] = rpc
    return pairs


def parse_bands_of(items: Union[None, Mapping[str, str], Sequence[str]]) -> Dict[str, str]:
    """``["IMAGE=REFIMAGE", ...]`` (CLI/QGIS) or a mapping -> ``{band image: reference-band image}``."""
    if not items:
        return {}
    if isinstance(items, Mapping):
        return {str(k): str(v) for k, v in items.items()}
    out = {}
    for it in items:
        if "=" not in str(it):
            raise BlockError(f"bands of (--bands-of) {it!r}: write IMAGE=REFIMAGE (a band image and the reference-band image of "
                             "its CCD)")
        a, b = str(it).split("=", 1)
        out[a.strip()] = b.strip()
    return out


def _read_obs(paths: Sequence[str], keys: Sequence[str], files: Sequence, dem, gcp_files=(), warns=None) -> Any:
    """Read and merge the observation files, image names resolved to keys. Tie rows naming an image that is not
    given are an error; GCP rows of such images (a GCP file of more images than the block) are dropped, with a
    warning."""
    import pandas as pd
    from ..observations import read_observations
    tables = []
    for f in files:
        t = read_observations(f, need_height=False, dem=dem)
        where = f"the observation file {os.path.basename(os.fspath(f))}"
        ids = {}
        left_out = []
        for i in t["image_id"].unique():
            try:
                ids[i] = _resolve(i, paths, keys, where)
            except BlockError:
                rows = t["image_id"] == i
                if f not in gcp_files or (t.loc[rows, "kind"] == "tie").any():
                    raise
                left_out.append(str(i))
        if left_out and warns is not None:
            warns.append(f"{where}: GCPs of {len(left_out)} image(s) not given left out ({', '.join(left_out[:4])}"
                         f"{', ...' if len(left_out) > 4 else ''})")
        t = t[t["image_id"].isin(list(ids))].copy()
        t["image_id"] = t["image_id"].map(ids)
        tables.append(t)
    if not tables:
        return None
    tab = pd.concat(tables, ignore_index=True)
    return tab.drop_duplicates(["point_id", "image_id"]).reset_index(drop=True)


def block_adjust(images: Sequence, *, dem, out, geoid=None, gcps=None, ties=None, match_ties: bool = False,
                 reference_ortho=None, bands_of=None, solver: str = "simultaneous", reference_ccd=None,
                 overwrite: bool = False, progress=None, check_plausibility: bool = True,
                 rpcs=None) -> Dict[str, Any]:
    """Block calibration of one group (METHODS §8) from files; see the module docstring for names and outputs.

    Parameters
    ----------
    images : image paths (RPC embedded or as a sidecar). The reference-band CCD images come **in their order
        across track** (adjacent ones must overlap); the other bands' images anywhere, each named in ``bands_of``.
    rpcs : ``["IMAGE=RPC", ...]`` (CLI ``--rpc``) or ``{image: rpc file}``: the RPC file of an image that carries
        none (a crop and its product's ``.geom``: the crop's origin is applied, :func:`gdal_gf4cal.crop.image_rpc`;
        the report's ``notes`` say so); other images: their own RPC, else the RPC file named like them beside them.
    dem : DEM path or number (tie-point heights); ``geoid``: its vertical datum (``auto``/``none``/``egm96``/...).
    gcps, ties : observation files (CSV/GeoPackage, long format: ``point_id, image, sample, line`` [``lon, lat, h``,
        ``role``, ``sigma``]); a single file may hold both (rows are de-duplicated).
    match_ties : tie points by raw-to-raw matching (adjacent CCDs and each band against its reference band).
    reference_ortho : an orthophoto to collect GCPs from for every reference-band image.
    bands_of : ``{band image: reference-band image}`` or ``["IMAGE=REFIMAGE", ...]``.
    solver : ``simultaneous`` or ``alternating``; ``alternating`` also runs the simultaneous solve and compares
        them in the report (``solver_comparison``).
    reference_ccd : the CCD image fixing the datum (default: the middle reference-band CCD).
    check_plausibility : every observation checked against its image as ``refine`` does (:func:`check_observations`:
        GCPs and tie measurements beyond the RPC's domain, GCP heights in feet or on another datum than the DEM's,
        GCPs far from their RPC prediction are refused before any work); ``False`` for experts only.

    Returns
    -------
    dict: the report written as ``report.json`` (+ ``outputs``, ``warnings``).
    """
    from .. import progress as _progress
    from ..block import adjust_block, calibration_dict, corrected_model, prediction_std, seam_offsets
    from ..dem import DEM
    from ..report import plot_seams, write_points_layer, write_report_json, write_residuals_gpkg
    from ..rpc_fit import fit_rpc_from_model
    from ..rpc_io import write_rpb
    from ..stats import accuracy_by_role
    from ..block import write_calibration

    paths = [os.fspath(p) for p in images]
    if len(paths) < 2:
        raise BlockError("a block needs the images of at least two CCDs; give every CCD image of the group")
    if solver not in ("simultaneous", "alternating"):
        raise BlockError(f"solver {solver!r} unknown; choose simultaneous or alternating")
    if not (gcps or reference_ortho):
        raise BlockError("no control: give GCPs (--gcps) or a reference ortho (--reference-ortho) to fix the datum")
    if not (ties or match_ties):
        raise BlockError("no tie points: give --ties or --match-ties to tie the CCDs and bands together")
    keys = image_keys(paths)
    bmap = {_resolve(a, paths, keys, BANDS_OF): _resolve(b, paths, keys, BANDS_OF)
            for a, b in parse_bands_of(bands_of).items()}
    order = [k for k in keys if k not in bmap]
    ref_ccd = _resolve(reference_ccd, paths, keys, "--reference-ccd") if reference_ccd else None
    rpc_of = {_resolve(a, paths, keys, RPC_PAIRS): b for a, b in parse_rpc_pairs(rpcs).items()}
    sizes, inputs = {}, list(rpc_of.values())
    models, crop_notes = {}, []
    for p, k in zip(paths, keys):
        size, files = _open_image(p)
        inputs += files
        models[k], note = image_rpc(p, rpc_of.get(k))
        crop_notes += [f"{k}: {note}"] if note else []
        sizes[k] = size
    obs_files = [os.fspath(f) for f in (gcps, ties) if f]
    obs_files = list(dict.fromkeys(obs_files))
    inputs += obs_files + [os.fspath(f) for f in (dem, reference_ortho) if isinstance(f, (str, os.PathLike))]
    dem_obj = DEM.from_user_input(dem, geoid=geoid)
    from ..block import derive_layout
    layout = derive_layout(models, order, bands_of=bmap, sizes={k: s for k, s in sizes.items() if s},
                           reference_ccd=ref_ccd)
    early_warns: List[str] = []
    tab = _read_obs(paths, keys, obs_files, dem_obj, gcp_files=[os.fspath(gcps)] if gcps else [],
                    warns=early_warns)
    if check_plausibility and tab is not None:
        with collect_warnings(early_warns):
            check_observations(tab, models, sizes, dem_obj)
    # declare every output before any work
    outd = os.fspath(out)
    outs = OutputSet(inputs, overwrite=overwrite, cancelled=cancel_check(progress))
    for k in keys:
        outs.declare(f"rpb:{k}", os.path.join(outd, f"{k}.RPB"))
    outs.declare("calibration", os.path.join(outd, "calibration.json"))
    outs.declare("report", os.path.join(outd, "report.json"))
    outs.declare("residuals", os.path.join(outd, "residuals.gpkg"), check=check_vector())
    outs.declare("seams_plot", os.path.join(outd, "seams.png"))
    warns: List[str] = list(early_warns)
    with outs, collect_warnings(warns):
        extra = []
        if reference_ortho:
            extra.append(_collect_from_ortho(paths, keys, order, models, reference_ortho, dem_obj,
                                             _progress.scaled(progress, 0.0, 0.2)))
        if match_ties:
            extra.append(_match_ties(paths, keys, layout, models, dem_obj, _progress.scaled(progress, 0.2, 0.35)))
        if extra:
            import pandas as pd
            tab = pd.concat(([tab] if tab is not None else []) + extra, ignore_index=True)
            tab = tab.drop_duplicates(["point_id", "image_id"]).reset_index(drop=True)
        est = adjust_block(tab, models, dem_obj, layout=layout, solver=solver, compare=(solver == "alternating"),
                           progress=_progress.scaled(progress, 0.35, 0.7))
        corrected = {k: corrected_model(est, k, models[k]) for k in keys}
        images_rep: Dict[str, Any] = {}
        for i, (p, k) in enumerate(zip(paths, keys)):
            _progress.report(progress, 0.7 + 0.2 * i / len(keys), f"refitting the RPC of {k}")
            new_rpc, fit = fit_rpc_from_model(corrected[k], size=layout.images[k].size,
                                              height_range=tuple(models[k].height_range))
            write_rpb(new_rpc, outs.tmp(f"rpb:{k}"), overwrite=True)
            rows = est.table[est.table["image_id"] == k]
            g = rows[rows["kind"] == "gcp"]
            t = rows[rows["kind"] == "tie"]
            W, H = layout.images[k].size
            S, L = (a.ravel() for a in np.meshgrid(np.linspace(0.5, W - 0.5, 11), np.linspace(0.5, H - 0.5, 11)))
            fs, fl = prediction_std(est, k, S, L)
            images_rep[k] = {"image": p, "rpb": outs.path(f"rpb:{k}"), "ccd": layout.images[k].ccd,
                             "precision_px": float(np.sqrt(np.mean(fs ** 2 + fl ** 2))),
                             "reference_band_image": layout.images[k].reference,
                             "rpc_fit": fit.to_dict(), "gcps": accuracy_by_role(g) if len(g) else None,
                             "ties": accuracy_by_role(t.assign(role="control"), roles=("control",))["control"]
                             if len(t) else None}
        pairs = list(layout.adjacent_pairs())
        pairs += _band_pairs(layout, est.table)
        seams = seam_offsets(est.table, models, corrected, dem_obj, pairs)
        band_reg = _band_to_band(est.table, layout)
        rep: Dict[str, Any] = {
            "command": "block-adjust", "method": "METHODS §8 block calibration in RPC space",
            "solver": solver, "layout": layout.to_dict(), "estimate": est.to_dict(), "stages": est.stages,
            "exterior": {n: float(v) for n, v in zip(est.names[:5], est.x[:5])},
            "images": images_rep,
            "seams": [{k: v for k, v in s.items() if k != "points"} for s in seams],
            "band_to_band": band_reg,
            "n_outliers": int(np.count_nonzero(est.outlier)),
            "outliers": [{"point_id": str(r.point_id), "image": str(r.image_id), "kind": str(r.kind)}
                         for r in est.table[est.table["outlier"]].itertuples()][:1000]}
        if est.comparison is not None:
            rep["solver_comparison"] = {
                solver: {"iterations": [s["iterations"] for s in est.stages],
                         "converged": [s["converged"] for s in est.stages],
                         "sigma0": float(est.sigma0)},
                est.comparison["solver"]: {"iterations": [s["iterations"] for s in est.comparison["stages"]],
                                           "converged": [s["converged"] for s in est.comparison["stages"]]},
                "max_prediction_difference_px": _max_difference(est.table, est.comparison["table"])}
        rep["warnings"] = list(est.warnings)
        if crop_notes:
            rep["notes"] = crop_notes
        write_calibration(calibration_dict(est), outs.tmp("calibration"))
        # residual GeoPackage: per image its GCPs (and tie rays), then the seams layer
        gp = outs.tmp("residuals")
        for k in keys:
            rows = est.table[est.table["image_id"] == k].rename(columns={"point_id": "id"})
            rows = rows[np.isfinite(rows["lon"].to_numpy(float))]
            if len(rows) == 0:
                continue
            write_residuals_gpkg(rows.drop(columns=[c for c in ("image_id",) if c in rows.columns]), gp,
                                 layer_prefix=f"{k}_", append=True, overwrite=True, title=f"{k} residuals")
        sp = [s for s in seams if s.get("points")]
        if sp:
            cols: Dict[str, Any] = {"pair": np.concatenate([np.full(len(s["points"]["point_id"]),
                                                                    f"{s['pair'][0]}|{s['pair'][1]}", dtype=object)
                                                            for s in sp])}
            for c in ("point_id", "line_b", "ds_before", "dl_before", "ds_after", "dl_after"):
                cols[c] = np.concatenate([np.asarray(s["points"][c]) for s in sp])
            cols["point_id"] = cols["point_id"].astype(str).astype(object)
            cols["offset_px_before"] = np.hypot(cols["ds_before"], cols["dl_before"])
            cols["offset_px_after"] = np.hypot(cols["ds_after"], cols["dl_after"])
            write_points_layer(gp, "seams", cols, np.concatenate([s["points"]["lon"] for s in sp]),
                               np.concatenate([s["points"]["lat"] for s in sp]),
                               description="one feature per overlap tie point: offset (px of the right image) of "
                                           "its measurement from the left image's prediction, before and after")
        rms = {k: (_planar_rms(est.table, k, "before"), _planar_rms(est.table, k, "after")) for k in keys}
        plot_seams(seams, outs.tmp("seams_plot"), residual_rms=rms)
        rep["outputs"] = outs.paths
        finish_report(rep, warns)
        write_report_json(rep, outs.tmp("report"))
    finish_report(rep, warns)
    _progress.report(progress, 1.0, "done")
    return rep


def check_observations(tab, models: Mapping[str, Any], sizes: Mapping[str, Any], dem=None) -> None:
    """Every observation against its image, as ``refine`` checks GCPs (:mod:`gdal_gf4cal.plausibility`; issue 19):
    per image its GCP rows (:func:`~gdal_gf4cal.plausibility.check_gcps_against`, heights against ``dem``) and its
    tie measurements (:func:`~gdal_gf4cal.plausibility.check_measured_inside`). A refusal (GCPError) names the
    image and the override; points outside an image but inside its RPC's domain are used, with a warning."""
    from ..errors import GCPError
    from ..plausibility import STRAY_FRACTION, check_gcps_against, check_measured_inside
    rows = tab.rename(columns={"point_id": "id"})
    for k, t in rows.groupby("image_id", sort=False):
        gcp = (t["kind"] == "gcp").to_numpy()
        try:
            if gcp.any():
                check_gcps_against(models[k], t[gcp], sizes.get(k), dem=dem, what=f"GCPs of {k}")
            if (~gcp).any():
                check_measured_inside(models[k], t[~gcp], sizes.get(k), what=f"tie points of {k}",
                                      stray_fraction=STRAY_FRACTION)
        except BlockError:
            raise
        except GCPError as exc:
            raise BlockError(f"{k}: {exc}") from None


def _planar_rms(table, k, when) -> float:
    r = table[(table["image_id"] == k) & ~table["outlier"]]
    v = np.hypot(r[f"res_sample_{when}"].to_numpy(float), r[f"res_line_{when}"].to_numpy(float))
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v ** 2))) if v.size else float("nan")


def _max_difference(a, b) -> float:
    d = np.hypot(a["pred_sample_after"].to_numpy(float) - b["pred_sample_after"].to_numpy(float),
                 a["pred_line_after"].to_numpy(float) - b["pred_line_after"].to_numpy(float))
    return float(np.nanmax(d)) if np.isfinite(d).any() else float("nan")


def _band_pairs(layout, table) -> list:
    """Adjacent-CCD pairs of the other bands: band images whose reference images are adjacent and that share ties."""
    adj = set(layout.adjacent_pairs())
    ties = table[table["kind"] == "tie"]
    pts = ties.groupby("image_id")["point_id"].apply(set).to_dict()
    out = []
    bands = layout.band_images
    for a in bands:
        for b in bands:
            ra, rb = layout.images[a].reference, layout.images[b].reference
            if (ra, rb) in adj and pts.get(a, set()) & pts.get(b, set()):
                out.append((a, b))
    return out


def _band_to_band(table, layout) -> Dict[str, Any]:
    """Band-to-band registration: per band image, residual RMS of its tie rays shared with its reference image."""
    out = {}
    ties = table[(table["kind"] == "tie") & ~table["outlier"]]
    for b in layout.band_images:
        ref = layout.images[b].reference
        pb = set(ties.loc[ties["image_id"] == ref, "point_id"])
        r = ties[(ties["image_id"] == b) & ties["point_id"].isin(pb)]
        ent = {"reference": ref, "n": int(len(r))}
        for when in ("before", "after"):
            v = np.hypot(r[f"res_sample_{when}"].to_numpy(float), r[f"res_line_{when}"].to_numpy(float))
            v = v[np.isfinite(v)]
            ent[f"rms_px_{when}"] = float(np.sqrt(np.mean(v ** 2))) if v.size else None
        out[b] = ent
    return out


def _collect_from_ortho(paths, keys, order, models, reference, dem, progress):
    """GCPs collected against an orthophoto for every reference-band image (issue 7's matcher)."""
    import pandas as pd
    from ..matching.collect import collect_gcps
    from ..observations import from_gcps
    tabs = []
    for i, k in enumerate(order):
        p = paths[keys.index(k)]
        W, H = _open_image(p)[0] or (512, 512)
        # dense enough for a cubic per CCD: about 8 x 8 windows per image (the matcher's default 256 px is for a
        # 6-parameter bias of a whole scene)
        spacing = int(max(32, min(256, min(W, H) // 8)))
        g = collect_gcps(p, models[k], os.fspath(reference), dem, spacing_px=spacing,
                         window_px=int(min(64, 2 * spacing)), progress=None)
        g = g[~g["outlier"].to_numpy(bool)] if "outlier" in g.columns else g
        g = g.assign(id=[f"O{k}_{j}" for j in g["id"]])
        tabs.append(from_gcps(g[["id", "lon", "lat", "h", "sample", "line", "role", "sigma"]], k))
        if progress:
            progress((i + 1) / len(order), f"GCPs of {k} from the reference ortho")
    return pd.concat(tabs, ignore_index=True)


#: Overlap strips narrower than this (px) are matched with 16 px windows and a 6 px search.
NARROW_STRIP_PX = 64
#: Matching windows aimed at per image pair (the grid spacing follows the overlap's area, 8 to 64 px).
TIES_PER_PAIR = 200


def _match_ties(paths, keys, layout, models, dem, progress):
    """Tie points by raw-to-raw matching (adjacent CCDs; every band against its reference band)."""
    import pandas as pd
    try:
        from ..matching import match_ties
    except ImportError:
        raise BlockError("--match-ties needs the raw-to-raw matcher, which this installation lacks; give tie points "
                         "with --ties") from None
    from ..matching.raw import overlap_region
    pairs = list(layout.adjacent_pairs()) + [(layout.images[b].reference, b) for b in layout.band_images]
    tabs = []
    for i, (a, b) in enumerate(pairs):
        pa, pb = paths[keys.index(a)], paths[keys.index(b)]
        # An MS overlap strip is ~50 px wide (200 pan px / 4): narrower than the default window plus its search
        # range, so narrow strips are matched with small windows; the spacing gives ~TIES_PER_PAIR windows.
        box, _ = overlap_region(pa, models[a], pb, models[b], dem, step_px=NARROW_STRIP_PX // 4)
        w, h = box[2] - box[0] - NARROW_STRIP_PX // 2, box[3] - box[1] - NARROW_STRIP_PX // 2
        kw: Dict[str, Any] = {"spacing_px": int(np.clip(np.sqrt(max(w, 1.0) * max(h, 1.0) / TIES_PER_PAIR), 8, 64))}
        if min(w, h) < NARROW_STRIP_PX:
            kw.update(window_px=16, search_px=6)
        t = match_ties(pa, models[a], pb, models[b], dem, ids=(a, b), **kw)
        if t is not None and len(t):
            t = t.copy()
            t["point_id"] = [f"M{i}_{p}" for p in t["point_id"]]
            tabs.append(t)
        if progress:
            progress((i + 1) / len(pairs), f"matched {a} and {b}")
    if not tabs:
        raise BlockError("raw-to-raw matching found no tie points; check the images overlap and have texture, or "
                         "give --ties")
    return pd.concat(tabs, ignore_index=True)
