"""One adjustment stage (METHODS §8): its observation rows, the tie points on the DEM (unknown lon, lat) eliminated
by Schur complement in each Gauss-Newton step (:meth:`Stage.solve`), the iterations with robust reweighting
(:func:`run_stage`) and the propagation of an earlier stage's errors (:func:`propagate_frozen`)."""
from __future__ import annotations

from typing import List, Sequence

import numpy as np
import scipy.sparse as sp

from ..estimation import Estimate, RadialHuber, robust_fit, solve_with_points
from ..geodesy import metres_per_degree
from .layout import BlockError
from .model import local_design

class Stage:
    """Arrays of one adjustment stage: observation rows, tie-point slots, weights."""

    def __init__(self, tab, rows, models, layout, index, dem, used_gcp):
        self.rows = rows                                           # row positions in ``tab``
        sub = tab.iloc[rows]
        self.image = sub["image_id"].to_numpy(object)
        self.meas = np.stack([sub["sample"].to_numpy(float), sub["line"].to_numpy(float)], axis=1)
        self.sigma = sub["sigma"].to_numpy(float)
        self.is_tie = (sub["kind"] == "tie").to_numpy()
        self.ground = np.stack([sub[c].to_numpy(float) for c in ("lon", "lat", "h")], axis=1)
        self.base_w = np.where(self.is_tie | used_gcp[rows], 1.0 / self.sigma ** 2, 0.0)
        self.cols = np.stack([index[i] for i in self.image]) if len(rows) else np.zeros((0, 13), int)
        self.design = np.zeros((len(rows), 2, 13))
        for im in dict.fromkeys(self.image):
            m = self.image == im
            self.design[m] = local_design(layout.images[im], layout.time_scale, self.meas[m, 0], self.meas[m, 1])
        tie_rows = np.flatnonzero(self.is_tie)
        pids = sub["point_id"].to_numpy(object)[tie_rows]
        self.point_ids, self.point_of = np.unique(pids, return_inverse=True) if tie_rows.size else (
            np.zeros(0, object), np.zeros(0, int))
        counts = np.bincount(self.point_of, minlength=self.point_ids.size)
        self.max_rays = int(counts.max()) if counts.size else 1
        order = np.argsort(self.point_of, kind="stable")
        slot = np.empty(tie_rows.size, int)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(int) if counts.size else np.zeros(0, int)
        slot[order] = np.arange(tie_rows.size) - np.repeat(starts, counts)
        self.tie_rows, self.slot = tie_rows, slot
        self.models, self.dem = models, dem

    def initial_points(self, x):
        """Tie-point ground (lon, lat): mean of every ray's DEM localisation with the current corrections."""
        n = self.point_ids.size
        lon = np.zeros(n)
        lat = np.zeros(n)
        cnt = np.zeros(n)
        v = np.einsum("nkc,nc->nk", self.design, x[self.cols])
        for im in dict.fromkeys(self.image[self.tie_rows]):
            m = self.tie_rows[self.image[self.tie_rows] == im]
            lo, la, _ = self.models[im].localize_dem(self.meas[m, 0] - v[m, 0], self.meas[m, 1] - v[m, 1], self.dem)
            ok = np.isfinite(lo) & np.isfinite(la)
            p = self.point_of[np.searchsorted(self.tie_rows, m)]
            np.add.at(lon, p[ok], np.asarray(lo)[ok])
            np.add.at(lat, p[ok], np.asarray(la)[ok])
            np.add.at(cnt, p[ok], 1.0)
        if (cnt == 0).any():
            bad = self.point_ids[cnt == 0][0]
            raise BlockError(f"tie point {bad!r} cannot be localised on the DEM in any of its images; check the DEM "
                             "covers the images and the tie point's image coordinates")
        return lon / cnt, lat / cnt

    def evaluate(self, x, plon, plat, with_jacobian=True):
        """Predicted positions (n, 2), RPC Jacobians by (lon, lat) along the DEM (n, 2, 2, per metre) and heights."""
        g = self.ground.copy()
        jp = None
        if self.tie_rows.size:
            lon = plon[self.point_of]
            lat = plat[self.point_of]
            h, dhx, dhy = self.dem.sample_with_gradient(lon, lat)
            h = np.asarray(h, float)
            if not np.all(np.isfinite(h)):
                raise BlockError(f"{int((~np.isfinite(h)).sum())} tie point(s) fall outside the DEM; give a DEM "
                                 "that covers the images")
            g[self.tie_rows] = np.stack([lon, lat, h], axis=1)
        pred = np.zeros((len(self.rows), 2))
        if with_jacobian and self.tie_rows.size:
            jp = np.zeros((self.tie_rows.size, 2, 2))
        for im in dict.fromkeys(self.image):
            m = self.image == im
            s, l = self.models[im].project(g[m, 0], g[m, 1], g[m, 2])
            pred[m, 0], pred[m, 1] = s, l
            if jp is not None:
                mt = m[self.tie_rows]
                if mt.any():
                    rows = self.tie_rows[mt]
                    j = np.asarray(self.models[im].project_jacobian(g[rows, 0], g[rows, 1], g[rows, 2]))
                    j = j.reshape(-1, 2, 3)
                    jj = j[:, :, :2] + j[:, :, 2:3] * np.stack([dhx[mt], dhy[mt]], axis=1)[:, None, :]
                    mx, my = metres_per_degree(g[rows, 1], g[rows, 2])
                    jp[mt] = jj / np.stack([mx, my], axis=1)[:, None, :]
        corr = np.einsum("nkc,nc->nk", self.design, x[self.cols])
        return pred + corr, pred, jp, g

    def solve(self, x, free, v, w, jp, covariance=False):
        """One Gauss-Newton step: (dx_global over all parameters, point steps in metres (N, 2), solution)."""
        fidx = np.full(x.size, -1)
        fidx[free] = np.arange(int(free.sum()))
        pf = int(free.sum())
        N, m = self.point_ids.size, self.max_rays
        k = 2 * m
        if jp is None:
            jp = np.zeros((0, 2, 2))
        # tie rows -> padded point layout
        jpp = np.zeros((N, k, 2))
        rr = np.zeros((N, k))
        ww = np.zeros((N, k))
        t = self.tie_rows
        base = self.point_of * k + 2 * self.slot
        for ax in range(2):
            jpp.reshape(N * k, 2)[base + ax] = jp[:, ax, :]
            rr.reshape(N * k)[base + ax] = v[t, ax]
            ww.reshape(N * k)[base + ax] = w[t, ax]

        def sparse_rows(rows_idx, out_rows, n_rows):
            c = fidx[self.cols[rows_idx]]                              # (n, 13)
            data, ri, ci = [], [], []
            for ax in range(2):
                d = self.design[rows_idx, ax, :]
                keep = (c >= 0) & (d != 0)
                data.append(d[keep])
                ri.append(np.broadcast_to((out_rows + ax)[:, None], c.shape)[keep])
                ci.append(c[keep])
            return sp.csr_matrix((np.concatenate(data), (np.concatenate(ri), np.concatenate(ci))), shape=(n_rows, pf))

        jg = sparse_rows(t, base, N * k)
        g_rows = np.flatnonzero(~self.is_tie & (w.sum(axis=1) > 0))
        extra = None
        if g_rows.size:
            je = sparse_rows(g_rows, 2 * np.arange(g_rows.size), 2 * g_rows.size)
            extra = (je, v[g_rows].ravel(), w[g_rows].ravel())
        sol = solve_with_points(jpp, rr, ww, jg, extra=extra, covariance=covariance)
        dx = np.zeros(x.size)
        dx[free] = sol.dx_global
        dp = np.where(np.isfinite(sol.dx_points), sol.dx_points, 0.0)
        return dx, dp, sol


