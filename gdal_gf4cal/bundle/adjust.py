"""``adjust_views``: bundle adjustment of separate views from their RPCs (METHODS §11, Grodecki & Dial 2003)."""
from __future__ import annotations

from dataclasses import replace
from typing import Any, List, Mapping

import numpy as np
import pandas as pd

from ..dem import DEM
from ..estimation import Estimate, RadialHuber, robust_fit, sigma0_and_cov, tukey_weights
from ..estimation.indexed import block_inverse
from .inputs import check_inputs, make_layout, make_rays, view_sizes
from .model import Rays, ViewLayout
from .result import BundleEstimate, datum_drift, reprojection, view_correction
from .solve import State, Weights, gauss_newton, project_all, reintersect
from .start import DEFAULT_DEM_SIGMA_M, base_weights, start_ground

__all__ = ["adjust_views", "BundleProblem", "ROBUST_TOL_PX", "PRIOR_EXCESS_SIGMAS"]

#: The robust reweighting stops when a re-solve moves the corrections less than this (px, at the image corners) and
#: the rejected rays stay: far below the corrections' floor (a few hundredths to tenths of a pixel); Huber weights can
#: cycle at a few thousandths of a pixel (Giza: 0.0056 px).
ROBUST_TOL_PX = 0.01
#: The down-weighting phase ends below this move (px): the rejection phase reweights on to ROBUST_TOL_PX.
ROBUST_PHASE1_TOL_PX = 0.05
#: A view whose correction at its image centre exceeds this many prior sigmas is reported (a warning): the views
#: disagree beyond their priors, as when one RPC carries a blunder-sized bias, and the priors then split it between
#: the views (a pair follows its first view by default: ``model.PAIR_FOLLOWER_FACTOR``; METHODS §11).
PRIOR_EXCESS_SIGMAS = 3.0
#: With 3 views or more and a view beyond :data:`PRIOR_EXCESS_SIGMAS`: every view's prior weight times Tukey's
#: biweight ``(1 - (z/c)^2)^2`` of its correction's size ``z`` (in its own prior sigmas), at least
#: :data:`PRIOR_WEIGHT_FLOOR` (the datum never goes singular), re-solved until the weights settle.
PRIOR_TUKEY_C = 4.685
PRIOR_WEIGHT_FLOOR = 1e-4
PRIOR_MAX_REWEIGHT = 10
#: Reweighted re-solves at most; an estimate that has not settled by then is reported as not converged.
ROBUST_MAX_FITS = 40


