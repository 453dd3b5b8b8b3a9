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
from ..threads import map_blocks

__all__ = ["IndexedJacobian", "CHUNK_ELEMENTS", "solve_rows", "block_inverse"]

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
    """The rows with weight: their ``point``, ``jw`` (w jp, (m, q)), ``cols``/``vals`` (m, c), ``wv`` (w vals),
    ``r`` (residuals) and whether ``point`` is sorted. Scattering them with ``bincount`` is faster than grouping
    rows by their columns (measured)."""

    point: np.ndarray
    jw: np.ndarray
    cols: np.ndarray
    vals: np.ndarray
    wv: np.ndarray
    r: np.ndarray
    sorted: bool

    def take(self, lo: int, hi: int):
        """The rows of the points ``lo:hi`` (a slice when sorted)."""
        if self.sorted:
            a, b = np.searchsorted(self.point, [lo, hi])
            return slice(a, b)
        return np.flatnonzero((self.point >= lo) & (self.point < hi))


def _npg(rows: _Rows, lo: int, hi: int, q: int, p: int) -> np.ndarray:
    """Dense ``N_pg`` (hi - lo, q, p) of the points ``lo:hi``: ``sum_k w jp^T a`` scattered by column index."""
    sel = rows.take(lo, hi)
    pts, n = rows.point[sel] - lo, hi - lo
    contrib = rows.jw[sel][:, :, None] * rows.vals[sel][:, None, :]           # (m, q, c)
    idx = (pts[:, None, None] * q + np.arange(q)[None, :, None]) * p + rows.cols[sel][:, None, :]
    return np.bincount(idx.ravel(), weights=contrib.ravel(), minlength=n * q * p).reshape(n, q, p)


def _global_normals(rows: _Rows, p: int):
    """``N_gg`` (p, p) and ``b_g`` (p,) of the rows with weight."""
    bg = np.bincount(rows.cols.ravel(), weights=(rows.wv * rows.r[:, None]).ravel(), minlength=p)
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


def block_inverse(npp: np.ndarray, det_min: float = 1e-30, rel_det_min: float = REL_DET_MIN):
    """Inverses of many small symmetric blocks ``(n, q, q)``: closed form for 3 x 3 (adjugate), LAPACK otherwise;
    ``(inv, ok)`` with NaN where ``|det| <= det_min`` (3 x 3: or below ``rel_det_min`` of the diagonal's
    product)."""
    n, q, _ = npp.shape
    if q != 3:
        inv = np.full((n, q, q), np.nan)
        ok = np.abs(np.linalg.det(npp)) > det_min
        if ok.any():
            inv[ok] = np.linalg.inv(npp[ok])
        return inv, ok
    a = np.ascontiguousarray(npp.transpose(1, 2, 0))          # (3, 3, n): the arithmetic runs along the blocks
    adj = np.empty_like(a)
    for i in range(3):
        for j in range(3):
            r0, r1 = [k for k in range(3) if k != j]
            c0, c1 = [k for k in range(3) if k != i]
            np.subtract(a[r0, c0] * a[r1, c1], a[r0, c1] * a[r1, c0], out=adj[i, j])
            if (i + j) % 2:
                np.negative(adj[i, j], out=adj[i, j])
    det = a[0, 0] * adj[0, 0] + a[0, 1] * adj[1, 0] + a[0, 2] * adj[2, 0]
    scale = np.abs(a[0, 0] * a[1, 1] * a[2, 2])
    ok = (np.abs(det) > det_min) & (np.abs(det) > rel_det_min * scale)      # rank-deficient blocks (one ray left)
    ok &= np.isfinite(det) & np.isfinite(scale)
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = adj / np.where(ok, det, np.nan)
    return np.ascontiguousarray(inv.transpose(2, 0, 1)), ok


def solve_indexed(jp, r, w, npp, bp, jac: IndexedJacobian, extra, covariance: bool, det_min: float = 1e-30):
    """The reduced system over chunks of points (module docstring) of the padded layout of
    :func:`~gdal_gf4cal.estimation.solve_with_points`; returns what it returns: ``(dx_points, cov_points, ok,
    dx_global, cov_global)`` (``cov_global`` = ``S^-1`` even without ``covariance``: it costs a ``p x p`` solve;
    ``cov_points`` only with it)."""
    inv, ok = block_inverse(npp, det_min)
    n, rp, q = jp.shape
    c = jac.cols.shape[2]
    wk = np.where(ok[:, None], w, 0.0).ravel()
    used = np.flatnonzero(wk)
    vals = jac.vals.reshape(-1, c)[used]
    rows = _Rows(used // rp, jp.reshape(-1, q)[used] * wk[used][:, None], jac.cols.reshape(-1, c)[used], vals,
                 vals * wk[used][:, None], r.reshape(-1)[used], True)
    return _eliminate(rows, npp, bp, inv, ok, jac.n_params, extra, covariance)


