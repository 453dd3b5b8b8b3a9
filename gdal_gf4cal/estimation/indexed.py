"""Schur elimination when each observation touches a few global parameters given by index (METHODS §8, §11).

:func:`~gdal_gf4cal.estimation.solve_with_points` takes ``jac_global`` as an :class:`IndexedJacobian`: for every
point's row ``(i, k)`` the ``c`` global columns it depends on (``cols (N, r, c)``) and their derivatives
(``vals (N, r, c)``), e.g. a tie ray in a bundle adjustment touching its view's 3 correction terms. The reduced
system ``S = N_gg - sum_i N_gp,i N_pp,i^-1 N_pg,i`` is then assembled over chunks of points with dense ``(q, p)``
blocks and one matrix product per chunk: cost linear in the points and in ``p^2``, memory bounded by the chunk,
never a sparse-times-sparse product (a 10-view, 100,000-point bundle: ~0.5 s per solve instead of ~20 s).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DegenerateGeometryError

__all__ = ["IndexedJacobian", "CHUNK_ELEMENTS"]

#: A 3 x 3 point block whose determinant is below this fraction of its diagonal's product is singular (e.g. a tie
#: with one ray left in the estimate; nearly parallel rays of B/H 0.01 stay far above it).
REL_DET_MIN = 1e-10
#: Elements of one chunk's dense ``(points, q, p)`` block.
CHUNK_ELEMENTS = 4_000_000


@dataclass
class IndexedJacobian:
    """``d(observation (i, k)) / d(global cols[i, k, c]) = vals[i, k, c]`` of ``n_params`` global parameters
    (entries of rows with weight 0 are ignored; a ``vals`` of 0 adds nothing)."""

    cols: np.ndarray
    vals: np.ndarray
    n_params: int


def _chunks(n: int, q: int, p: int):
    step = max(1, int(CHUNK_ELEMENTS // max(1, q * p)))
    for a in range(0, n, step):
        yield slice(a, min(n, a + step))


@dataclass
class _Rows:
    """The rows with weight, point-major: their ``point``, ``jw`` (w jp, (m, q)), ``cols``/``vals`` (m, c) and
    ``wv`` (w vals). Scattering them with ``bincount`` is faster than grouping rows by their columns (measured)."""

    point: np.ndarray
    jw: np.ndarray
    cols: np.ndarray
    vals: np.ndarray
    wv: np.ndarray


def _used_rows(jp, w, jac: IndexedJacobian, ok) -> _Rows:
    n, r, q = jp.shape
    c = jac.cols.shape[2]
    wk = np.where(ok[:, None], w, 0.0).ravel()
    used = np.flatnonzero(wk)
    cols, vals = jac.cols.reshape(-1, c)[used], jac.vals.reshape(-1, c)[used]
    return _Rows(used // r, jp.reshape(-1, q)[used] * wk[used][:, None], cols, vals, vals * wk[used][:, None])


def _npg(rows: _Rows, lo: int, hi: int, q: int, p: int) -> np.ndarray:
    """Dense ``N_pg`` (hi - lo, q, p) of the points ``lo:hi``: ``sum_k w jp^T a`` scattered by column index."""
    a, b = np.searchsorted(rows.point, [lo, hi])
    pts, n = rows.point[a:b] - lo, hi - lo
    contrib = rows.jw[a:b][:, :, None] * rows.vals[a:b][:, None, :]           # (m, q, c)
    idx = (pts[:, None, None] * q + np.arange(q)[None, :, None]) * p + rows.cols[a:b][:, None, :]
    return np.bincount(idx.ravel(), weights=contrib.ravel(), minlength=n * q * p).reshape(n, q, p)


def _global_normals(rows: _Rows, r_used: np.ndarray, p: int):
    """``N_gg`` (p, p) and ``b_g`` (p,) of the rows with weight."""
    bg = np.bincount(rows.cols.ravel(), weights=(rows.wv * r_used[:, None]).ravel(), minlength=p)
    pair = (rows.cols[:, :, None] * p + rows.cols[:, None, :]).ravel()
    return np.bincount(pair, weights=(rows.wv[:, :, None] * rows.vals[:, None, :]).ravel(),
                       minlength=p * p).reshape(p, p), bg


def cholesky_reduced(s_eq: np.ndarray):
    """Cholesky factor (``scipy.linalg.cho_factor``) of an equilibrated reduced system; DegenerateGeometryError
    with the condition number when it is not (numerically) positive definite. Shared by both Schur paths."""
    from scipy.linalg import LinAlgError, cho_factor
    try:                                             # Cholesky: the equilibrated S is SPD when determined
        fac = cho_factor(s_eq, check_finite=False)
        piv = np.abs(np.diag(fac[0]))
        if piv.min() ** 2 <= 1e-12 * piv.max() ** 2:
            raise LinAlgError("ill-conditioned")
    except LinAlgError:
        sv = np.linalg.svd(s_eq, compute_uv=False)
        raise DegenerateGeometryError(f"the global parameters are not determined (condition number "
                                      f"{sv[0] / max(sv[-1], 1e-300):.3g}); freeze blocks or add observations") \
            from None
    return fac


def _solve_reduced(s_mat: np.ndarray, b_red: np.ndarray):
    """Equilibrated Cholesky solve of the reduced system: ``(dx, S^-1)``; DegenerateGeometryError if singular."""
    from scipy.linalg import cho_solve
    d = np.sqrt(np.abs(np.diag(s_mat)))
    if not np.all(d > 0):
        raise DegenerateGeometryError(f"{int(np.sum(d <= 0))} global parameter(s) have no observation; freeze "
                                      "blocks or add observations")
    fac = cholesky_reduced(s_mat / np.outer(d, d))
    dx = cho_solve(fac, b_red / d, check_finite=False) / d
    cov = cho_solve(fac, np.eye(s_mat.shape[0]), check_finite=False) / np.outer(d, d)
    return dx, cov


def block_inverse(npp: np.ndarray, det_min: float = 1e-30):
    """Inverses of many small symmetric blocks ``(n, q, q)``: closed form for 3 x 3 (adjugate), LAPACK otherwise;
    ``(inv, ok)`` with NaN where ``|det| <= det_min`` (3 x 3: or below :data:`REL_DET_MIN` of the diagonal's
    product)."""
    n, q, _ = npp.shape
    inv = np.full((n, q, q), np.nan)
    if q != 3:
        ok = np.abs(np.linalg.det(npp)) > det_min
        if ok.any():
            inv[ok] = np.linalg.inv(npp[ok])
        return inv, ok
    a = npp
    adj = np.empty_like(a)
    for i in range(3):
        for j in range(3):
            r0, r1 = [k for k in range(3) if k != j]
            c0, c1 = [k for k in range(3) if k != i]
            adj[:, i, j] = (-1) ** (i + j) * (a[:, r0, c0] * a[:, r1, c1] - a[:, r0, c1] * a[:, r1, c0])
    det = np.einsum("nj,nj->n", a[:, 0, :], adj[:, :, 0])
    scale = np.abs(a[:, 0, 0] * a[:, 1, 1] * a[:, 2, 2])
    ok = (np.abs(det) > det_min) & (np.abs(det) > REL_DET_MIN * scale)      # rank-deficient blocks (one ray left)
    inv[ok] = adj[ok] / det[ok, None, None]
    return inv, ok


def solve_indexed(jp, r, w, npp, bp, jac: IndexedJacobian, extra, covariance: bool, det_min: float = 1e-30):
    """The reduced system over chunks of points (module docstring); returns what ``solve_with_points`` returns:
    ``(dx_points, cov_points, ok, dx_global, cov_global)`` (``cov_global`` = ``S^-1`` even without
    ``covariance``: it costs a ``p x p`` solve; ``cov_points`` only with it)."""
    inv, ok = block_inverse(npp, det_min)
    n, _, q = jp.shape
    p = jac.n_params
    rows = _used_rows(jp, w, jac, ok)
    wk = np.where(ok[:, None], w, 0.0).ravel()
    ngg, bg = _global_normals(rows, r.reshape(-1)[wk != 0], p)
    if extra is not None:
        import scipy.sparse as sp
        je = extra[0].toarray() if sp.issparse(extra[0]) else np.asarray(extra[0], float)
        re_, we = np.nan_to_num(np.asarray(extra[1], float)), np.asarray(extra[2], float)
        ngg = ngg + (je * we[:, None]).T @ je
        bg = bg + je.T @ (we * re_)
    inv0 = np.where(ok[:, None, None], np.nan_to_num(inv), 0.0)
    jw = (jp * np.where(ok[:, None], w, 0.0)[:, :, None])
    s_mat, b_red = ngg.copy(), bg.copy()
    for sl in _chunks(n, q, p):
        npg = _npg(rows, sl.start, sl.stop, q, p)
        t = np.matmul(inv0[sl], npg)                                           # N_pp^-1 N_pg
        s_mat -= npg.reshape(-1, p).T @ t.reshape(-1, p)
        b_red -= np.einsum("nqi,nq->i", t, bp[sl])
    dxg, cov_g = _solve_reduced(s_mat, b_red)
    a_dx = np.einsum("nkc,nkc->nk", jac.vals, dxg[jac.cols])                  # each row's global move
    rhs = bp - np.einsum("nkq,nk->nq", jw, a_dx)
    dxp = np.full((n, q), np.nan)
    dxp[ok] = np.einsum("nij,nj->ni", inv[ok], rhs[ok])
    cov_p = inv.copy() if covariance else np.empty((0, q, q))
    if covariance:
        for sl in _chunks(n, q, p):
            t = np.matmul(inv0[sl], _npg(rows, sl.start, sl.stop, q, p))
            cov_p[sl] = np.where(ok[sl, None, None], inv[sl] + np.matmul(t @ cov_g, t.transpose(0, 2, 1)), inv[sl])
    return dxp, cov_p, ok, dxg, cov_g