def redundancy(stage: Stage, w) -> np.ndarray:
    """Approximate redundancy per row: ``1 - 1/m`` for a ray of a tie point with ``m`` used rays, 1 for GCPs."""
    red = np.ones(len(stage.rows))
    if stage.tie_rows.size:
        used = (w[stage.tie_rows].sum(axis=1) > 0).astype(float)
        m = np.bincount(stage.point_of, weights=used, minlength=stage.point_ids.size)
        red[stage.tie_rows] = np.clip(1.0 - 1.0 / np.maximum(m[stage.point_of], 1.0), 0.05, 1.0)
    return red


class StageNorm(RadialHuber):
    """The driver's radial Huber weights for a block stage (METHODS §8, robust weights) with the stage's schedule:
    phase 0 a-priori weights, 1 down-weighting, 2 rejection too (``z > reject_k``), each phase until the fit moves
    less than ``tol`` over a cycle of the free sets, or, in phases 0 and 1, moves less than ``100 tol`` after 4
    cycles (a blunder's tie point may cycle over a DEM kink until it is rejected: the driver's own two-phase rule,
    ``tol`` with a stable set, then never reaches the rejection); converged when the rejected set is stable too.
    A ray's a-priori sigma: its measurement sigma times the square root of its redundancy (:func:`redundancy`).
    ``robust=False``: phase 2 with weights 1, nothing rejected (Gauss-Newton to convergence)."""

    def __init__(self, reject_k: float, n_sets: int, robust: bool = True):
        super().__init__(huber_c=2.5 if robust else np.inf, reject_k=reject_k if robust else np.inf,
                         sigma=lambda problem, est: problem.ray_sigma())
        self.n_sets, self.phase = n_sets, 0 if robust else 2
        self.small = self.in_phase = 0
        self.started = self.converged = False

    def _count(self, change: float, tol: float) -> None:
        """Count one Gauss-Newton step; phases 0 and 1 end when settled (class docstring)."""
        self.small = self.small + 1 if change < tol else 0
        self.in_phase += 1
        if self.phase < 2 and (self.small >= self.n_sets or (self.in_phase >= 4 * self.n_sets
                                                             and change < 100 * tol)):
            self.phase += 1
            self.small = self.in_phase = 0

    def step(self, problem, est, st):
        if not self.started:                                # the driver's first solve counts too
            self.started = True
            self._count(problem.history[-1], st.tol)
        problem.phase = self.phase
        if self.phase == 0:
            return st.weights.copy()
        st.phase = self.phase
        return super().step(problem, est, st)

    def settled(self, problem, old, new, st) -> bool:
        pending, phase = st.info.pop("pending", None), self.phase
        self._count(problem.change(old, new), st.tol)
        if phase == 2:
            st.outlier = pending                            # the rejected set of this solve
            if self.small >= self.n_sets:                   # converged when the fit rejects the same rows
                res = np.asarray(new.residuals, float).reshape(problem.n_points, 2)
                self.converged = np.array_equal(self.weights(res, problem, new)[1], st.outlier)
                self.small = self.small if self.converged else 0
        return self.converged