class BundleProblem:
    """The bundle as a problem of the core's robust driver: a "point" is a ray (k = 2: sample, line);
    ``fit(point_weights)`` runs Gauss-Newton from the current state with the a-priori weights times the factors and
    returns the :class:`~gdal_gf4cal.estimation.Estimate` (residuals (n_rays, 2))."""

    k = 2

    def __init__(self, models, layout: ViewLayout, rays: Rays, state: State, wts: Weights, *, tol_px: float = 1e-5,
                 max_iter: int = 20, progress=None):
        self.models, self.layout, self.rays, self.state, self.base = models, layout, rays, state, wts
        self.n_points, self.n_params = rays.view.size, layout.n_params
        self.tol_px, self.max_iter, self.progress = tol_px, max_iter, progress
        self.solution = self.lin = None
        self.sd_factor = np.ones(self.n_points)
        self.refit_steps = 4                      # reweighted: usually one step lands (gauss_newton's warm)
        self.last_change = np.inf
        self.point_cov = None
        self.iterations, self.converged = 0, False

    def change(self, old: Estimate, new: Estimate) -> float:
        """How far a re-solve moved the corrections: the largest change of a view's ``(ds, dl)`` at the image's
        corners and centre (px); the robust driver stops reweighting below its ``tol``."""
        d = new.x - old.x
        out = 0.0
        for v in self.layout.views:
            w, h = self.layout.sizes[v]
            s, l = np.array([0.0, w, 0.0, w, 0.5 * w]), np.array([0.0, 0.0, h, h, 0.5 * h])
            a_s, a_l = self.layout.design(v, s, l)
            sl_s, sl_l = self.layout.slices(v)
            out = max(out, float(np.abs(a_s @ d[sl_s]).max()), float(np.abs(a_l @ d[sl_l]).max()))
        return out

    @property
    def sigma(self) -> np.ndarray:
        """A-priori σ of each ray (px)."""
        return self.rays.sigma

    def fit(self, point_weights=None) -> Estimate:
        pw = np.ones(self.n_points) if point_weights is None else np.asarray(point_weights, float)
        wts = replace(self.base, rays=self.base.rays * pw)
        # reweighted: a step that lands where its linear model said ends the fit (usually the first); so may the
        # robust driver's first fit (given weights): every reweighting steps on from there
        steps = self.max_iter if self.solution is None else self.refit_steps
        self.state, self.solution, self.lin, it, self.converged, self.last_change = gauss_newton(
            self.models, self.layout, self.rays, self.state, wts, tol_px=self.tol_px, max_iter=steps,
            progress=self.progress, lin=self.lin, warm=self.solution is not None or point_weights is not None)
        self.iterations += it
        lost = ~self.solution.ok & (np.bincount(self.rays.point, weights=(self.base.rays > 0).astype(float),
                                                minlength=self.rays.n_points) >= 2)
        if lost.any():                            # points the weights leave undetermined: from all their rays
            self.state = reintersect(self.models, self.layout, self.rays, self.state, self.base, lost)
            self.lin = project_all(self.models, self.layout, self.rays, self.state)
        return _estimate(self, wts)


def _ray_variance(pb: BundleProblem, w_rays: np.ndarray, rows=None):
    """``j^T N_pp^-1 j`` (n_rays, 2) of each ray through its point's own block at weights ``w_rays`` (the views'
    parameters held: the datum's uncertainty, shared by a point and the corrections, cancels in a residual), and
    which points the block determines; ``rows`` (bool, n_rays): only those rays' (the others 0)."""
    rays, jac = pb.rays, pb.lin.jac_points.transpose(2, 1, 0)          # (3, 2, n): the rays last
    jw = jac * w_rays
    npp = np.empty((rays.n_points, 3, 3))
    for a in range(3):                                   # the 6 distinct entries, one bincount each
        for b in range(a, 3):
            npp[:, a, b] = npp[:, b, a] = np.bincount(rays.point, weights=jw[a, 0] * jac[b, 0]
                                                      + jw[a, 1] * jac[b, 1], minlength=rays.n_points)
    npp[:, [0, 1, 2], [0, 1, 2]] += pb.base.ground
    inv, ok = block_inverse(npp)
    out = np.zeros((2, rays.view.size))
    sel = slice(None) if rows is None else np.flatnonzero(rows)
    j, pt = jac[:, :, sel], rays.point[sel]
    for a in range(3):                                   # j^T inv j from the 6 distinct entries of each inverse
        for b in range(a, 3):
            f = np.nan_to_num(inv[:, a, b])[pt] * (1.0 if a == b else 2.0)
            out[:, sel] += j[a] * j[b] * f
    return np.ascontiguousarray(out.T), ok, inv


