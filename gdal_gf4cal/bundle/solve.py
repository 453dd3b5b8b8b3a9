"""Gauss-Newton of the bundle adjustment with the points eliminated by Schur complement (METHODS §11).

Unknowns: the views' correction parameters (the reduced system: a few per view, whatever the number of points) and
each point's ground position, stepped in local metres (east, north, up) so its 3 x 3 block is well conditioned.
Rows per point (:mod:`~gdal_gf4cal.bundle.model`): its rays (sample, line) and three ground rows (a control GCP's
known ground ± ``gcp_sigma_m``; every tie's height ± ``dem_sigma_m`` from the DEM where one is given, re-sampled
at the tie's current ground before each step: :func:`resample_dem`). The
datum: one pseudo-observation per correction parameter, ``0 ± prior`` (the ``extra`` rows of
:func:`gdal_gf4cal.estimation.solve_with_points`).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Dict, Mapping, Optional

import numpy as np
import scipy.sparse as sp

from ..estimation import IndexedJacobian, solve_with_points
from ..geodesy import metres_per_degree
from .model import Rays, ViewLayout

__all__ = ["State", "Linearisation", "linearise", "gauss_newton", "project_all", "resample_dem"]


@dataclass
class State:
    """Current values: ``x`` (correction parameters), ``ground`` (n_points, 3) lon, lat, h."""

    x: np.ndarray
    ground: np.ndarray


@dataclass
class Linearisation:
    """Predictions and derivatives at one state: ``pred`` (n_rays, 2) corrected positions, ``rpc_pred`` (the RPC's
    own), ``jac_points`` (n_rays, 2, 3) px per metre (east, north, up), ``design`` (view -> rows, A_s, A_l)."""

    pred: np.ndarray
    rpc_pred: np.ndarray
    jac_points: Optional[np.ndarray]
    design: Dict[int, Any] = field(default_factory=dict)


def project_all(models: Mapping[str, Any], layout: ViewLayout, rays: Rays, state: State,
                jacobian: bool = True) -> Linearisation:
    """Corrected predictions of every ray (and their derivatives): one vectorised call per view."""
    n = rays.view.size
    pred, rpc_pred = np.empty((n, 2)), np.empty((n, 2))
    jp = np.empty((n, 2, 3)) if jacobian else None
    design: Dict[int, Any] = {}
    g = state.ground[rays.point]
    for j, v in enumerate(layout.views):
        rows = np.flatnonzero(rays.view == j)
        if rows.size == 0:
            continue
        lon, lat, h = g[rows, 0], g[rows, 1], g[rows, 2]
        s, l = models[v].project(lon, lat, h)
        s, l = np.asarray(s, float), np.asarray(l, float)
        ds, dl, dj = layout.correction(v, state.x, s, l)
        rpc_pred[rows, 0], rpc_pred[rows, 1] = s, l
        pred[rows, 0], pred[rows, 1] = s + ds, l + dl
        if jacobian:
            mx, my = metres_per_degree(lat, h)
            jac = np.asarray(models[v].project_jacobian(lon, lat, h), float).reshape(-1, 2, 3)
            jac = jac / np.stack([mx, my, np.ones_like(mx)], axis=1)[:, None, :]
            jp[rows] = jac + np.matmul(dj, jac)
            design[j] = (rows,) + layout.design(v, s, l)
    return Linearisation(pred, rpc_pred, jp, design)


def _global_jacobian(layout: ViewLayout, rays: Rays, lin: Linearisation) -> IndexedJacobian:
    """``d(pred)/d(x)`` of every padded point row by column index (rows ``2 slot + axis`` of each point): a ray
    touches its view's sample (or line) terms only."""
    c = max(max(len(t) for t in layout.models_used[v].terms) for v in layout.views)
    n_rows = rays.n_points * rays.rows_per_point
    cols, vals = np.zeros((n_rows, c), int), np.zeros((n_rows, c))
    for j, (rows, a_s, a_l) in lin.design.items():
        for axis, a, sl in zip((0, 1), (a_s, a_l), layout.slices(layout.views[j])):
            flat = rays.flat_rows(axis)[rows]
            cols[flat, :sl.stop - sl.start] = np.arange(sl.start, sl.stop)
            vals[flat, :sl.stop - sl.start] = a
    shape = (rays.n_points, rays.rows_per_point, c)
    return IndexedJacobian(cols.reshape(shape), vals.reshape(shape), layout.n_params)


@dataclass
class Weights:
    """Weights of one solve: ``rays`` (n_rays,) on both axes (0: out), ``ground`` (n_points, 3) of the ground
    rows, ``prior`` (n_params,) of the datum pseudo-observations; ``ground_obs`` (n_points, 3) what the ground rows
    observe (lon, lat, h; NaN where unweighted); ``dem`` and ``dem_points`` (n_points bool): the DEM whose height
    at the current ground the height rows of those points observe (:func:`resample_dem`)."""

    rays: np.ndarray
    ground: np.ndarray
    prior: np.ndarray
    ground_obs: np.ndarray
    dem: Any = None
    dem_points: Optional[np.ndarray] = None

    def subset(self, points: np.ndarray, rays: np.ndarray) -> "Weights":
        """The weights of the points ``points`` (bool) and their rays ``rays`` (bool)."""
        dp = None if self.dem_points is None else self.dem_points[points]
        return Weights(self.rays[rays], self.ground[points], self.prior, self.ground_obs[points], self.dem, dp)