class StageProblem:
    """One stage as a problem of the robust driver (:func:`~gdal_gf4cal.estimation.robust_fit`): a point is an
    observation row (``k = 2``: sample, line); ``fit(factors)`` is one Gauss-Newton step at the current parameters
    with the a-priori weights times the factors, over the next set of ``free_sets`` (one set: simultaneous;
    exterior then interior: alternating), tie points eliminated by Schur (:meth:`Stage.solve`); the Estimate's
    residuals are at the new parameters. ``change``: the largest move of a corrected position through the global
    parameters and the 99th percentile of the tie points' moves (a blunder's point may cycle over a DEM kink until
    it is rejected), of the last step."""

    k = 2

    def __init__(self, stage: Stage, x, free_sets, progress=None, max_iter: int = 60, label: str = "stage"):
        self.stage, self.x, self.free_sets = stage, np.array(x, float), np.asarray(free_sets)
        self.n_points = len(stage.rows)
        self.n_params = int(np.any(self.free_sets, axis=0).sum())
        self.plon, self.plat = stage.initial_points(self.x)
        self.pred, _, self.jp, _ = stage.evaluate(self.x, self.plon, self.plat)
        self.used_w = np.repeat(stage.base_w[:, None], 2, axis=1)
        self.history: List[float] = []
        self.phase, self.progress, self.max_iter, self.label = 0, progress, max_iter, label

    def ray_sigma(self) -> np.ndarray:
        return self.stage.sigma * np.sqrt(redundancy(self.stage, self.used_w))

    def fit(self, factors) -> Estimate:
        st = self.stage
        free = self.free_sets[len(self.history) % len(self.free_sets)]
        w = st.base_w[:, None] * np.asarray(factors, float)[:, None] * np.ones((1, 2))
        dx, dp, _ = st.solve(self.x, free, st.meas - self.pred, w, self.jp)
        self.x = self.x + dx
        mx, my = metres_per_degree(self.plat, 0.0)
        self.plon = self.plon + dp[:, 0] / mx
        self.plat = self.plat + dp[:, 1] / my
        move = np.abs(np.einsum("nkc,nc->nk", st.design, dx[st.cols]))
        change = float(np.max(move[st.base_w > 0])) if (st.base_w > 0).any() else 0.0
        if st.tie_rows.size:
            pm = np.abs(np.einsum("nkq,nq->nk", self.jp, dp[st.point_of])).max(axis=1)
            change = max(change, float(np.percentile(pm, 99)))
        self.history.append(change)
        self.used_w = w
        self.pred, _, self.jp, _ = st.evaluate(self.x, self.plon, self.plat)
        if self.progress is not None:
            it = len(self.history)
            self.progress(min(it / self.max_iter, 0.99), f"{self.label}, iteration {it} "
                          f"({ITERATION_PHASES[self.phase]}): largest change of a corrected position {change:.3g} px")
        v = (st.meas - self.pred).ravel()
        return Estimate(names=[], x=self.x, cov=np.zeros((0, 0)), sigma0=float("nan"), dof=0,
                        redundancy=np.full(v.size, np.nan), residuals=v, normalised=np.full(v.size, np.nan),
                        weights=w.ravel())

    def change(self, old: Estimate, new: Estimate) -> float:
        return self.history[-1]


