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

from dataclasses import dataclass, replace
from typing import Any, Mapping, Optional

import numpy as np
import scipy.sparse as sp

from ..estimation.indexed import solve_rows
from ..estimation.schur import PointSolution
from ..geodesy import metres_per_degree
from ..threads import map_blocks
from .model import Rays, ViewLayout

__all__ = ["State", "Linearisation", "System", "linearise", "gauss_newton", "project_all", "resample_dem"]


@dataclass
class State:
    """Current values: ``x`` (correction parameters), ``ground`` (n_points, 3) lon, lat, h."""

    x: np.ndarray
    ground: np.ndarray


@dataclass
class Linearisation:
    """Predictions and derivatives at one state: ``pred`` (n_rays, 2) corrected positions, ``rpc_pred`` (the RPC's
    own), ``jac_points`` (n_rays, 2, 3) px per metre (east, north, up), ``cols`` / ``vals`` (2, n_rays, c): the
    parameters each ray's sample (0) and line (1) correction uses and their derivatives (padded with 0). The
    derivatives are views of arrays with the rays last (``(3, 2, n_rays)``, ``(c, 2, n_rays)``): the arithmetic
    over them runs along the rays, not over triples (several times faster in NumPy)."""

    pred: np.ndarray
    rpc_pred: np.ndarray
    jac_points: Optional[np.ndarray]
    cols: Optional[np.ndarray] = None
    vals: Optional[np.ndarray] = None


def project_all(models: Mapping[str, Any], layout: ViewLayout, rays: Rays, state: State,
                jacobian: bool = True) -> Linearisation:
    """Corrected predictions of every ray (and their derivatives): one vectorised call per view (its rays one
    slice when sorted by view: :meth:`Rays.view_rows`), the views over the thread pool
    (:func:`~gdal_gf4cal.threads.map_blocks`; each view's numbers as computed alone: the same bits whatever the
    threads)."""
    n = rays.view.size
    c = max(max(len(t) for t in layout.models_used[v].terms) for v in layout.views)
    out = Linearisation(np.empty((n, 2)), np.empty((n, 2)), None)
    if jacobian:          # np.empty, padding set per view: np.zeros of arrays this size costs more (measured: 3x)
        out.jac_points, out.cols, out.vals = np.empty((3, 2, n)), np.empty((c, 2, n), int), np.empty((c, 2, n))
        mpd = metres_per_degree(state.ground[:, 1], state.ground[:, 2])
    map_blocks(lambda sl: [_project_view(models, layout, rays, state, j, out, mpd if jacobian else None)
                           for j in range(sl.start, sl.stop)], len(layout.views), block=1)
    if jacobian:                                       # views of them, the rays last (:class:`Linearisation`)
        out.jac_points = out.jac_points.transpose(2, 1, 0)
        out.cols, out.vals = out.cols.transpose(1, 2, 0), out.vals.transpose(1, 2, 0)
    return out


