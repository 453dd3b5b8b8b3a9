"""The block adjustment (METHODS §8): checks, the reference-band and band stages, the a-posteriori covariance and
the :class:`~gdal_gf4cal.block.BlockEstimate` (:func:`adjust_block`)."""
from __future__ import annotations

import math
from typing import Any, Dict, List, Mapping, Optional, Sequence

import numpy as np

from .. import progress as _progress
from ..errors import DegenerateGeometryError
from ..observations import flag_outliers, validate_observations
from .coverage import unsupported_terms
from .estimate import BlockEstimate
from .layout import BlockError, BlockLayout, derive_layout, layout_from_calibration
from .model import DATUM_TERMS, EXTERIOR_NAMES, INTERIOR_NAMES, parameter_blocks
from .stage import Stage, redundancy, run_stage, stage_rows

def _check_control(tab, layout: BlockLayout, min_gcps: int = 4):
    ctrl = tab[(tab["kind"] == "gcp") & (tab["role"] == "control")]
    counts = ctrl.groupby("image_id")["point_id"].nunique()
    for im in layout.order:
        n = int(counts.get(im, 0))
        if n < min_gcps:
            raise BlockError(f"{im}: {n} control GCP(s); the block needs >= {min_gcps} per reference-band CCD image "
                             "to fix its interior cubic and the datum; add GCPs (--gcps)")


def adjust_block(observations, models: Mapping[str, Any], dem, *, layout: Optional[BlockLayout] = None,
                 order: Optional[Sequence[str]] = None, bands_of: Optional[Mapping[str, str]] = None,
                 reference_ccd: Optional[str] = None, solver: str = "simultaneous", robust: bool = True,
                 compare: bool = False, tol: float = 1e-3, max_iter: int = 60, reject_k: float = 5.0,
                 calibration: Optional[Mapping[str, Any]] = None, progress=None) -> BlockEstimate:
    """Block calibration of one group in RPC space (METHODS §8; module docstring).

    Parameters
    ----------
    observations : the long observation table (:mod:`gdal_gf4cal.observations`): GCP rows (``lon, lat, h``) and tie
        rows (``kind='tie'``, shared ``point_id``); ``image_id`` = the keys of ``models``. ``sigma`` in px.
    models : ``{image id: RPCModel}`` (any sensor model with ``project``/``project_jacobian``/``localize``).
    dem : :class:`~gdal_gf4cal.dem.DEM` (ellipsoidal): tie-point heights.
    layout : a :class:`BlockLayout`; default :func:`derive_layout` (``order``, ``bands_of``, ``reference_ccd``).
    order : the reference-band CCD images across track (default: the images without ``bands_of`` entry, in the
        order of ``models``).
    solver : ``"simultaneous"`` (one sparse Gauss-Newton on everything) or ``"alternating"`` (exterior, then
        interior, repeated; METHODS §8's paper scheme).
    robust : robust reweighting and blunder rejection (module docstring).
    compare : also run the other solver and keep its stages (iterations, parameters) in ``comparison``.
    tol : convergence: largest change of any predicted position in one iteration, px.
    calibration : a group calibration (:func:`calibration_dict`; ``models`` keyed by its image names): only the
        scene's exterior is estimated, every interior held at the calibrated values (another scene of the same
        camera and group with a few GCPs, METHODS §8's validation); ``layout`` comes from the calibration.

    Returns
    -------
    BlockEstimate
        ``x`` over the blocks ``exterior``, ``datum:<reference CCD>`` (frozen, 0), ``interior:<image>``; ``cov``
        (a-posteriori) and the per-row diagnostics (``residuals`` / ``weights`` / ``normalised`` are ``(n_rows * 2)``,
        sample then line of each row of ``table``); ``outlier`` per row.

    Raises
    ------
    BlockError
        Unknown images in the observations, too few GCPs for the datum, a layout problem (:func:`derive_layout`).
    DegenerateGeometryError
        The observations do not determine the parameters.
    """
    if solver not in ("simultaneous", "alternating"):
        raise BlockError(f"solver {solver!r} unknown; choose simultaneous or alternating")
    tab = validate_observations(observations, need_height=False, dem=dem)
    unknown = sorted(set(tab["image_id"]) - set(models))
    if unknown:
        raise BlockError(f"the observations name image {unknown[0]!r}, which is not among the images "
                         f"({', '.join(list(models)[:6])}{', ...' if len(models) > 6 else ''}); give that image or "
                         "fix the observation file's image column")
    if calibration is not None:
        layout = layout_from_calibration(calibration, models)
    if layout is None:
        bands_of = dict(bands_of or {})
        if order is None:
            order = [m for m in models if m not in bands_of]
        layout = derive_layout(models, order, bands_of=bands_of, reference_ccd=reference_ccd)
    gcp = (tab["kind"] == "gcp").to_numpy()
    if gcp.any() and not np.all(np.isfinite(tab.loc[gcp, "h"].to_numpy(float))):
        raise BlockError("some GCPs have no height; give h or a DEM to take it from")
    if calibration is not None:
        n = int(tab.loc[(tab["kind"] == "gcp") & (tab["role"] == "control"), "point_id"].nunique())
        if n < 3:
            raise BlockError(f"{n} control GCP(s); the scene's exterior (5 terms) needs >= 3; add GCPs (--gcps)")
        return _adjust(tab, models, dem, layout, solver, robust, tol, max_iter, reject_k, progress,
                       start=calibration)
    _check_control(tab, layout)
    result = _adjust(tab, models, dem, layout, solver, robust, tol, max_iter, reject_k, progress)
    if compare:
        other = "alternating" if solver == "simultaneous" else "simultaneous"
        alt = _adjust(tab, models, dem, layout, other, robust, tol, max_iter * 4 if other == "alternating" else
                      max_iter, reject_k, None)
        result.comparison = {"solver": other, "stages": alt.stages, "parameters": alt.parameters,
                             "table": alt.table}
    return result



