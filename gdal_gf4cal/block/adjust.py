"""The block adjustment (METHODS §8): checks, the reference-band and band stages, the a-posteriori covariance and
the :class:`~gdal_gf4cal.block.BlockEstimate` (:func:`adjust_block`)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, List, Mapping, Optional, Sequence

import numpy as np

from .. import progress as _progress
from ..errors import DegenerateGeometryError
from ..estimation import sigma0_and_cov
from ..estimation.result import names_and_blocks
from ..observations import flag_outliers, validate_observations
from .coverage import unsupported_terms
from .estimate import BlockEstimate
from .layout import BlockError, BlockLayout, derive_layout, layout_from_calibration, pair_bands
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
        order of ``models``; without ``bands_of`` either, the pairing is derived from the RPCs:
        :func:`~gdal_gf4cal.block.pair_bands`).
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
        if order is None and not bands_of:
            order, bands_of = pair_bands(models, list(models))
        elif order is None:
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



@dataclass
class _Rows:
    """Per observation row of the table, what the stages found: predictions before (original RPCs) and after,
    weights used, rejection flags, tie-point ground and redundancy (a stage keeps the earlier stage's values for the
    rows it does not re-estimate: the reference GCPs)."""

    pred_before: np.ndarray
    pred_after: np.ndarray
    weights: np.ndarray
    outlier: np.ndarray
    ground: np.ndarray
    redundancy: np.ndarray

    @classmethod
    def empty(cls, tab) -> "_Rows":
        n = len(tab)
        return cls(np.full((n, 2), np.nan), np.full((n, 2), np.nan), np.zeros((n, 2)), np.zeros(n, bool),
                   tab[["lon", "lat", "h"]].to_numpy(float).copy(), np.ones(n))


@dataclass
class _StageSpec:
    label: str
    images: List[str]
    band_stage: bool
    free: np.ndarray                                         # parameters the stage may estimate


def _stage_specs(layout: BlockLayout, sl: Mapping[str, slice], x, index, start) -> List[_StageSpec]:
    """The stages (module docstring): reference band (exterior + its interiors), then the other bands'
    interiors; with a calibration ``start`` (another scene), its exterior alone, ``x`` set to the calibration."""
    p = x.size
    ext = np.zeros(p, bool)
    ext[sl["exterior"]] = True
    ref_imgs, band_imgs = list(layout.order), layout.band_images

    def interiors(images):
        m = np.zeros(p, bool)
        for im in images:
            m[sl[f"interior:{im}"]] = True
        return m

    if start is not None:                                   # another scene: its exterior only, interiors calibrated
        for im in layout.images:
            x[index[im][5:]] = [float(start["images"][im]["interior"][n]) for n in INTERIOR_NAMES]
        x[sl["exterior"]] = [float(start["exterior"][n]) for n in EXTERIOR_NAMES]
        return [_StageSpec("exterior", ref_imgs + band_imgs, False, ext)]
    specs = [_StageSpec("reference", ref_imgs, False, ext | interiors(ref_imgs))]
    if band_imgs:
        specs.append(_StageSpec("bands", band_imgs, True, interiors(band_imgs)))
    return specs


def _solve_stage(tab, models, dem, layout, index, spec: _StageSpec, x, rows_out: _Rows, *, solver, robust, tol,
                 max_iter, reject_k, progress):
    """One stage: its rows solved (:func:`~gdal_gf4cal.block.stage.run_stage`), ``rows_out`` filled; returns
    (x, the stage's report entry, what the covariance needs)."""
    control = (tab["kind"] == "gcp").to_numpy() & (tab["role"] == "control").to_numpy()
    rows = stage_rows(tab, spec.images, spec.band_stage, list(layout.images))
    stage = Stage(tab, rows, models, layout, index, dem, control)
    ext = np.zeros(x.size, bool)
    ext[:len(EXTERIOR_NAMES)] = True
    alternate = solver == "alternating" and not spec.band_stage
    free_sets = [spec.free & ext, spec.free & ~ext] if alternate else [spec.free]
    # before: the original RPCs, tie points from their rays' mean
    pb, _, _, _ = stage.evaluate(x, *stage.initial_points(x), with_jacobian=False)
    x, plon, plat, info = run_stage(stage, x, np.array(free_sets), robust=robust, tol=tol, max_iter=max_iter,
                                    reject_k=reject_k, progress=progress, label=f"{spec.label} stage")
    pa, _, _, g = stage.evaluate(x, plon, plat, with_jacobian=False)
    mine = tab["image_id"].iloc[rows].isin(spec.images).to_numpy() | np.isnan(rows_out.pred_after[rows, 0])
    r = rows[mine]
    rows_out.pred_before[r] = pb[mine]
    rows_out.pred_after[r] = pa[mine]
    fw = stage.base_w * info["factor"]
    rows_out.weights[r] = fw[mine, None]
    rows_out.outlier[r] = info["rejected"][mine]
    rows_out.ground[rows[stage.is_tie]] = g[stage.is_tie]
    rows_out.redundancy[r] = redundancy(stage, np.repeat(fw[:, None], 2, axis=1))[mine]
    n_obs, n_pts, n_free = int(2 * np.count_nonzero(fw > 0)), int(stage.point_ids.size), int(spec.free.sum())
    entry = {"stage": spec.label, "images": list(spec.images), "solver": "simultaneous" if spec.band_stage else
             solver, "iterations": int(info["iterations"]), "converged": bool(info["converged"]),
             "history_px": [float(h) for h in info["history"]], "history_meaning": HISTORY_MEANING,
             "n_free_parameters": n_free, "reduced_system_size": n_free, "n_tie_points": n_pts,
             "n_observations": n_obs, "n_rejected": int(np.count_nonzero(info["rejected"]))}
    return x, entry, (stage, x.copy(), plon, plat, fw, spec.free, n_obs - 2 * n_pts - n_free)


#: What a stage's ``history_px`` holds (report.json, the iteration trace).
HISTORY_MEANING = ("per Gauss-Newton iteration, the largest change of a corrected position (px); the weights "
                   "change between phases (a-priori, robust down-weighting, rejection), so a phase's first "
                   "iteration moves again")


def _covariance(solved, rows: _Rows, tab, p: int):
    """A-posteriori covariance from the last solve of each stage (:func:`~gdal_gf4cal.estimation.sigma0_and_cov`
    on its reduced normal matrix; one sigma0 over all stages) and the propagation of the earlier stages' errors
    left for :meth:`BlockEstimate.complete_covariance`. Returns (sigma0, dof, cov, pending)."""
    v_all = tab[["sample", "line"]].to_numpy(float) - rows.pred_after
    vtpv = float(np.nansum(rows.weights * v_all ** 2))
    dof = sum(d for *_, d in solved)
    cov = np.zeros((p, p))
    sigma0 = 1.0
    earlier = np.zeros(p, bool)                             # parameters of the stages before (frozen now)
    pending: List[Any] = []
    for stage, xs, plon, plat, fw, free_all, _ in solved:
        pred, _, jp, _ = stage.evaluate(xs, plon, plat)
        w = np.repeat(fw[:, None], 2, axis=1)
        try:
            _, _, sol = stage.solve(xs, free_all, stage.meas - pred, w, jp, covariance=True)
            fi = np.flatnonzero(free_all)
            s0, cov[np.ix_(fi, fi)] = sigma0_and_cov(sol.normal_global, vtpv, dof)
            sigma0 = s0 if math.isfinite(s0) else 1.0
            if earlier.any():                          # on demand (one reduced solve per frozen parameter)
                pending.append((stage, xs, free_all, earlier.copy(), w, jp))
        except DegenerateGeometryError:
            pass
        earlier |= free_all
    return sigma0, dof, cov, pending


def _adjust(tab, models, dem, layout: BlockLayout, solver, robust, tol, max_iter, reject_k, progress,
            start: Optional[Mapping[str, Any]] = None) -> BlockEstimate:
    blocks, index = parameter_blocks(layout)
    names, sl = names_and_blocks(blocks, 0)
    x = np.zeros(len(names))
    specs = _stage_specs(layout, sl, x, index, start)
    unsupported, coverage_warnings = unsupported_terms(tab, layout, index, x.size, interiors=start is None)
    datum = np.zeros(x.size, bool)
    datum[sl[f"datum:{layout.reference_ccd}"]] = True
    rows = _Rows.empty(tab)
    stages_out, solved = [], []
    for si, spec in enumerate(specs):
        spec.free = spec.free & ~datum & ~unsupported
        prog = _progress.scaled(progress, si / len(specs), (si + 0.9) / len(specs))
        x, entry, done = _solve_stage(tab, models, dem, layout, index, spec, x, rows, solver=solver, robust=robust,
                                      tol=tol, max_iter=max_iter, reject_k=reject_k, progress=prog)
        stages_out.append(entry)
        solved.append(done)
    sigma0, dof, cov, pending = _covariance(solved, rows, tab, x.size)
    return _estimate(tab, layout, names, sl, x, cov, sigma0, dof, rows, stages_out, pending, coverage_warnings)


def _estimate(tab, layout, names, sl, x, cov, sigma0, dof, rows: _Rows, stages_out, pending, warnings
              ) -> BlockEstimate:
    """The :class:`BlockEstimate` with its table (predictions, residuals, outlier flags, tie ground)."""
    table = tab.copy()
    table[["lon", "lat", "h"]] = rows.ground
    for tag, pr in (("before", rows.pred_before), ("after", rows.pred_after)):
        table[f"pred_sample_{tag}"] = pr[:, 0]
        table[f"pred_line_{tag}"] = pr[:, 1]
        table[f"res_sample_{tag}"] = table["sample"].to_numpy(float) - pr[:, 0]
        table[f"res_line_{tag}"] = table["line"].to_numpy(float) - pr[:, 1]
    outl = rows.outlier
    table = flag_outliers(table, outl, "reject")
    v_all = tab[["sample", "line"]].to_numpy(float) - rows.pred_after
    sig = table["sigma"].to_numpy(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        normalised = (v_all / (sigma0 * sig[:, None] * np.sqrt(rows.redundancy)[:, None])).ravel()
    est = BlockEstimate(names=names, x=x, cov=cov, sigma0=sigma0, dof=int(dof),
                        redundancy=np.repeat(rows.redundancy, 2), residuals=v_all.ravel(), normalised=normalised,
                        weights=rows.weights.ravel(), blocks=sl, frozen=(f"datum:{layout.reference_ccd}",),
                        outlier=outl, outlier_level=np.where(outl, "reject", ""),
                        iterations=int(sum(s["iterations"] for s in stages_out)), table=table, layout=layout,
                        stages=stages_out, cov_pending=pending)
    est.notes.append(f"datum: {', '.join(DATUM_TERMS)} of {layout.reference_ccd} fixed at 0 (they duplicate e0, e1, "
                     "kappa)")
    est.warnings.extend(warnings)
    for s in stages_out:
        if not s["converged"]:
            est.warnings.append(f"{s['stage']} stage ({s['solver']}) did not converge in {s['iterations']} "
                                "iterations; its results are the last iterate")
    return est