def resample_dem(wts: Weights, ground: np.ndarray) -> Weights:
    """``wts`` with the DEM height rows observing the DEM at the points' current ``ground`` (lon, lat): the height
    a tie should have where it now is, not where the uncorrected rays put it (a biased view moves the start by tens
    of metres). Points off the DEM keep their previous target."""
    if wts.dem is None or wts.dem_points is None or not wts.dem_points.any():
        return wts
    idx = np.flatnonzero(wts.dem_points)
    h = np.asarray(wts.dem.sample(ground[idx, 0], ground[idx, 1], nodata="nan"), float)
    obs = wts.ground_obs.copy()
    ok = np.isfinite(h)
    obs[idx[ok], 0], obs[idx[ok], 1], obs[idx[ok], 2] = ground[idx[ok], 0], ground[idx[ok], 1], h[ok]
    return replace(wts, ground_obs=obs)


def linearise(models, layout: ViewLayout, rays: Rays, state: State, wts: Weights):
    """The padded point-block system at ``state``: ``(jac_points, residuals, weights, jac_global, extra, lin)``."""
    lin = project_all(models, layout, rays, state)
    n_pts, r_pp, k2 = rays.n_points, rays.rows_per_point, 2 * rays.k
    jp = np.zeros((n_pts * r_pp, 3))
    res = np.zeros(n_pts * r_pp)
    w = np.zeros(n_pts * r_pp)
    v = rays.meas - lin.pred
    for axis in (0, 1):
        flat = rays.flat_rows(axis)
        jp[flat] = lin.jac_points[:, axis, :]
        res[flat] = v[:, axis]
        w[flat] = wts.rays
    jp, res, w = jp.reshape(n_pts, r_pp, 3), res.reshape(n_pts, r_pp), w.reshape(n_pts, r_pp)
    mx, my = metres_per_degree(state.ground[:, 1], state.ground[:, 2])
    to_m = np.stack([mx, my, np.ones_like(mx)], axis=1)
    delta = np.nan_to_num((wts.ground_obs - state.ground) * to_m)
    for c in range(3):
        jp[:, k2 + c, c] = 1.0
        res[:, k2 + c] = delta[:, c]
        w[:, k2 + c] = wts.ground[:, c]

    jg = _global_jacobian(layout, rays, lin)
    extra = (sp.identity(layout.n_params, format="csr"), -state.x, wts.prior)
    return jp, res, w, jg, extra, lin


def step(models, layout: ViewLayout, rays: Rays, state: State, wts: Weights, covariance: bool = False):
    """One Gauss-Newton step: ``(new_state, change_px, solution, lin)`` (``change_px``: the largest move of a
    ray's prediction)."""
    jp, res, w, jg, extra, lin = linearise(models, layout, rays, state, wts)
    sol = solve_with_points(jp, res, w, jg, extra=extra, covariance=covariance)
    dp = np.where(np.isfinite(sol.dx_points), sol.dx_points, 0.0)
    mx, my = metres_per_degree(state.ground[:, 1], state.ground[:, 2])
    ground = state.ground + dp / np.stack([mx, my, np.ones_like(mx)], axis=1)
    x = state.x + sol.dx_global
    gm = np.einsum("nkc,nkc->nk", jg.vals, sol.dx_global[jg.cols])
    ray_g = np.stack([gm[rays.point, 2 * rays.slot], gm[rays.point, 2 * rays.slot + 1]], axis=1)
    move = np.abs(np.einsum("nrq,nq->nr", lin.jac_points, dp[rays.point]) + ray_g)
    used = wts.rays > 0
    change = float(move[used].max()) if used.any() else 0.0
    return State(x, ground), change, sol, lin


def reintersect(models, layout: ViewLayout, rays: Rays, state: State, wts: Weights, points: np.ndarray,
                iterations: int = 4) -> State:
    """The ground of the points ``points`` (bool) from all their rays at the weights ``wts`` with the corrections
    held: points the robust weights leave undetermined get residuals that mean something (METHODS §7)."""
    if not points.any():
        return state
    sub = rays.subset(points)
    keep = np.flatnonzero(points)
    sw = wts.subset(points, np.isin(rays.point, keep))
    g = state.ground[points].copy()
    for _ in range(iterations):
        jp, res, w, _, _, _ = linearise(models, layout, sub, State(state.x, g), resample_dem(sw, g))
        sol = solve_with_points(jp, res, w, covariance=False)
        dp = np.where(np.isfinite(sol.dx_points), sol.dx_points, 0.0)
        mx, my = metres_per_degree(g[:, 1], g[:, 2])
        g = g + dp / np.stack([mx, my, np.ones_like(mx)], axis=1)
    ground = state.ground.copy()
    ground[points] = g
    return State(state.x, ground)


def gauss_newton(models, layout: ViewLayout, rays: Rays, state: State, wts: Weights, *, tol_px: float = 1e-5,
                 max_iter: int = 20, progress=None):
    """Iterate :func:`step` until the predictions move less than ``tol_px`` (at most ``max_iter`` steps); the
    predictions and derivatives at the solution; the DEM's height targets re-sampled at the current ground before
    each step (:func:`resample_dem`). Returns ``(state, solution, lin, iterations, converged, change)`` (the
    solution of the last step: its ``cov_global`` is the reduced system's unit-weight inverse)."""
    converged = False
    it = 0
    sol = None
    change = np.inf
    for it in range(1, max_iter + 1):
        state, change, sol, _ = step(models, layout, rays, state, resample_dem(wts, state.ground))
        if progress is not None:
            progress(min(it / max_iter, 0.99), f"bundle iteration {it}: largest change {change:.3g} px")
        if change < tol_px:
            converged = True
            break
    return state, sol, project_all(models, layout, rays, state), it, converged, change