def solve_rows(point, jac_points, residuals, weights, cols, vals, n_points: int, n_params: int, *, prior=None,
               extra=None, covariance: bool = False, det_min: float = 1e-30, groups=None):
    """Schur elimination of observation rows given one by one (no padding): row ``k`` observes point
    ``point[k]``'s ``q`` parameters (``jac_points`` (m, q)) and the global columns ``cols[k]`` (``vals`` (m, c)),
    ``residuals``, ``weights`` (m,); ``prior``: ``(weights (n, q), residuals (n, q))`` direct observations of each
    point's parameters (e.g. a DEM's height); ``extra`` as in :func:`~gdal_gf4cal.estimation.solve_with_points`.
    ``groups``: optional ``[(rows, cols slice), ...]``, every row in one group, a group's rows using the same
    contiguous columns (``vals[rows, :width]``) and seeing each point at most once (a bundle's view and axis): the
    normals are then assembled by slices and matrix products instead of index scatters (several times faster).
    Returns ``(dx_points, cov_points, ok, dx_global, cov_global)`` as it does; the reduced system is ``n_params``
    square whatever the rows (a bundle adjustment's rays: 2 rows each)."""
    point = np.asarray(point)
    jp, w = np.asarray(jac_points, float), np.asarray(weights, float)
    r = np.nan_to_num(np.asarray(residuals, float))
    q = jp.shape[1]
    jw = jp * w[:, None]
    npp = np.empty((n_points, q, q))
    for a in range(q):                                                          # symmetric: q (q + 1) / 2 sums
        for b in range(a, q):
            npp[:, a, b] = npp[:, b, a] = np.bincount(point, weights=jw[:, a] * jp[:, b], minlength=n_points)
    bp = np.stack([np.bincount(point, weights=jw[:, a] * r, minlength=n_points) for a in range(q)], axis=1)
    if prior is not None:
        pw, pr = np.asarray(prior[0], float), np.nan_to_num(np.asarray(prior[1], float))
        npp[:, np.arange(q), np.arange(q)] += pw
        bp += pw * pr
    inv, ok = block_inverse(npp, det_min)
    if groups is not None and n_params:
        if not ok.all():                                                         # singular points leave
            w = np.where(ok[point], w, 0.0)
            jw = jp * w[:, None]
        return _eliminate_groups(point, jw, r, w, np.asarray(vals, float), groups, npp, bp, inv, ok, n_params,
                                 extra, covariance)
    used = np.flatnonzero((w != 0) & ok[point])
    v = np.asarray(vals, float)[used]
    rows = _Rows(point[used], jw[used], np.asarray(cols)[used], v, v * w[used][:, None], r[used],
                 bool(np.all(point[used][1:] >= point[used][:-1])))
    return _eliminate(rows, npp, bp, inv, ok, n_params, extra, covariance)


def _add_extra(ngg, bg, extra):
    """The observations of the global parameters alone (``extra``) added to ``N_gg``, ``b_g``."""
    if extra is None:
        return ngg, bg
    import scipy.sparse as sp
    je = extra[0].toarray() if sp.issparse(extra[0]) else np.asarray(extra[0], float)
    re_, we = np.nan_to_num(np.asarray(extra[1], float)), np.asarray(extra[2], float)
    return ngg + (je * we[:, None]).T @ je, bg + je.T @ (we * re_)


def _group_parts(point, vals, groups):
    """Each group's rows sorted by point: ``(points, rows, cols slice, vals (n_g, width))`` (``rows`` a slice, and
    the rest views, when the group's rows are one slice already in point order)."""
    out = []
    for rows, cols in groups:
        rows = rows if isinstance(rows, slice) else np.asarray(rows)
        pts = point[rows]
        if pts.size > 1 and np.any(pts[1:] < pts[:-1]):
            rows = np.arange(rows.start, rows.stop) if isinstance(rows, slice) else rows
            o = np.argsort(pts, kind="stable")
            rows, pts = rows[o], pts[o]
        out.append((pts, rows, cols, vals[rows, :cols.stop - cols.start]))
    return out


def _sub(rows, i: int, j: int):
    """Rows ``i:j`` of a group's ``rows`` (a slice or indices)."""
    return slice(rows.start + i, rows.start + j) if isinstance(rows, slice) else rows[i:j]