def _adjust(tab, models, dem, layout: BlockLayout, solver, robust, tol, max_iter, reject_k, progress,
            start: Optional[Mapping[str, Any]] = None) -> BlockEstimate:
    blocks, index = parameter_blocks(layout)
    names = [n for b in blocks for n in b.names]
    sl: Dict[str, slice] = {}
    pos = 0
    for b in blocks:
        sl[b.name] = slice(pos, pos + b.size)
        pos += b.size
    p = len(names)
    x = np.zeros(p)
    datum = np.zeros(p, bool)
    datum[sl[f"datum:{layout.reference_ccd}"]] = True
    unsupported, coverage_warnings = unsupported_terms(tab, layout, index, p, interiors=start is None)
    ext = np.zeros(p, bool)
    ext[sl["exterior"]] = True
    ref_imgs = list(layout.order)
    band_imgs = layout.band_images
    is_ref_int = np.zeros(p, bool)
    for im in ref_imgs:
        is_ref_int[sl[f"interior:{im}"]] = True
    is_band_int = np.zeros(p, bool)
    for im in band_imgs:
        is_band_int[sl[f"interior:{im}"]] = True
    control = (tab["kind"] == "gcp").to_numpy() & (tab["role"] == "control").to_numpy()
    used_gcp_ref = control
    stages_out: List[Dict[str, Any]] = []
    n = len(tab)
    pred_after = np.full((n, 2), np.nan)
    pred_before = np.full((n, 2), np.nan)
    weights = np.zeros((n, 2))
    outl = np.zeros(n, bool)
    ground = tab[["lon", "lat", "h"]].to_numpy(float).copy()
    red_all = np.ones(n)
    specs = [("reference", ref_imgs, False, ext | is_ref_int)]
    if band_imgs:
        specs.append(("bands", band_imgs, True, is_band_int))
    if start is not None:                                   # another scene: its exterior only, interiors calibrated
        for im in layout.images:
            idx = index[im]
            x[idx[5:]] = [float(start["images"][im]["interior"][n]) for n in INTERIOR_NAMES]
        x[sl["exterior"]] = [float(start["exterior"][n]) for n in EXTERIOR_NAMES]
        specs = [("exterior", ref_imgs + band_imgs, False, ext)]
        used_gcp_ref = control
    final_stage = []
    for si, (label, imgs, band_stage, free_all) in enumerate(specs):
        rows = stage_rows(tab, imgs, band_stage, ref_imgs + band_imgs)
        stage = Stage(tab, rows, models, layout, index, dem, used_gcp_ref)
        free_all = free_all & ~datum & ~unsupported
        if solver == "alternating" and not band_stage:
            free_sets = [free_all & ext, free_all & ~ext]
        else:
            free_sets = [free_all]
        prog = _progress.scaled(progress, si / len(specs), (si + 0.9) / len(specs)) if progress else None
        # before: the original RPCs, tie points from their rays' mean
        x0 = x.copy()
        plon0, plat0 = stage.initial_points(x0)
        pb, _, _, _ = stage.evaluate(x0, plon0, plat0, with_jacobian=False)
        x, plon, plat, info = run_stage(stage, x, np.array(free_sets), robust=robust, tol=tol, max_iter=max_iter,
                                         reject_k=reject_k, progress=prog)
        pa, _, _, g = stage.evaluate(x, plon, plat, with_jacobian=False)
        # a stage's rows: the earlier stage's values stay for rows it does not re-estimate (reference GCPs)
        mine = tab["image_id"].iloc[rows].isin(imgs).to_numpy() | np.isnan(pred_after[rows, 0])
        r = rows[mine]
        pred_before[r] = pb[mine]
        pred_after[r] = pa[mine]
        fw = stage.base_w * info["factor"]
        weights[r] = fw[mine, None]
        outl[r] = info["rejected"][mine]
        ground[rows[stage.is_tie]] = g[stage.is_tie]
        red_all[r] = redundancy(stage, np.repeat(fw[:, None], 2, axis=1))[mine]
        dof_obs = int(2 * np.count_nonzero(fw > 0))
        n_pts = int(stage.point_ids.size)
        stages_out.append({"stage": label, "images": list(imgs), "solver": solver if not band_stage else
                           "simultaneous", "iterations": int(info["iterations"]), "converged": bool(info["converged"]),
                           "history_px": [float(h) for h in info["history"]], "n_free_parameters": int(free_all.sum()),
                           "reduced_system_size": int(free_all.sum()), "n_tie_points": n_pts,
                           "n_observations": dof_obs, "n_rejected": int(np.count_nonzero(info["rejected"]))})
        final_stage.append((stage, x.copy(), plon, plat, fw, free_all, dof_obs, n_pts))
    # a-posteriori covariance from the last solve of each stage
    cov = np.zeros((p, p))
    v_all = tab[["sample", "line"]].to_numpy(float) - pred_after
    wsum = float(np.nansum(weights * v_all ** 2))
    dof = sum(d - 2 * npt - int(f.sum()) for _, _, _, _, _, f, d, npt in final_stage)
    sigma0 = math.sqrt(wsum / dof) if dof > 0 else 1.0
    earlier = np.zeros(p, bool)                             # parameters of the stages before (frozen now)
    pending: List[Any] = []
    for stage, xs, plon, plat, fw, free_all, _, _ in final_stage:
        pred, _, jp, _ = stage.evaluate(xs, plon, plat)
        w = np.repeat(fw[:, None], 2, axis=1)
        try:
            _, _, sol = stage.solve(xs, free_all, stage.meas - pred, w, jp, covariance=True)
            fi = np.flatnonzero(free_all)
            cov[np.ix_(fi, fi)] = sigma0 ** 2 * sol.cov_global
            if earlier.any():                          # on demand (one reduced solve per frozen parameter)
                pending.append((stage, xs, free_all, earlier.copy(), w, jp))
        except DegenerateGeometryError:
            pass
        earlier |= free_all
    table = tab.copy()
    table[["lon", "lat", "h"]] = ground
    for tag, pr in (("before", pred_before), ("after", pred_after)):
        table[f"pred_sample_{tag}"] = pr[:, 0]
        table[f"pred_line_{tag}"] = pr[:, 1]
        table[f"res_sample_{tag}"] = table["sample"].to_numpy(float) - pr[:, 0]
        table[f"res_line_{tag}"] = table["line"].to_numpy(float) - pr[:, 1]
    table = flag_outliers(table, outl, "robust")
    sig = table["sigma"].to_numpy(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        normalised = (v_all / (sigma0 * sig[:, None] * np.sqrt(red_all)[:, None])).ravel()
    frozen = (f"datum:{layout.reference_ccd}",)
    est = BlockEstimate(names=names, x=x, cov=cov, sigma0=sigma0, dof=int(dof), redundancy=np.repeat(red_all, 2),
                        residuals=v_all.ravel(), normalised=normalised, weights=weights.ravel(), blocks=sl,
                        frozen=frozen, outlier=outl, outlier_level=np.where(outl, "robust", ""),
                        iterations=int(sum(s["iterations"] for s in stages_out)), table=table, layout=layout,
                        stages=stages_out, cov_pending=pending)
    est.notes.append(f"datum: {', '.join(DATUM_TERMS)} of {layout.reference_ccd} fixed at 0 (they duplicate e0, e1, "
                     "kappa)")
    est.warnings.extend(coverage_warnings)
    for s in stages_out:
        if not s["converged"]:
            est.warnings.append(f"{s['stage']} stage ({s['solver']}) did not converge in {s['iterations']} "
                                "iterations; its results are the last iterate")
    return est


