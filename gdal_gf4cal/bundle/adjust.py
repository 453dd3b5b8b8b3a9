"""``adjust_views``: bundle adjustment of separate views from their RPCs (METHODS §11, Grodecki & Dial 2003)."""
from __future__ import annotations

from typing import Any, Dict, List, Mapping, Optional

import numpy as np
import pandas as pd

from ..dem import DEM
from ..estimation import Estimate
from .inputs import check_inputs, make_layout, make_rays, view_sizes
from .model import Rays, ViewLayout
from .result import BundleEstimate, datum_drift, reprojection, view_correction
from .solve import State, Weights, gauss_newton, project_all
from .start import base_weights, start_ground

__all__ = ["adjust_views", "BundleProblem"]


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
        self.iterations, self.converged = 0, False

    @property
    def sigma(self) -> np.ndarray:
        """A-priori σ of each ray (px)."""
        return self.rays.sigma

    def fit(self, point_weights=None) -> Estimate:
        pw = np.ones(self.n_points) if point_weights is None else np.asarray(point_weights, float)
        wts = Weights(self.base.rays * pw, self.base.ground, self.base.prior, self.base.ground_obs)
        self.state, self.solution, self.lin, it, self.converged = gauss_newton(
            self.models, self.layout, self.rays, self.state, wts, tol_px=self.tol_px, max_iter=self.max_iter,
            progress=self.progress)
        self.iterations += it
        return _estimate(self, wts)


def _estimate(pb: BundleProblem, wts: Weights) -> Estimate:
    """The Estimate at the problem's current solution (sigma0 and covariance through the core)."""
    from ..estimation import lsq
    rays, sol = pb.rays, pb.solution
    v = rays.meas - pb.lin.pred
    w2 = np.repeat(wts.rays[:, None], 2, axis=1)
    ok_pts = sol.ok
    red_pts = np.einsum("nai,nij,naj->na", pb.lin.jac_points, sol.cov_points[rays.point], pb.lin.jac_points)
    red = np.where(w2 > 0, np.clip(1.0 - w2 * np.nan_to_num(red_pts, nan=1.0 / np.maximum(w2, 1e-300)), 0.0, 1.0),
                   0.0)
    vtpv = float(np.sum(w2 * v * v) + np.sum(wts.prior * pb.state.x ** 2))
    n_obs = int(np.count_nonzero(w2)) + int(np.count_nonzero(wts.ground)) + int(np.count_nonzero(wts.prior))
    dof = n_obs - 3 * int(ok_pts.sum()) - pb.n_params
    s_mat = np.linalg.inv(sol.cov_global)
    sigma0, cov = lsq.sigma0_and_cov(s_mat, vtpv, dof) if hasattr(lsq, "sigma0_and_cov") else \
        _sigma0_and_cov(sol.cov_global, vtpv, dof)
    s0 = sigma0 if np.isfinite(sigma0) else 1.0
    sd = np.sqrt(np.where(w2 > 0, red / np.maximum(w2, 1e-300), np.nan))
    with np.errstate(invalid="ignore", divide="ignore"):
        norm = np.where(sd > 1e-12, v / (s0 * sd), np.nan)
    return Estimate(names=pb.layout.names, x=pb.state.x.copy(), cov=cov, sigma0=float(s0), dof=int(dof),
                    redundancy=red, residuals=v, normalised=norm, weights=w2,
                    blocks={vw: slice(pb.layout.offset[vw], pb.layout.offset[vw] + pb.layout.models_used[vw].n_params)
                            for vw in pb.layout.views}, iterations=pb.iterations)


def _sigma0_and_cov(cov_unit, vtpv, dof):
    """Until the core's ``sigma0_and_cov`` is merged (same formula)."""
    sigma0 = float(np.sqrt(vtpv / dof)) if dof > 0 else float("nan")
    return sigma0, (cov_unit if dof <= 0 else sigma0 ** 2 * cov_unit)


def _robust(pb: BundleProblem):
    """The core's one robust driver on whole rays (radial Huber, then rejection); plain least squares without it."""
    try:
        from ..estimation import RadialHuber, robust_fit
    except ImportError:                                           # the driver is not merged yet
        return pb.fit(), ["robust driver unavailable: plain least squares"]
    est = robust_fit(pb, norm=RadialHuber(sigma=lambda p, e: p.sigma * np.sqrt(np.clip(
        e.redundancy.max(axis=1) if e.redundancy.ndim == 2 else e.redundancy, 0.05, 1.0))),
        start=None, max_iter=30, tol=1e-4)
    return est, []