def _estimate(pb: BundleProblem, wts: Weights) -> Estimate:
    """The Estimate at the problem's current solution (sigma0 and covariance through the core's
    :func:`~gdal_gf4cal.estimation.sigma0_and_cov`). Redundancy of a ray ``1 - w j^T N_pp^-1 j``; a ray left out
    is normalised by ``sqrt(1/w + j^T N_pp^-1 j)``, or, when its point is undetermined without it, as if in
    (:attr:`BundleProblem.sd_factor`: that standard deviation over the ray's σ)."""
    rays, sol = pb.rays, pb.solution
    v = rays.meas - pb.lin.pred
    w0 = np.stack([pb.base.rays, pb.base.rays], axis=1)                # (n, 2): both axes
    w2 = np.stack([wts.rays, wts.rays], axis=1)
    q, ok, pb.point_cov = _ray_variance(pb, wts.rays)
    lone = (wts.rays == 0) & ~ok[rays.point]              # rays left out whose point is undetermined without them
    q0 = _ray_variance(pb, pb.base.rays, lone)[0] if lone.any() else np.zeros_like(q)
    red = np.where(w2 > 0, np.clip(1.0 - w2 * q, 0.0, 1.0), 0.0)
    var = np.where(w2 > 0, np.maximum(red, 0.05) / np.maximum(w2, 1e-300),
                   np.where(ok[rays.point, None], 1.0 / np.maximum(w0, 1e-300) + q,
                            np.maximum(1.0 / np.maximum(w0, 1e-300) - q0, 0.05 / np.maximum(w0, 1e-300))))
    pb.sd_factor = np.sqrt(var * np.maximum(w0, 1e-300)).max(axis=1)
    vtpv = float(np.sum(w2 * v * v) + np.sum(wts.prior * pb.state.x ** 2))
    n_obs = int(np.count_nonzero(w2)) + int(np.count_nonzero(wts.ground)) + int(np.count_nonzero(wts.prior))
    dof = n_obs - 3 * int(sol.ok.sum()) - pb.n_params
    sigma0, cov = sigma0_and_cov(np.linalg.inv(sol.cov_global), vtpv, dof)
    s0 = sigma0 if np.isfinite(sigma0) else 1.0
    with np.errstate(invalid="ignore", divide="ignore"):
        norm = v / (s0 * np.sqrt(var))
    lay = pb.layout
    return Estimate(names=lay.names, x=pb.state.x.copy(), cov=cov, sigma0=float(s0), dof=int(dof),
                    redundancy=red, residuals=v, normalised=norm, weights=w2,
                    blocks={vw: slice(lay.offset[vw], lay.offset[vw] + lay.models_used[vw].n_params)
                            for vw in lay.views}, iterations=pb.iterations)


def _robust(pb: BundleProblem):
    """The core's one robust driver on whole rays: radial Huber down-weighting, then rejection beyond 4 robust
    sigmas (each ray's σ times its redundancy's square root); check rays are tested, never used."""
    norm = RadialHuber(sigma=lambda p, e: p.rays.sigma * p.sd_factor, min_points=2,
                       too_few="; the ties disagree beyond their stated sigma: check the image ids and the ties")
    return robust_fit(pb, norm=norm, start=None, candidates=pb.rays.control, max_iter=ROBUST_MAX_FITS,
                      tol=ROBUST_TOL_PX, phase1_tol=ROBUST_PHASE1_TOL_PX)


