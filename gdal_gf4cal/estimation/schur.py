"""Normal equations with point blocks eliminated by Schur complement (METHODS §7; block calibration next).

Observations come per point: ``r`` rows per point, each depending on the point's own ``q`` parameters (e.g. a
tie point's ground coordinates, or intersection's east/north/up) and on ``p`` global parameters (sensor
corrections; none for plain intersection). The normal matrix

    [ N_pp  N_pg ] [dx_p]   [b_p]
    [ N_gp  N_gg ] [dx_g] = [b_g]

has a block-diagonal ``N_pp`` (one ``q x q`` block per point), so the points are eliminated:
``S = N_gg - sum_i N_gp,i N_pp,i^-1 N_pg,i``, ``S dx_g = b_g - sum_i N_gp,i N_pp,i^-1 b_p,i`` (``scipy.sparse``
when ``p`` is large), then ``dx_p,i = N_pp,i^-1 (b_p,i - N_pg,i dx_g)``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.linalg import cho_solve

from ..errors import DegenerateGeometryError
from .indexed import IndexedJacobian, block_inverse, cholesky_reduced, solve_indexed

#: A 3 x 3 point block whose determinant is below this fraction of its diagonal's product is rank-deficient up to
#: rounding (e.g. a point seen by one image): singular, as LAPACK's LU would find it.
RANK_DEFICIENT = 1e-13
#: Global parameter count above which the reduced system is assembled and solved with scipy.sparse.
SPARSE_ABOVE = 500


@dataclass
class PointSolution:
    """One Gauss-Newton step of a point-block system.

    ``dx_points`` (N, q) and ``cov_points`` (N, q, q) (``N_pp^-1``-based, including the uncertainty of the global
    parameters; NaN for points whose block is singular), ``ok`` (N,) the points whose block is regular,
    ``dx_global`` (p,) and ``cov_global`` (p, p) (``S^-1``; empty without global parameters), all for unit
    weight (multiply by ``sigma0^2`` for a-posteriori covariances).
    """

    dx_points: np.ndarray
    cov_points: np.ndarray
    ok: np.ndarray
    dx_global: np.ndarray
    cov_global: np.ndarray
    #: The reduced normal matrix ``S`` of the global parameters (unit weight) when the covariance was asked: for
    #: :func:`~gdal_gf4cal.estimation.sigma0_and_cov`.
    normal_global: Optional[np.ndarray] = None


def solve_with_points(jac_points, residuals, weights, jac_global=None, *, det_min: float = 1e-30,
                      covariance: bool = True, extra=None) -> PointSolution:
    """Solve the normal equations of point-block observations by Schur complement (module docstring).

    (Long by design: the point elimination and its three reduced-system paths, dense, sparse and indexed, side by
    side so that they visibly share one elimination.)

    Parameters
    ----------
    jac_points : ndarray (N, r, q)
        Derivatives of each point's ``r`` observations by its own parameters.
    residuals, weights : ndarray (N, r)
        ``observed - predicted`` and weights (0: not observed).
    jac_global : ndarray (N, r, p), optional
        Derivatives by the global parameters.
        Or an :class:`~gdal_gf4cal.estimation.indexed.IndexedJacobian` (each row's few global columns by index;
        chunked dense assembly, the fast path of bundle adjustment). Or a ``scipy.sparse`` matrix ``(N * r, p)`` (rows point-major: row ``i * r + k`` is observation ``k`` of
        point ``i``): the normal equations are then assembled sparsely (each observation touching a few global
        parameters, as in block adjustment, METHODS §8), cost linear in ``N``.
    det_min : float
        Points whose ``N_pp`` block has ``|det| <= det_min`` are singular (``ok`` False, NaN step).
    extra : (J (m, p) dense or sparse, residuals (m,), weights (m,)), optional
        Observations of the global parameters alone (e.g. GCPs, whose ground is known), added to the reduced
        system.

    Raises
    ------
    DegenerateGeometryError
        The reduced system of the global parameters is singular.
    """
    jp = np.asarray(jac_points, dtype=float)
    r = np.nan_to_num(np.asarray(residuals, dtype=float))
    w = np.asarray(weights, dtype=float)
    n, _, q = jp.shape
    if isinstance(jac_global, IndexedJacobian):                               # rows touching a few globals
        npp, bp, _, _ = _point_normals(jp, r, w, det_min, invert=False)        # solve_indexed inverts them
        return PointSolution(*solve_indexed(jp, r, w, npp, bp, jac_global, extra, covariance, det_min))
    npp, bp, inv, ok = _point_normals(jp, r, w, det_min)
    if jac_global is None:
        dxp = np.full((n, q), np.nan)
        if ok.any():
            dxp[ok] = np.matmul(inv[ok], bp[ok][..., None])[..., 0]
        return PointSolution(dxp, inv if covariance else np.empty((0, q, q)), ok, np.zeros(0), np.zeros((0, 0)))
    if sp.issparse(jac_global):
        return _solve_sparse(jp, r, w, npp, bp, ok, inv, sp.csr_matrix(jac_global), extra, covariance)
    if extra is not None:
        raise ValueError("extra observations need a sparse jac_global")
    jg = np.asarray(jac_global, dtype=float)
    p = jg.shape[2]
    jg_ok, jp_ok, w_ok, r_ok, inv_ok = jg[ok], jp[ok], w[ok], r[ok], inv[ok]
    npg = np.einsum("nr,nri,nrj->nij", w_ok, jp_ok, jg_ok)                  # (n, q, p)
    bg = np.einsum("nr,nri,nr->i", w_ok, jg_ok, r_ok)
    ngg = np.einsum("nr,nri,nrj->ij", w_ok, jg_ok, jg_ok)
    t = np.einsum("nij,njk->nik", inv_ok, npg)                                # N_pp^-1 N_pg
    b_red = bg - np.einsum("nqi,nq->i", npg, np.einsum("nij,nj->ni", inv_ok, bp[ok]))
    if p > SPARSE_ABOVE:
        m = ok.sum()
        rows = np.repeat(np.arange(m * q), p).reshape(m, q, p)
        cols = np.broadcast_to(np.arange(p), (m, q, p))
        npg_s = sp.csr_matrix((npg.ravel(), (rows.ravel(), cols.ravel())), shape=(m * q, p))
        t_s = sp.csr_matrix((t.ravel(), (rows.ravel(), cols.ravel())), shape=(m * q, p))
        s_mat = (sp.csr_matrix(ngg) - npg_s.T @ t_s).tocsc()
        s_mat.eliminate_zeros()
        try:
            dxg = spla.spsolve(s_mat, b_red)
        except RuntimeError as exc:                                            # singular factor
            raise DegenerateGeometryError(f"the global parameters are not determined ({exc}); freeze blocks or "
                                          "add observations") from None
        s_dense = s_mat.toarray() if covariance else None
    else:
        s_dense = ngg - np.einsum("nqi,nqj->ij", npg, t)
        sv = np.linalg.svd(s_dense, compute_uv=False)
        if sv[-1] <= 1e-12 * sv[0]:
            raise DegenerateGeometryError(f"the global parameters are not determined (condition number "
                                          f"{sv[0] / max(sv[-1], 1e-300):.3g}); freeze blocks or add observations")
        dxg = np.linalg.solve(s_dense, b_red)
    if not np.all(np.isfinite(dxg)):
        raise DegenerateGeometryError("the global parameters are not determined; freeze blocks or add observations")
    dxp = np.full((n, q), np.nan)
    dxp[ok] = np.einsum("nij,nj->ni", inv_ok, bp[ok] - npg @ dxg)
    cov_g = np.linalg.inv(s_dense) if covariance else np.zeros((0, 0))
    cov_p = inv
    if covariance:
        cov_p = inv.copy()
        cov_p[ok] = inv_ok + np.einsum("nqi,ij,nrj->nqr", t, cov_g, t)
    return PointSolution(dxp, cov_p, ok, dxg, cov_g, s_dense if covariance else None)


def _point_normals(jp, r, w, det_min: float, invert: bool = True):
    """Per point ``N_pp`` (n, q, q), ``b_p`` (n, q), ``N_pp^-1`` (NaN where singular) and ``ok`` (regular);
    without ``invert`` the last two are None."""
    n, _, q = jp.shape
    jw = (jp * w[:, :, None]).transpose(0, 2, 1)                              # (n, q, r): matmul, not 3-way einsum
    npp = np.matmul(jw, jp)
    bp = np.matmul(jw, r[:, :, None])[:, :, 0]
    if not invert:
        return npp, bp, None, None
    if q == 3:                                                                # closed form (LAPACK's batched inv
        inv, ok = block_inverse(npp, det_min, rel_det_min=RANK_DEFICIENT)      # is ~50x slower on many 3x3)
        return npp, bp, inv, ok
    inv = np.full((n, q, q), np.nan)
    if q == 2:                                                                # closed form (many 2x2 blocks)
        det = npp[:, 0, 0] * npp[:, 1, 1] - npp[:, 0, 1] * npp[:, 1, 0]
        ok = np.abs(det) > det_min
        d = np.where(ok, det, 1.0)
        inv[ok] = (np.stack([npp[:, 1, 1], -npp[:, 0, 1], -npp[:, 1, 0], npp[:, 0, 0]], axis=1)
                   / d[:, None]).reshape(n, 2, 2)[ok]
    else:
        ok = np.abs(np.linalg.det(npp)) > det_min
        if ok.any():
            inv[ok] = np.linalg.inv(npp[ok])
    return npp, bp, inv, ok


def _solve_sparse(jp, r, w, npp, bp, ok, inv, jg, extra, covariance: bool) -> PointSolution:
    """Sparse assembly of the reduced system (``jac_global`` a sparse ``(N * r, p)`` matrix), see
    :func:`solve_with_points`. The reduced matrix is ``p x p`` whatever the number of points; it is solved after
    equilibration by its diagonal (dense below :data:`SPARSE_ABOVE` globals, ``scipy.sparse`` above)."""
    n, k, q = jp.shape
    p = jg.shape[1]
    if jg.shape[0] != n * k:
        raise ValueError(f"sparse jac_global has {jg.shape[0]} rows; expected {n * k} (points x observations)")
    wk = np.where(ok[:, None], w, 0.0)                                        # singular points leave the system
    wf = wk.ravel()
    rows = np.repeat(np.arange(n * k), q)
    cols = (np.arange(n)[:, None, None] * q + np.arange(q)[None, None, :] + np.zeros((1, k, 1), int)).ravel()
    pmat = sp.csr_matrix(((jp * wk[:, :, None]).ravel(), (rows, cols)), shape=(n * k, n * q))
    npg = (pmat.T @ jg).tocsr()                                               # (N q, p): sum_k w jp^T jg
    ngg = (jg.T @ sp.diags(wf) @ jg).tocsr()
    bg = jg.T @ (wf * r.ravel())
    if extra is not None:
        je = sp.csr_matrix(extra[0])
        re_ = np.nan_to_num(np.asarray(extra[1], dtype=float))
        we = np.asarray(extra[2], dtype=float)
        ngg = ngg + (je.T @ sp.diags(we) @ je).tocsr()
        bg = bg + je.T @ (we * re_)
    inv0 = np.where(ok[:, None, None], np.nan_to_num(inv), 0.0)
    bi = np.arange(n * q).reshape(n, q)
    minv = sp.csr_matrix((inv0.ravel(), (np.repeat(bi, q, axis=1).ravel(), np.tile(bi, (1, q)).ravel())),
                         shape=(n * q, n * q))
    t = (minv @ npg).tocsr()                                                  # N_pp^-1 N_pg
    bp0 = np.where(ok[:, None], bp, 0.0)
    s_mat = (ngg - npg.T @ t).tocsc()
    b_red = bg - npg.T @ np.einsum("nij,nj->ni", inv0, bp0).ravel()
    d = np.sqrt(np.abs(s_mat.diagonal()))
    if not np.all(d > 0):
        raise DegenerateGeometryError(f"{int(np.sum(d <= 0))} global parameter(s) have no observation; freeze "
                                      "blocks or add observations")
    dinv = sp.diags(1.0 / d)
    s_eq = (dinv @ s_mat @ dinv)
    if p > SPARSE_ABOVE:
        try:
            z = spla.spsolve(s_eq.tocsc(), b_red / d)
        except RuntimeError as exc:
            raise DegenerateGeometryError(f"the global parameters are not determined ({exc}); freeze blocks or "
                                          "add observations") from None
        s_dense = s_eq.toarray() if covariance else None
    else:
        s_dense = s_eq.toarray()
        fac = cholesky_reduced(s_dense)
        z = cho_solve(fac, b_red / d, check_finite=False)
    dxg = z / d
    if not np.all(np.isfinite(dxg)):
        raise DegenerateGeometryError("the global parameters are not determined; freeze blocks or add observations")
    dxp = np.full((n, q), np.nan)
    corr = (npg @ dxg).reshape(n, q)
    dxp[ok] = np.einsum("nij,nj->ni", inv[ok], bp[ok] - corr[ok])
    cov_g = np.zeros((0, 0))
    cov_p = np.empty((0, q, q))
    if covariance:
        cov_g = (cho_solve(fac, np.eye(p), check_finite=False) if p <= SPARSE_ABOVE else np.linalg.inv(s_dense)) \
            / np.outer(d, d)
        tt = t.toarray().reshape(n, q, p) if n * q * p <= 5e7 else None
        cov_p = inv.copy()
        if tt is not None:
            t_ok = tt[ok]
            cov_p[ok] = inv[ok] + np.matmul(t_ok @ cov_g, t_ok.transpose(0, 2, 1))
    return PointSolution(dxp, cov_p, ok, dxg, cov_g, s_mat.toarray() if covariance else None)