def _npg_groups(parts, jw, lo: int, hi: int, q: int, p: int) -> np.ndarray:
    """``N_pg`` of the points ``lo:hi`` transposed, ``(p, q, hi - lo)``: each group sets its columns of the points it
    sees (once each) by 1-D scatters."""
    npg = np.zeros((p, q, hi - lo))
    for pts, rows, cols, a in parts:
        i, j = np.searchsorted(pts, [lo, hi])
        if j > i:
            at, jwr, ar = pts[i:j] - lo, jw[_sub(rows, i, j)], a[i:j]
            for c in range(cols.stop - cols.start):
                for k in range(q):
                    npg[cols.start + c, k, at] = jwr[:, k] * ar[:, c]
    return npg


def _cholesky_t(inv0: np.ndarray) -> np.ndarray:
    """``L`` (q, q, n) with ``L L^T = inv0`` per point (closed-form Cholesky; 0 for a zero block); NaN where a
    block is not positive definite."""
    n, q, _ = inv0.shape
    a = inv0.transpose(1, 2, 0)
    low = np.zeros((q, q, n))
    with np.errstate(invalid="ignore", divide="ignore"):
        for j in range(q):
            d = a[j, j] - np.sum(low[j, :j] ** 2, axis=0)
            low[j, j] = np.where(d == 0, 0.0, np.sqrt(np.where(d >= 0, d, np.nan)))
            for i in range(j + 1, q):
                low[i, j] = np.where(low[j, j] > 0, (a[i, j] - np.sum(low[i, :j] * low[j, :j], axis=0))
                                     / low[j, j], 0.0)
    return low


def _padded_columns(parts, p: int) -> np.ndarray:
    """``M`` (G c, p): column ``c`` of group ``g`` in the padded layout (``c`` the widest group) -> its parameter."""
    c = max(cols.stop - cols.start for _, _, cols, _ in parts)
    m = np.zeros((len(parts) * c, p))
    for g, (_, _, cols, _) in enumerate(parts):
        m[g * c + np.arange(cols.stop - cols.start), np.arange(cols.start, cols.stop)] = 1.0
    return m


def _y_groups(parts, jw, low, lo: int, hi: int) -> np.ndarray:
    """``Y^T = (L^T N_pg)^T`` of the points ``lo:hi`` in the padded columns (:func:`_padded_columns`), ``(G c,
    q (hi - lo))``: each group's ``w jp`` and ``a`` placed densely by point (1-D scatters), ``L^T w jp`` then
    ``(L^T w jp) a^T`` per point and group, dense."""
    m, q, c = hi - lo, jw.shape[1], max(cols.stop - cols.start for _, _, cols, _ in parts)
    jwd, ad = np.zeros((len(parts), q, m)), np.zeros((len(parts), c, m))
    for g, (pts, rows, cols, a) in enumerate(parts):
        i, j = np.searchsorted(pts, [lo, hi])
        if j > i:
            at, jr, ar = pts[i:j] - lo, jw[_sub(rows, i, j)], a[i:j]
            for k in range(q):
                jwd[g, k, at] = jr[:, k]
            for k in range(cols.stop - cols.start):
                ad[g, k, at] = ar[:, k]
    lt = low[:, :, lo:hi]
    ld = np.stack([sum(lt[j, k] * jwd[:, j, :] for j in range(k, q)) for k in range(q)], axis=1)   # (G, q, m)
    return (ad[:, :, None, :] * ld[:, None, :, :]).reshape(len(parts) * c, q * m)


def _points_share(parts, jw, low, inv0, pd_ok, sl: slice, p: int):
    """The points ``sl``'s share of the reduced system: ``(Y Y^T, None)`` in the padded columns, or, with a block
    not quite positive definite among them, ``(None, N_gp N_pp^-1 N_pg)``."""
    if pd_ok[sl].all():
        y = _y_groups(parts, jw, low, sl.start, sl.stop)
        return y @ y.T, None                                                   # symmetric: BLAS syrk
    q = jw.shape[1]
    npg, blk = _npg_groups(parts, jw, sl.start, sl.stop, q, p), inv0[sl]
    out = np.zeros((p, p))
    for k in range(q):
        out += npg[:, k, :] @ sum(blk[:, k, j] * npg[:, j, :] for j in range(q)).T
    return None, out