def adjust_views(observations, models: Mapping[str, Any], *, dem=None, model: str = "affine", sizes=None,
                 prior_sigma_px=None, robust: bool = True, progress=None, gcp_sigma_m: float = 0.01,
                 dem_sigma_m: float = DEFAULT_DEM_SIGMA_M, tol_px: float = 1e-5, max_iter: int = 20) -> BundleEstimate:
    """Bundle adjustment of separate views from their RPCs (METHODS §11).

    Parameters
    ----------
    observations : DataFrame
        The observation table (:mod:`gdal_gf4cal.observations`): ties (any number of views per point) and GCPs
        (``role`` control or check), ``sample, line`` in GDAL's pixel convention, ``sigma`` px.
    models : mapping view -> RPCModel
        The vendor RPCs, keyed by the table's ``image_id``.
    dem : DEM, path, number or None
        Starting heights of the ties whose rays are nearly parallel
        (:data:`~gdal_gf4cal.bundle.start.PARALLEL_SIGMA_M`), and every tie's height prior ``DEM(lon, lat) ±
        dem_sigma_m``, re-sampled at the tie's current ground at each Gauss-Newton step: it fixes the
        along-epipolar part of a relative bias (a height shift of all ties, which ties alone cannot see). Without
        a DEM the views' priors alone hold the datum.
    model : 'translation' | 'shift-drift' | 'affine'
        The per-view correction (METHODS §4.1); slope terms fall back to a translation, with a note, in a view whose
        ties do not span :data:`~gdal_gf4cal.bundle.model.MIN_SPAN` of the image.
    sizes : mapping view -> (width, height), optional
        Image sizes (default: the RPC's).
    prior_sigma_px : float or mapping view -> float, optional
        σ of the datum pseudo-observations ``Δ-parameter = 0 ± σ`` (default: ERR_BIAS over the pixel size, else
        :data:`~gdal_gf4cal.bundle.model.DEFAULT_PRIOR_M` over the pixel size).
    robust : bool
        Down-weight and reject blunder rays through the core's robust driver.
    gcp_sigma_m : float
        σ of a control GCP's ground coordinates (m).
    dem_sigma_m : float
        σ of the DEM's height prior on every tie (m; default
        :data:`~gdal_gf4cal.bundle.start.DEFAULT_DEM_SIGMA_M`, a global DEM's typical absolute accuracy).

    Raises
    ------
    BundleError
        Bad input, one line (see :mod:`gdal_gf4cal.bundle.inputs`).
    """
    sizes = view_sizes(models, sizes)
    dem_obj = DEM.from_user_input(dem) if dem is not None else None
    tab, codes = check_inputs(observations, models, sizes, dem=dem_obj, return_codes=True)
    layout = make_layout(tab, models, sizes, model, prior_sigma_px, codes)
    rays = make_rays(tab, layout, codes)
    ground0, _, notes = start_ground(models, layout, rays, dem_obj)
    wts = base_weights(models, layout, rays, ground0, dem_obj, gcp_sigma_m=gcp_sigma_m, dem_sigma_m=dem_sigma_m)
    state0 = State(np.zeros(layout.n_params), ground0)
    before = project_all(models, layout, rays, state0)
    pb = BundleProblem(models, layout, rays, state0, wts, tol_px=tol_px, max_iter=max_iter, progress=progress)
    pb.lin = before                                   # the first Gauss-Newton step's linearisation too
    est = _robust(pb) if robust else pb.fit()
    est = _robust_priors(pb, est, robust)
    return _result(est, pb, tab, before, ground0, layout.notes + notes)


def _robust_priors(pb: BundleProblem, est: Estimate, robust: bool) -> Estimate:
    """Views' priors that do not follow one view's blunder-sized bias (METHODS §11): with 3 views or more and a
    view whose correction exceeds :data:`PRIOR_EXCESS_SIGMAS` of its prior, the priors re-weighted by Tukey's
    biweight of each view's correction (:data:`PRIOR_TUKEY_C`, floor :data:`PRIOR_WEIGHT_FLOOR`) and the block
    re-solved until the weights settle: the agreeing views hold the datum, the odd one takes its bias whole (a
    warning names it). With 2 views nothing tells which one is off: by default the pair follows its first view
    (``model.PAIR_FOLLOWER_FACTOR``); priors the user made equal split it, and :func:`prior_excess` says so."""
    lay = pb.layout
    if len(lay.views) < 3 or not prior_excess(lay, est.x):
        return est
    given, w_old = lay.prior_px.copy(), np.ones(lay.n_params)
    for _ in range(PRIOR_MAX_REWEIGHT):
        w = np.ones(lay.n_params)
        for v, (_, _, z) in view_excess(lay, est.x, given).items():
            w[lay.offset[v]:lay.offset[v] + lay.models_used[v].n_params] = max(
                float(tukey_weights(z, PRIOR_TUKEY_C)), PRIOR_WEIGHT_FLOOR)
        if np.max(np.abs(w - w_old)) < 1e-3:
            break
        w_old = w
        lay.prior_px = given / np.sqrt(w)
        pb.base = replace(pb.base, prior=1.0 / lay.prior_px ** 2)
        est = _robust(pb) if robust else pb.fit()
    odd = [f"{v} ({ds:+.1f}, {dl:+.1f}) px, {z:.1f} sigmas of its {given[lay.offset[v]]:.3g} px prior"
           for v, (ds, dl, z) in view_excess(lay, est.x, given).items() if z > PRIOR_EXCESS_SIGMAS]
    if odd:
        est.warnings.append(f"view(s) {'; '.join(odd)}: beyond what the other views agree on (a blunder-sized RPC "
                            "bias?): their prior down-weighted (Tukey), the block held by the agreeing views")
    return est