def _project_view(models, layout: ViewLayout, rays: Rays, state: State, j: int, out: Linearisation, mpd) -> None:
    """:func:`project_all` of view ``j``'s rays, into ``out`` (the derivatives still ``(3 | c, 2, n)``)."""
    v, rows = layout.views[j], rays.view_rows(j)
    pt = rays.point[rows]
    if pt.size == 0:
        return
    lon, lat, h = state.ground[pt, 0], state.ground[pt, 1], state.ground[pt, 2]
    both = getattr(models[v], "project_with_jacobian", None) if mpd is not None else None
    if both is not None:                               # RPCs: values and derivatives from one evaluation
        s, l, jac_deg = both(lon, lat, h)
    else:
        s, l = models[v].project(lon, lat, h)
        jac_deg = models[v].project_jacobian(lon, lat, h) if mpd is not None else None
    s, l = np.asarray(s, float), np.asarray(l, float)
    ds, dl, dj, design = layout.correction(v, state.x, s, l, design=True)
    out.rpc_pred[rows, 0], out.rpc_pred[rows, 1] = s, l
    out.pred[rows, 0], out.pred[rows, 1] = s + ds, l + dl
    if mpd is None:
        return
    jd = np.asarray(jac_deg, float).reshape(-1, 6).T.reshape(2, 3, -1)          # (s, l) x (lon, lat, h) x rays
    jm = np.stack([jd[:, 0] / mpd[0][pt], jd[:, 1] / mpd[1][pt], jd[:, 2]], axis=1)  # px per m east, north, up
    for a in range(2):                                 # (I + d corr / d(s, l)) @ jac
        out.jac_points[:, a, rows] = jm[a] + dj[:, a, 0] * jm[0] + dj[:, a, 1] * jm[1]
    for axis, des, sl in zip((0, 1), design, layout.slices(v)):
        for k in range(out.cols.shape[0]):             # padded with 0 beyond the view's terms
            out.cols[k, axis, rows] = sl.start + k if k < sl.stop - sl.start else 0
            out.vals[k, axis, rows] = des[:, k] if k < sl.stop - sl.start else 0.0


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


@dataclass
class System:
    """The linearised rows at one state for :func:`~gdal_gf4cal.estimation.indexed.solve_rows`: every ray's
    sample row then every ray's line row (``point``, ``jac_points`` (2 n, 3) px per metre, ``residuals``,
    ``weights``, ``cols``/``vals`` the view's terms), ``prior`` (the ground rows: weights and residuals in metres,
    (n_points, 3)), ``extra`` (the datum pseudo-observations), ``lin`` and ``groups`` (each view's sample rows
    and line rows with their parameters: a point has one ray per view)."""

    point: np.ndarray
    jac_points: np.ndarray
    residuals: np.ndarray
    weights: np.ndarray
    cols: np.ndarray
    vals: np.ndarray
    prior: Any
    extra: Any
    lin: Linearisation
    groups: Any = None

    def solve(self, n_points: int, n_params: int, covariance: bool = False) -> PointSolution:
        dxp, cov_p, ok, dxg, cov_g = solve_rows(self.point, self.jac_points, self.residuals, self.weights,
                                                self.cols, self.vals, n_points, n_params, prior=self.prior,
                                                extra=self.extra, covariance=covariance, groups=self.groups)
        return PointSolution(dxp, cov_p, ok, dxg, cov_g)


def _ground_rows(state: State, wts: Weights):
    """Weights and residuals (m, east north up) of the points' ground rows (a GCP's ground, the DEM height)."""
    mx, my = metres_per_degree(state.ground[:, 1], state.ground[:, 2])
    delta = np.nan_to_num((wts.ground_obs - state.ground) * np.stack([mx, my, np.ones_like(mx)], axis=1))
    return wts.ground, delta


def _shifted(rows, by: int):
    """Rays ``rows`` (a slice or indices) moved by ``by`` rows."""
    return slice(rows.start + by, rows.stop + by) if isinstance(rows, slice) else rows + by


def linearise(models, layout: ViewLayout, rays: Rays, state: State, wts: Weights,
              lin: Optional[Linearisation] = None) -> System:
    """The rows of the system at ``state`` (``lin``: the predictions and derivatives there, when known)."""
    lin = project_all(models, layout, rays, state) if lin is None else lin
    v = rays.meas - lin.pred
    n_par, n = layout.n_params, rays.view.size
    groups = []
    for j, name in enumerate(layout.views):
        rows = rays.view_rows(j)
        groups += [(_shifted(rows, axis * n), sl) for axis, sl in enumerate(layout.slices(name))]
    return System(np.concatenate([rays.point, rays.point]), lin.jac_points.transpose(1, 0, 2).reshape(-1, 3),
                  v.T.ravel(), np.concatenate([wts.rays, wts.rays]), lin.cols.reshape(-1, lin.cols.shape[2]),
                  lin.vals.reshape(-1, lin.vals.shape[2]), _ground_rows(state, wts),
                  (sp.identity(n_par, format="csr"), -state.x, wts.prior) if n_par else None, lin, groups)