def _eliminate_groups(point, jw, r, w, vals, groups, npp, bp, inv, ok, p: int, extra, covariance: bool):
    """:func:`_eliminate` for rows in groups (:func:`solve_rows`): the same reduced system, by slices; the
    points' share ``N_gp N_pp^-1 N_pg = Y^T Y`` with ``Y = L^T N_pg`` (``L L^T = N_pp^-1``), one symmetric
    product per chunk (a chunk with a block not quite positive definite: ``N_gp N_pp^-1 N_pg`` as it is)."""
    n, q = bp.shape
    parts = _group_parts(point, vals, groups)
    ngg, bg = np.zeros((p, p)), np.zeros(p)
    for _, rows, cols, a in parts:
        wa = a * w[rows][:, None]
        ngg[cols, cols] += wa.T @ a
        bg[cols] += wa.T @ r[rows]
    s_mat, b_red = _add_extra(ngg, bg, extra)
    inv0 = np.where(ok[:, None, None], np.nan_to_num(inv), 0.0)
    u = np.matmul(inv0, bp[:, :, None])[:, :, 0]                               # N_pp^-1 b_p
    ju = sum(jw[:, k] * u[:, k][point] for k in range(q))                     # (w jp) . N_pp^-1 b_p per row
    for _, rows, cols, a in parts:                                             # N_gp N_pp^-1 b_p
        b_red[cols] -= a.T @ ju[rows]
    low = _cholesky_t(inv0)
    pd_ok = np.all(np.isfinite(low), axis=(0, 1))
    chunks = list(_chunks(n, q, p))
    shares = map_blocks(lambda b: [_points_share(parts, jw, low, inv0, pd_ok, chunks[i], p)
                                   for i in range(b.start, b.stop)], len(chunks), block=1)
    pad = _padded_columns(parts, p)
    s_pad = np.zeros((pad.shape[0],) * 2)
    for padded, direct in (share for blk in shares for share in blk):          # in chunk order, whatever threads
        if padded is not None:
            s_pad += padded
        else:
            s_mat = s_mat - direct
    dxg, cov_g = _solve_reduced(s_mat - pad.T @ s_pad @ pad, b_red)
    a_dx = np.zeros(point.size)                                                # each row's global move
    for _, rows, cols, a in parts:
        a_dx[rows] = a @ dxg[cols]
    rhs = bp - np.stack([np.bincount(point, weights=jw[:, k] * a_dx, minlength=n) for k in range(q)], axis=1)
    dxp = np.full((n, q), np.nan)
    dxp[ok] = np.matmul(inv[ok], rhs[ok][:, :, None])[:, :, 0]
    cov_p = inv.copy() if covariance else np.empty((0, q, q))
    if covariance:
        for sl in _chunks(n, q, p):
            t = np.matmul(inv0[sl], _npg_groups(parts, jw, sl.start, sl.stop, q, p).transpose(2, 1, 0))
            cov_p[sl] = np.where(ok[sl, None, None], inv[sl] + np.matmul(t @ cov_g, t.transpose(0, 2, 1)), inv[sl])
    return dxp, cov_p, ok, dxg, cov_g


def _eliminate(rows: _Rows, npp, bp, inv, ok, p: int, extra, covariance: bool):
    """The one elimination of both entries: ``S = N_gg - sum N_gp N_pp^-1 N_pg`` over chunks of points, its
    solve, the points' back-substitution (and their covariance)."""
    n, q = bp.shape
    if p == 0:                                                                  # points alone
        dxp = np.full((n, q), np.nan)
        dxp[ok] = np.matmul(inv[ok], bp[ok][:, :, None])[:, :, 0]
        return dxp, inv.copy() if covariance else np.empty((0, q, q)), ok, np.zeros(0), np.zeros((0, 0))
    ngg, bg = _add_extra(*_global_normals(rows, p), extra)
    inv0 = np.where(ok[:, None, None], np.nan_to_num(inv), 0.0)
    s_mat, b_red = ngg.copy(), bg.copy()
    for sl in _chunks(n, q, p):
        npg = _npg(rows, sl.start, sl.stop, q, p)
        t = np.matmul(inv0[sl], npg)                                           # N_pp^-1 N_pg
        s_mat -= npg.reshape(-1, p).T @ t.reshape(-1, p)
        b_red -= np.einsum("nqi,nq->i", t, bp[sl])
    dxg, cov_g = _solve_reduced(s_mat, b_red)
    a_dx = np.einsum("mc,mc->m", rows.vals, dxg[rows.cols])                   # each row's global move
    rhs = bp - np.stack([np.bincount(rows.point, weights=rows.jw[:, a] * a_dx, minlength=n) for a in range(q)],
                        axis=1)
    dxp = np.full((n, q), np.nan)
    dxp[ok] = np.matmul(inv[ok], rhs[ok][:, :, None])[:, :, 0]
    cov_p = inv.copy() if covariance else np.empty((0, q, q))
    if covariance:
        for sl in _chunks(n, q, p):
            t = np.matmul(inv0[sl], _npg(rows, sl.start, sl.stop, q, p))
            cov_p[sl] = np.where(ok[sl, None, None], inv[sl] + np.matmul(t @ cov_g, t.transpose(0, 2, 1)), inv[sl])
    return dxp, cov_p, ok, dxg, cov_g