def _table(tab: pd.DataFrame, preds, est: Estimate) -> pd.DataFrame:
    """The observations with ``pred_/res_{sample,line}_{before,after}`` (``preds``: name -> (n, 2), table order),
    ``weight``, ``outlier``, ``outlier_level``: one new frame, its columns consolidated once (the views' rows are
    taken from it next: a frame of many blocks would consolidate then, a copy of the whole table)."""
    new = {c: tab[c] for c in tab.columns}
    s, l = tab["sample"].to_numpy(float), tab["line"].to_numpy(float)
    for name, pred in preds.items():
        new[f"pred_sample_{name}"], new[f"pred_line_{name}"] = pred[:, 0], pred[:, 1]
        new[f"res_sample_{name}"], new[f"res_line_{name}"] = s - pred[:, 0], l - pred[:, 1]
    new["weight"] = est.weights[:, 0]
    flag = np.zeros(len(tab), bool) if est.outlier is None else np.asarray(est.outlier, bool)
    new["outlier"] = flag
    lvl = est.outlier_level if est.outlier_level is not None else np.full(len(tab), "")
    new["outlier_level"] = np.where(flag, np.asarray(lvl, str), "")
    return pd.DataFrame(new, index=tab.index)


#: The Estimate's per-ray arrays, in the rays' order (by view, then point) during the fits, returned in the table's.
_PER_RAY = ("redundancy", "residuals", "normalised", "weights", "outlier", "outlier_level", "point_weights")


def _in_table_order(est: Estimate, rays) -> Estimate:
    n = rays.view.size
    for f in _PER_RAY:
        a = getattr(est, f)
        if a is not None and np.ndim(a) >= 1 and len(a) == n:
            setattr(est, f, rays.to_table_order(np.asarray(a)))
    z = est.norm_info.get("z")
    if z is not None and np.ndim(z) == 1 and len(z) == n:
        est.norm_info["z"] = rays.to_table_order(np.asarray(z))
    return est


def _points(pb: BundleProblem, ground0: np.ndarray, sigma0: float) -> pd.DataFrame:
    """Ground of every point after and before, views seeing it, a-posteriori σ (m) east, north, up given the
    corrections (the relative precision of the intersection)."""
    rays, g = pb.rays, pb.state.ground
    cov = pb.point_cov * sigma0 ** 2
    sd = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0))
    return pd.DataFrame({"point_id": rays.point_ids, "kind": np.where(rays.point_is_gcp, "gcp", "tie"),
                         "lon": g[:, 0], "lat": g[:, 1], "h": g[:, 2], "lon_before": ground0[:, 0],
                         "lat_before": ground0[:, 1], "h_before": ground0[:, 2],
                         "n_views": np.bincount(rays.point, minlength=rays.n_points),
                         "sigma_e_m": sd[:, 0], "sigma_n_m": sd[:, 1], "sigma_u_m": sd[:, 2]})