def adjust_views(observations, models: Mapping[str, Any], *, dem=None, model: str = "affine", sizes=None,
                 prior_sigma_px=None, robust: bool = True, progress=None, gcp_sigma_m: float = 0.01,
                 dem_sigma_m: float = 50.0, tol_px: float = 1e-5, max_iter: int = 20) -> BundleEstimate:
    """Bundle adjustment of separate views from their RPCs (METHODS §11).

    Parameters
    ----------
    observations : DataFrame
        The observation table (:mod:`gdal_gf4cal.observations`): ties (any number of views per point) and GCPs
        (``role`` control or check), ``sample, line`` in GDAL's pixel convention, ``sigma`` px.
    models : mapping view -> RPCModel
        The vendor RPCs, keyed by the table's ``image_id``.
    dem : DEM, path, number or None
        Starting heights where rays are nearly parallel, and a weak height prior (± ``dem_sigma_m``) on the ties.
    model : 'translation' | 'shift-drift' | 'affine'
        The per-view correction (METHODS §4.1); slope terms fall back to a translation, with a note, in a view whose
        ties do not span :data:`~gdal_gf4cal.bundle.model.MIN_SPAN` of the image.
    sizes : mapping view -> (width, height), optional
        Image sizes (default: the RPC's).
    prior_sigma_px : float or mapping view -> float, optional
        σ of the datum pseudo-observations ``Δ-parameter = 0 ± σ`` (default: ERR_BIAS over the pixel size, else
        :data:`~gdal_gf4cal.bundle.model.DEFAULT_PRIOR_PX`).
    robust : bool
        Down-weight and reject blunder rays through the core's robust driver.
    gcp_sigma_m : float
        σ of a control GCP's ground coordinates (m).

    Raises
    ------
    BundleError
        Bad input, one line (see :mod:`gdal_gf4cal.bundle.inputs`).
    """
    sizes = view_sizes(models, sizes)
    dem_obj = DEM.from_user_input(dem) if dem is not None else None
    tab = check_inputs(observations, models, sizes, dem=dem_obj)
    layout = make_layout(tab, models, sizes, model, prior_sigma_px)
    rays = make_rays(tab, layout)
    ground0, notes = start_ground(models, layout, rays, dem_obj)
    wts = base_weights(models, layout, rays, ground0, dem_obj, gcp_sigma_m=gcp_sigma_m, dem_sigma_m=dem_sigma_m)
    state0 = State(np.zeros(layout.n_params), ground0)
    before = project_all(models, layout, rays, state0, jacobian=False)
    pb = BundleProblem(models, layout, rays, state0, wts, tol_px=tol_px, max_iter=max_iter, progress=progress)
    est, more = _robust(pb) if robust else (pb.fit(), [])
    return _result(est, pb, tab, before, ground0, layout.notes + notes + more)


def _table(tab: pd.DataFrame, before, after, est: Estimate) -> pd.DataFrame:
    out = tab.copy()
    for name, lin in (("before", before), ("after", after)):
        out[f"pred_sample_{name}"], out[f"pred_line_{name}"] = lin.pred[:, 0], lin.pred[:, 1]
        out[f"res_sample_{name}"] = out["sample"].to_numpy(float) - lin.pred[:, 0]
        out[f"res_line_{name}"] = out["line"].to_numpy(float) - lin.pred[:, 1]
    out["weight"] = est.weights[:, 0]
    flag = np.zeros(len(out), bool) if est.outlier is None else np.asarray(est.outlier, bool)
    out["outlier"] = flag
    lvl = est.outlier_level if est.outlier_level is not None else np.full(len(out), "")
    out["outlier_level"] = np.where(flag, np.asarray(lvl, str), "")
    return out


def _points(pb: BundleProblem, ground0: np.ndarray, sigma0: float) -> pd.DataFrame:
    """Ground of every point after and before, views seeing it, a-posteriori σ (m) east, north, up."""
    rays, g = pb.rays, pb.state.ground
    cov = pb.solution.cov_points * sigma0 ** 2
    sd = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0))
    return pd.DataFrame({"point_id": rays.point_ids, "kind": np.where(rays.point_is_gcp, "gcp", "tie"),
                         "lon": g[:, 0], "lat": g[:, 1], "h": g[:, 2], "lon_before": ground0[:, 0],
                         "lat_before": ground0[:, 1], "h_before": ground0[:, 2],
                         "n_views": np.bincount(rays.point, minlength=rays.n_points),
                         "sigma_e_m": sd[:, 0], "sigma_n_m": sd[:, 1], "sigma_u_m": sd[:, 2]})


def _result(est: Estimate, pb: BundleProblem, tab, before, ground0, notes: List[str]) -> BundleEstimate:
    layout, rays = pb.layout, pb.rays
    after = project_all(pb.models, layout, rays, pb.state, jacobian=False)
    table = _table(tab, before, after, est)
    used = (est.weights[:, 0] > 0) & ~table["outlier"].to_numpy(bool)
    used_b = used if used.any() else rays.control
    rep = {"before": reprojection(rays.meas - before.pred, rays, layout, used_b),
           "after": reprojection(rays.meas - after.pred, rays, layout, used_b)}
    drift, drift_enu = datum_drift(ground0, pb.state.ground, np.flatnonzero(~rays.point_is_gcp))
    corrections = {v: view_correction(layout, v, est.x, est.cov, est.sigma0, table) for v in layout.views}
    out = BundleEstimate(**{f: getattr(est, f) for f in Estimate.__dataclass_fields__})
    out.notes = list(est.notes) + notes
    out.views, out.corrections = list(layout.views), corrections
    out.model_used = {v: layout.models_used[v].name for v in layout.views}
    out.points, out.reprojection, out.table = _points(pb, ground0, est.sigma0), rep, table
    out.datum_drift_m, out.datum_drift_enu_m = drift, drift_enu
    out.prior_px, out.sizes, out.reduced_size = layout.prior_px.copy(), dict(layout.sizes), int(layout.n_params)
    out.converged, out.iterations = bool(pb.converged), int(pb.iterations)
    return out