#: What the iterations of a stage do, by the driver's phase (named in the iteration trace): the first solve with
#: the a-priori weights, then down-weighting (radial Huber), then rejection too.
ITERATION_PHASES = {0: "a-priori weights", 1: "robust down-weighting", 2: "robust rejection"}


def run_stage(stage: Stage, x, free_sets, *, robust: bool, tol: float, max_iter: int, reject_k: float,
              progress=None, label: str = "stage"):
    """Gauss-Newton with robust reweighting (the driver's radial Huber, :class:`StageNorm`) of one stage:
    (x, plon, plat, info) with ``info``: iterations (Gauss-Newton solves), converged, history (change per
    iteration, px), factor (robust factor per row, 0: out), rejected (per row)."""
    problem = StageProblem(stage, x, free_sets, progress, max_iter, label)
    norm = StageNorm(reject_k, len(free_sets), robust)
    est = robust_fit(problem, norm=norm, start=None, max_iter=max_iter - 1, tol=tol)
    return problem.x, problem.plon, problem.plat, {
        "iterations": len(problem.history), "converged": norm.converged, "history": problem.history,
        "factor": est.point_weights, "rejected": est.outlier}


def stage_rows(tab, images: Sequence[str], band_stage: bool, all_images: Sequence[str]):
    """Rows of a stage: GCPs of its images; ties with >= 2 rays in the images considered (reference stage: its own
    images; band stage: every image, for ties with at least one ray in a band image)."""
    in_stage = tab["image_id"].isin(list(images)).to_numpy()
    tie = (tab["kind"] == "tie").to_numpy()
    gcp_rows = np.flatnonzero(in_stage & ~tie)
    if band_stage:
        cand = tie & tab["image_id"].isin(list(all_images)).to_numpy()
        touched = set(tab.loc[tie & in_stage, "point_id"])
        cand &= tab["point_id"].isin(touched).to_numpy()
    else:
        cand = tie & in_stage
    n = tab[cand].groupby("point_id")["image_id"].transform("size")
    tie_rows = np.flatnonzero(cand)[(n.to_numpy() >= 2)]
    return np.sort(np.concatenate([gcp_rows, tie_rows]))



def propagate_frozen(stage: Stage, xs, free, frozen, w, jp, cov) -> None:
    """Add to ``cov`` (in place) what the errors of the ``frozen`` parameters (an earlier stage's, with their
    covariance already in ``cov``) do to this stage's ``free`` ones: the band stage fits each band's interior to the
    reference band's corrected positions, so a reference exterior or interior error is absorbed by the band interior
    (METHODS §6 propagation). Linear response ``S = d x_free / d x_frozen`` (one reduced solve per frozen parameter
    that this stage's rows see, tie points re-eliminated); ``cov_ff += S C S^T``, ``cov_fF = S C``."""
    fr = np.flatnonzero(frozen)
    if not fr.size:
        return
    seen = np.zeros(cov.shape[0], bool)
    seen[np.unique(stage.cols[np.any(stage.design != 0, axis=1)].ravel())] = True
    fr = fr[seen[fr]]
    if not fr.size:
        return
    fi = np.flatnonzero(free)
    sens = np.zeros((fi.size, fr.size))
    for j, c in enumerate(fr):
        dv = -stage.design[:, :, :] * (stage.cols == c)[:, None, :]
        dx, _, _ = stage.solve(xs, free, dv.sum(axis=2), w, jp)
        sens[:, j] = dx[fi]
    c_ff = cov[np.ix_(fr, fr)]
    cross = sens @ c_ff
    cov[np.ix_(fi, fi)] += cross @ sens.T
    cov[np.ix_(fi, fr)] = cross
    cov[np.ix_(fr, fi)] = cross.T