def _moved(ground: np.ndarray, dp: np.ndarray) -> np.ndarray:
    mx, my = metres_per_degree(ground[:, 1], ground[:, 2])
    return ground + np.where(np.isfinite(dp), dp, 0.0) / np.stack([mx, my, np.ones_like(mx)], axis=1)


def step(models, layout: ViewLayout, rays: Rays, state: State, wts: Weights, covariance: bool = False,
         lin: Optional[Linearisation] = None):
    """One Gauss-Newton step: ``(new_state, change_px, solution, lin, move)`` (``move`` (n_rays, 2): each ray's
    predicted move, linear in the step; ``change_px``: its largest size over the rays in the estimate; ``lin``:
    the linearisation at ``state``, when known)."""
    sys_ = linearise(models, layout, rays, state, wts, lin)
    sol = sys_.solve(rays.n_points, layout.n_params, covariance)
    dp = np.where(np.isfinite(sol.dx_points), sol.dx_points, 0.0)
    a_dx = np.empty(2 * rays.view.size)                 # each row's global move, group by group
    for rows, cols in sys_.groups:
        a_dx[rows] = sys_.vals[rows, :cols.stop - cols.start] @ sol.dx_global[cols]
    jp, dpr = sys_.lin.jac_points.transpose(2, 1, 0), dp[rays.point]       # (3, 2, n), (n, 3)
    move = (jp[0] * dpr[:, 0] + jp[1] * dpr[:, 1] + jp[2] * dpr[:, 2] + a_dx.reshape(2, -1)).T
    used = wts.rays > 0
    change = float(np.abs(move[used]).max()) if used.any() else 0.0
    return State(state.x + sol.dx_global, _moved(state.ground, dp)), change, sol, sys_.lin, move


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
        sys_ = linearise(models, layout, sub, State(state.x, g), resample_dem(sw, g))
        dxp, _, _, _, _ = solve_rows(sys_.point, sys_.jac_points, sys_.residuals, sys_.weights,
                                     sys_.cols[:, :0], sys_.vals[:, :0], sub.n_points, 0, prior=sys_.prior)
        g = _moved(g, dxp)
    ground = state.ground.copy()
    ground[points] = g
    return State(state.x, ground)


def gauss_newton(models, layout: ViewLayout, rays: Rays, state: State, wts: Weights, *, tol_px: float = 1e-5,
                 max_iter: int = 20, progress=None, lin: Optional[Linearisation] = None, warm: bool = False):
    """Iterate :func:`step` until the predictions move less than ``tol_px`` (at most ``max_iter`` steps); the
    predictions and derivatives at the solution; the DEM's height targets re-sampled at the current ground before
    each step (:func:`resample_dem`). ``lin``: the linearisation at ``state`` when known (one projection per
    step). ``warm``: ``state`` is the solution at other weights (a robust reweighting; or reweighted steps follow):
    a step whose predictions land where its linear model said (within ``tol_px``) is converged too, however far
    the reweighting moved them (its error is second order in that move). Returns ``(state, solution, lin, iterations, converged, change)``
    (the solution of the last step: its ``cov_global`` is the reduced system's unit-weight inverse)."""
    converged = False
    it = 0
    sol = None
    change = np.inf
    used = wts.rays > 0
    for it in range(1, max_iter + 1):
        state, change, sol, old, move = step(models, layout, rays, state, resample_dem(wts, state.ground), lin=lin)
        lin = project_all(models, layout, rays, state)
        off = float(np.abs(lin.pred - old.pred - move)[used].max()) if used.any() and warm else np.inf
        if progress is not None:
            progress(min(it / max_iter, 0.99), f"bundle iteration {it}: largest change {change:.3g} px")
        if change < tol_px or (wts.dem is None and off < tol_px):
            converged = True
            break
    return state, sol, lin if lin is not None else project_all(models, layout, rays, state), it, converged, change