def _result(est: Estimate, pb: BundleProblem, tab, before, ground0, notes: List[str]) -> BundleEstimate:
    layout, rays = pb.layout, pb.rays
    after = pb.lin                                    # the predictions at the final state (one projection fewer)
    used = (est.weights[:, 0] > 0) & ~(np.zeros(rays.view.size, bool) if est.outlier is None
                                       else np.asarray(est.outlier, bool))
    used_b = used if used.any() else rays.control
    rep = {"before": reprojection(rays.meas - before.pred, rays, layout, used_b),
           "after": reprojection(rays.meas - after.pred, rays, layout, used_b)}
    drift, drift_enu = datum_drift(ground0, pb.state.ground, np.flatnonzero(~rays.point_is_gcp))
    est = _in_table_order(est, rays)
    table = _table(tab, {"before": rays.to_table_order(before.pred), "after": rays.to_table_order(after.pred)}, est)
    view = rays.to_table_order(rays.view)
    by_view = np.argsort(view, kind="stable")                           # each view's rows in table order
    cut = np.searchsorted(view[by_view], np.arange(len(layout.views) + 1))
    corrections = {v: view_correction(layout, v, est.x, est.cov, est.sigma0, table, by_view[cut[j]:cut[j + 1]])
                   for j, v in enumerate(layout.views)}
    out = BundleEstimate(**{f: getattr(est, f) for f in Estimate.__dataclass_fields__})
    out.notes = list(est.notes) + notes
    out.views, out.corrections = list(layout.views), corrections
    out.model_used = {v: layout.models_used[v].name for v in layout.views}
    out.points, out.reprojection, out.table = _points(pb, ground0, est.sigma0), rep, table
    out.datum_drift_m, out.datum_drift_enu_m = drift, drift_enu
    out.prior_px, out.sizes, out.reduced_size = layout.prior_px.copy(), dict(layout.sizes), int(layout.n_params)
    robust = est.point_weights is not None
    settled = not robust or int(est.iterations) < ROBUST_MAX_FITS
    out.converged = bool(pb.converged or pb.last_change < ROBUST_TOL_PX)      # Gauss-Newton at its solution
    if not settled:
        out.warnings.append(f"the robust reweighting did not settle in {ROBUST_MAX_FITS} re-solves (the corrections "
                            f"kept moving by more than {ROBUST_TOL_PX:g} px)")
    out.iterations = int(pb.iterations)
    excess = prior_excess(layout, est.x)
    if excess:
        out.warnings.append(excess)
    return out


def view_excess(layout: ViewLayout, x: np.ndarray, prior_px=None):
    """``{view: (ds, dl, z)}``: each view's correction at its image centre (px) and its size in units of the view's
    prior σ (``prior_px`` per parameter, default :attr:`ViewLayout.prior_px`)."""
    prior_px = layout.prior_px if prior_px is None else prior_px
    out = {}
    for v in layout.views:
        w, h = layout.sizes[v]
        a_s, a_l = layout.design(v, [0.5 * w], [0.5 * h])
        sl_s, sl_l = layout.slices(v)
        ds, dl = float(a_s[0] @ x[sl_s]), float(a_l[0] @ x[sl_l])
        out[v] = (ds, dl, float(np.hypot(ds, dl) / prior_px[layout.offset[v]]))
    return out


def prior_excess(layout: ViewLayout, x: np.ndarray) -> str:
    """A warning (or ``""``) naming the views whose correction at the image centre exceeds
    :data:`PRIOR_EXCESS_SIGMAS` times their prior: the split of such a bias between the views is set by the priors
    alone; it moves the block (with a DEM on sloping terrain, also the along-epipolar relative correction)."""
    over = [f"{v} ({ds:+.1f}, {dl:+.1f}) px against {layout.prior_px[layout.offset[v]]:.3g} px"
            for v, (ds, dl, z) in view_excess(layout, x).items() if z > PRIOR_EXCESS_SIGMAS]
    if not over:
        return ""
    return (f"corrections beyond {PRIOR_EXCESS_SIGMAS:g} prior sigmas: {'; '.join(over)}: the views disagree more "
            "than their priors allow (one RPC with a blunder-sized bias?) and the priors split that between the views, "
            "which moves the block; give the RPCs you trust a small prior and the suspect one a large one "
            "(--prior-sigma VIEW=PX, prior_sigma_px={view: px})")
