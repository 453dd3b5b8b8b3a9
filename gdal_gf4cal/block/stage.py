"""One adjustment stage (METHODS §8): its observation rows, the tie points on the DEM (unknown lon, lat) eliminated
by Schur complement in each Gauss-Newton step (:meth:`Stage.solve`), the iterations with robust reweighting
(:func:`run_stage`) and the propagation of an earlier stage's errors (:func:`propagate_frozen`)."""
from __future__ import annotations

from typing import List, Sequence

import numpy as np
import scipy.sparse as sp

from ..estimation import radial_huber_weights, solve_with_points
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


def _robust(stage: Stage, v, w_used, n_params, reject: bool, reject_k: float):
    red = redundancy(stage, w_used)
    sig = stage.sigma * np.sqrt(red)
    fw, out, scale, z = radial_huber_weights(v, sig, n_params, reject_k=reject_k)
    if not reject:
        out = np.zeros_like(out)
    factor = np.where(out, 0.0, fw)
    return factor, out, z


def run_stage(stage: Stage, x, free_sets, *, robust: bool, tol: float, max_iter: int, reject_k: float,
               progress=None):
    """Gauss-Newton (+ robust reweighting) cycling through ``free_sets`` (one set: simultaneous; exterior then
    interior: alternating). Returns (x, plon, plat, info)."""
    plon, plat = stage.initial_points(x)
    npar = int(np.any(free_sets, axis=0).sum())
    factor = np.ones(len(stage.rows))
    rejected = np.zeros(len(stage.rows), bool)
    phase = 0 if robust else 2            # 0: a-priori weights, 1: down-weighting, 2: rejection
    history: List[float] = []
    small_in_row = in_phase = 0
    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        free = free_sets[(it - 1) % len(free_sets)]
        pred, _, jp, _ = stage.evaluate(x, plon, plat)
        v = stage.meas - pred
        w = stage.base_w[:, None] * factor[:, None] * np.ones((1, 2))
        dx, dp, _ = stage.solve(x, free, v, w, jp)
        x = x + dx
        mx, my = metres_per_degree(plat, 0.0)
        plon = plon + dp[:, 0] / mx
        plat = plat + dp[:, 1] / my
        # change: the largest move of a corrected position through the global parameters, and the 99th percentile
        # of the tie points' moves (a blunder's point may cycle over a DEM kink until it is rejected)
        move = np.abs(np.einsum("nkc,nc->nk", stage.design, dx[stage.cols]))
        change = float(np.max(move[stage.base_w > 0])) if (stage.base_w > 0).any() else 0.0
        if stage.tie_rows.size:
            pm = np.abs(np.einsum("nkq,nq->nk", jp, dp[stage.point_of])).max(axis=1)
            change = max(change, float(np.percentile(pm, 99)))
        history.append(change)
        if progress is not None:
            progress(min(it / max_iter, 0.99), f"iteration {it}: largest change {change:.3g} px")
        small_in_row = small_in_row + 1 if change < tol else 0
        in_phase += 1
        if small_in_row >= len(free_sets) or (phase < 2 and in_phase >= 4 * len(free_sets) and change < 100 * tol):
            if phase == 2:
                pred, _, _, _ = stage.evaluate(x, plon, plat, with_jacobian=False)
                v = stage.meas - pred
                f2, out, _ = _robust(stage, v, w, npar, True, reject_k) if robust else (factor, rejected, None)
                if np.array_equal(out, rejected):
                    converged = True
                    break
                factor, rejected = f2, out
                small_in_row = 0
                continue
            phase += 1
            small_in_row = in_phase = 0
        if phase >= 1 and robust:
            pred, _, _, _ = stage.evaluate(x, plon, plat, with_jacobian=False)
            v = stage.meas - pred
            factor, rejected, _ = _robust(stage, v, w, npar, phase == 2, reject_k)
    return x, plon, plat, {"iterations": it, "converged": converged, "history": history, "factor": factor,
                           "rejected": rejected}



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


