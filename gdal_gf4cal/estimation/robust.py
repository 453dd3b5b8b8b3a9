"""The robust estimator's parts (METHODS §4, §6): a high-breakdown start, then data snooping with Student-t thresholds
(the loop itself is the one robust driver, :func:`~gdal_gf4cal.estimation.robust_fit` in ``driver.py``).

Observations come per *point* (a GCP gives a sample and a line observation; a tie point one pair per image):
``design`` has shape ``(n_points, k, p)``, ``obs`` and ``weights`` ``(n_points, k)``; or, for the start, a *shared*
design ``(n_points, q)``: each of the ``k`` axes its own ``q`` parameters on the same row (a compensation with the
same terms on both axes), at the cost of one axis. A point is in or out as a whole.

1. **Start** (:func:`high_breakdown_start`): least trimmed squares over the ``h = (n + m + 1) // 2`` best points
   (``m`` the minimal number of points that determine the parameters), searched from every minimal subset when
   ``C(n, m)`` is small, else from ``n_subsets`` seeded random ones, each improved by one concentration step
   (refit on its ``h`` best points). Up to ``n - h`` blunders, even coherent ones (the same offset on many
   points), cannot pull the start; this is what an M-estimator started from least squares cannot do (2 blunders
   in 7 GCPs broke it).
2. **Reweighting**: the start's scale (consistency-corrected) keeps the points within the 99.9 % chi-square
   bound, each residual normalised by its own variance (``1 -/+ leverage`` inside/outside the fit); least
   squares on them, until the set is stable. The same from all points: when that set is larger and its scale not
   significantly larger (F test, 1 %), the start only over-fitted its trimmed half and the larger set is kept.
3. **Data snooping**: normalised residuals (Baarda's w) of every point, in or out, against
   :func:`critical_value`; points are left out while they exceed it, until the set is stable. A point out of the
   fit comes back only when it also passes :func:`readmissible` (its residuals jointly consistent with the fit,
   F test at 1 %): a hysteresis. With little redundancy the Student-t threshold is very wide (17 for 4 degrees of
   freedom), and without it a 60 px blunder outside a 5-point affine fit (its prediction variance inflated by
   extrapolation) was let back in, inflated sigma and pulled its fellow blunder in after it (2 in 7 GCPs
   masked).
"""
from __future__ import annotations

import math
from contextlib import nullcontext
from functools import lru_cache
from itertools import combinations
from typing import Optional, Tuple

import numpy as np

from ..errors import DegenerateGeometryError
from ..threads import blas_serial, rows_times
from .lsq import gram

#: Largest number of minimal subsets searched exhaustively; beyond it ``n_subsets`` random ones are drawn.
MAX_EXHAUSTIVE = 3000
#: Significance level of the re-admission test (:func:`readmissible`).
READMIT_LEVEL = 0.01


@lru_cache(maxsize=256)
def critical_value(threshold: float, dof: int) -> float:
    """Critical normalised residual for ``dof`` degrees of freedom of the estimated sigma (METHODS §4, §6).

    ``threshold`` is read as a standard-normal quantile (large redundancy, Baarda's w-test). The residuals are
    normalised with an *estimated* sigma, so with few redundant observations they follow Student's t: the
    threshold becomes the t quantile of the same two-sided probability.
    """
    from scipy import stats     # ~1 s to import: only when first needed (CLI, QGIS start-up)
    if dof <= 0:
        return math.inf
    return float(stats.t.isf(stats.norm.sf(threshold), dof))


def readmissible(normalised, dof: int, *, threshold: float = 4.0, sigma: float = 1.0, start_sigma: float = 0.0,
                 level: Optional[float] = None) -> np.ndarray:
    """Per point out of a fit, True when its ``k`` normalised residuals (``(n, k)``, each scaled by the fit's
    ``sigma`` and its own prediction variance) are jointly consistent with the fit: ``q = sum(w^2) / k`` below
    the ``1 - level`` quantile of ``F(k, dof)`` (the nested F test of adding the point; ``dof`` those of the fit's
    sigma), or below the snooping ``threshold`` taken with a known sigma (chi-square of the same probability as
    the per-axis test; the bound with large redundancy). The re-admission side of the snooping hysteresis
    (module docstring, step 3): with 4 degrees of freedom a point stays out above q = 18 (the Student-t
    threshold would let it back up to |w| = 17 per axis), with 40 above q = 9 (|w| ~ 4.2 on one axis).

    ``start_sigma`` (the ``lts_scale`` of :func:`high_breakdown_start`) floors the sigma: the plain scale of a
    trimmed set that was chosen for fitting best is biased low (4 of 6 points), the LTS scale is corrected for
    the trimming."""
    w = np.nan_to_num(np.asarray(normalised, dtype=float), nan=0.0)
    w = w.reshape(w.shape[0], -1)
    k = w.shape[1]
    if start_sigma > sigma > 0:
        w = w * (sigma / start_sigma)
    if dof <= 0:
        return np.ones(w.shape[0], bool)
    level = READMIT_LEVEL if level is None else level
    bound = max(_f_ppf(1.0 - level, k, int(dof)), _chi2_isf(k * _norm_sf2(threshold), k) / k)
    return np.sum(w * w, axis=1) / k <= bound


@lru_cache(maxsize=64)
def _norm_sf2(threshold: float) -> float:
    from scipy import stats     # ~1 s to import: only when first needed (CLI, QGIS start-up)
    return float(2.0 * stats.norm.sf(threshold))


@lru_cache(maxsize=64)
def _chi2_isf(p: float, k: int) -> float:
    from scipy import stats     # ~1 s to import: only when first needed (CLI, QGIS start-up)
    return float(stats.chi2.isf(min(p, 1.0), k))


def min_subset_points(design) -> int:
    """Points in a minimal subset of ``design`` (n, k, p): ``ceil(p / k)`` when the axes share parameters, and at
    least the parameters of any axis estimated independently of the others (columns non-zero on that axis
    only: a block-diagonal affine, 3 + 3 parameters, needs 3 points; a detector polynomial with 4 sample and
    1 line parameters needs 4, not 3)."""
    a = np.asarray(design)
    n, k, p = a.shape
    on_axis = np.any(a != 0, axis=0)                                   # (k, p)
    own = on_axis & (on_axis.sum(axis=0) == 1)[None, :]
    return int(max(math.ceil(p / k), int(own.sum(axis=1).max()) if k > 1 else p))


#: Chance that every random subset of the search holds a blunder which :func:`subset_count` allows: that of the
#: default 300 subsets of 6 points (poly2) at 40 % blunders, 6e-7.
SEARCH_MISS = (1.0 - 0.6 ** 6) ** 300


def subset_count(m: int, blunders: float = 0.4, most: int = 300) -> int:
    """Random minimal subsets of ``m`` points that hold a clean one but with probability :data:`SEARCH_MISS` when
    a share ``blunders`` of the points are blunders (``log(miss) / log(1 - (1 - blunders)^m)``, at most
    ``most``): 59 for 3-point subsets (affine), 300 for 6 (poly2), the same guarantee at a fifth of the search."""
    clean = (1.0 - blunders) ** int(m)
    if clean >= 1.0:
        return 1
    return int(min(most, max(1, math.ceil(math.log(SEARCH_MISS) / math.log1p(-clean) - 1e-9))))


def _subsets(n: int, m: int, n_subsets: int, seed: int) -> np.ndarray:
    if math.comb(n, m) <= MAX_EXHAUSTIVE:
        return np.array(list(combinations(range(n), m)), dtype=np.intp).reshape(-1, m)
    keys = np.random.default_rng(seed).random((n_subsets, n))
    # the m smallest of n uniform keys per row: a uniform random m-subset (argpartition: the same sets as a full
    # argsort, in O(n)); for the few points of a small subset, m argmin passes find the same sets 2-4x faster
    if m > _ARGMIN_SUBSET:
        return np.argpartition(keys, m - 1, axis=1)[:, :m]
    out = np.empty((n_subsets, m), dtype=np.intp)
    rows = np.arange(n_subsets)
    for i in range(m):
        out[:, i] = np.argmin(keys, axis=1)
        keys[rows, out[:, i]] = np.inf
    return out


#: Largest minimal subset drawn by argmin passes (:func:`_subsets`).
_ARGMIN_SUBSET = 8


def _normal_parts(a: np.ndarray, y: np.ndarray, w: np.ndarray, scale: np.ndarray):
    """Per-point outer products (n, q*q) and right-hand sides (n, q*c) of the column-scaled normal equations
    (``a`` (n, g, q), ``y`` (n, g, c), ``w`` (n, g): :func:`_layout`): computed once per point set, shared by every
    :func:`_batched_fit` on it."""
    n, g, q = a.shape
    aw = a / scale                                                   # (n, g, q) column-scaled
    wa = aw * w[:, :, None]
    outer = np.matmul(wa.transpose(0, 2, 1), aw).reshape(n, q * q)   # sum_g w a a^T per point
    rhs = np.sum(wa[:, :, :, None] * y[:, :, None, :], axis=1)       # sum_g w a y^T per point
    return outer, rhs.reshape(n, -1)


def _batched_fit(a: np.ndarray, y: np.ndarray, w: np.ndarray, mask: np.ndarray, scale: np.ndarray, parts=None):
    """Weighted LS for each row of ``mask`` (K, n) over the points it selects (:func:`_layout`'s arrays); returns
    (x (K, q, c), ok (K,)).

    The K normal matrices are one matrix product ``mask @ (per-point outer products)`` (BLAS), not a loop;
    ``parts`` (:func:`_normal_parts`) avoids recomputing the per-point products.
    """
    n, g, q = a.shape
    c = y.shape[2]
    outer, rhs_pt = _normal_parts(a, y, w, scale) if parts is None else parts
    nmat, rhs = (mask @ outer).reshape(-1, q, q), (mask @ rhs_pt).reshape(-1, q, c)
    # Regular subsets: the column-scaled normal matrix (diagonal <= 1) has a determinant well above zero (the c
    # axes of a shared design: the same test as on their block-diagonal joint matrix).
    sign, logdet = np.linalg.slogdet(nmat)
    ok = (sign > 0) & (logdet > q * math.log(1e-10))
    nmat = np.where(ok[:, None, None], nmat, np.eye(q))
    try:
        x = np.linalg.solve(nmat, rhs) / scale[:, None]
    except np.linalg.LinAlgError:          # a subset singular despite its determinant (e.g. an empty piece)
        x = np.zeros((len(nmat), q, c))
        for i in np.flatnonzero(ok):
            try:
                x[i] = np.linalg.solve(nmat[i], rhs[i]) / scale[:, None]
            except np.linalg.LinAlgError:
                ok[i] = False
    return x, ok


@lru_cache(maxsize=256)
def _lts_consistency(h: int, n: int, k: int) -> float:
    from scipy import stats     # ~1 s to import: only when first needed (CLI, QGIS start-up)
    alpha = h / n
    return float(k * stats.chi2.cdf(stats.chi2.ppf(alpha, k), k + 2) / alpha) if alpha < 1 else float(k)


@lru_cache(maxsize=64)
def _chi2_ppf(p: float, k: int) -> float:
    from scipy import stats     # ~1 s to import: only when first needed (CLI, QGIS start-up)
    return float(stats.chi2.ppf(p, k))


@lru_cache(maxsize=1024)
def _f_ppf(p: float, d1: int, d2: int) -> float:
    from scipy import stats     # ~1 s to import: only when first needed (CLI, QGIS start-up)
    return float(stats.f.ppf(p, d1, d2))


#: :meth:`_AllPoints.inflation` without an inverse: fit the set first.
_FIT = object()


class _OuterFits:
    """The start's fits of one point set from the per-point outer products (:func:`_batched_fit` of one mask) and
    the leverages from their own normal matrix (:func:`_inflation`): the default evaluation of
    :func:`high_breakdown_start` (its numbers since issue 10; :class:`_AllPoints` is the faster one). Arrays as
    :func:`_layout`'s, parameters ``x`` (q, c)."""

    def __init__(self, a: np.ndarray, y: np.ndarray, w: np.ndarray, scale: np.ndarray, parts):
        self.a, self.y, self.w, self.scale, self.parts = a, y, w, scale, parts

    def fit(self, mask: np.ndarray):
        x, ok = _batched_fit(self.a, self.y, self.w, mask[None].astype(float), self.scale, self.parts)
        return (x[0] if ok[0] else None), None

    def sq(self, x: np.ndarray) -> np.ndarray:
        return _point_sq(self.a, self.y, self.w, x[None])[0]

    def inflation(self, fit_set: np.ndarray, ninv=None) -> np.ndarray:
        return _inflation(self.a, self.w, fit_set, self.scale)


def _inflation(a: np.ndarray, w: np.ndarray, fit_set: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Per point, the factor of sigma^2 in the expected squared residual norm over its observations: ``1 - lev``
    inside ``fit_set``, ``1 + lev`` outside it (``lev`` the mean leverage of the point's observations; ``a``
    (n, g, q), ``w`` (n, g): :func:`_layout`, the c axes of a shared row have its leverage)."""
    n, g, q = a.shape
    aw = a / scale
    rows = (aw * np.sqrt(w * fit_set[:, None])[:, :, None]).reshape(n * g, q)
    nmat = rows.T @ rows
    try:
        ninv = np.linalg.inv(nmat)
    except np.linalg.LinAlgError:
        return np.ones(n)
    lev = np.sum(w * np.sum((aw @ ninv) * aw, axis=2), axis=1) / g
    return np.maximum(np.where(fit_set, 1.0 - lev, 1.0 + lev), 1e-6)


class _AllPoints:
    """Every point's rows as column-scaled rows ``(n * g, q)`` for the start's fits of one point set
    (concentration, reweighting; arrays as :func:`_layout`'s, parameters ``x`` (q, c)): one ``A^T W A``
    (:func:`~gdal_gf4cal.estimation.lsq.gram`, BLAS on the calling thread) per fit for all c axes, its inverse
    shared with the leverages of the same set (:meth:`inflation`); no per-point outer products."""

    def __init__(self, a: np.ndarray, y: np.ndarray, w: np.ndarray, scale: np.ndarray):
        n, g, q = a.shape
        self.n, self.g, self.q, self.scale = n, g, q, scale
        self.rows = (a / scale).reshape(n * g, q)
        self.y, self.w = y.reshape(n * g, -1), np.ascontiguousarray(w).reshape(-1)

    def fit(self, mask: np.ndarray):
        """``(x or None, column-scaled N^-1 or None)`` of the weighted LS over the points of ``mask`` (bool (n,)):
        ``x`` None when the set does not determine the parameters (the determinant test of :func:`_batched_fit`),
        ``N^-1`` None when ``N`` cannot be inverted."""
        wa = self.rows * (self.w * np.repeat(mask, self.g))[:, None]
        nmat = gram(wa, self.rows)
        rhs = gram(wa, self.y)
        try:
            ninv = np.linalg.inv(nmat)
        except np.linalg.LinAlgError:
            ninv = None
        sign, logdet = np.linalg.slogdet(nmat)
        if ninv is None or not (sign > 0 and logdet > self.q * math.log(1e-10)):
            return None, ninv
        try:
            return np.linalg.solve(nmat, rhs) / self.scale[:, None], ninv
        except np.linalg.LinAlgError:
            return None, ninv

    def sq(self, x: np.ndarray) -> np.ndarray:
        """Weighted squared residual norm per point (n,) of the parameters ``x`` (q, c)."""
        b = x * self.scale[:, None]
        # one axis: the matrix-vector product (its own BLAS kernel, the numbers of the joint design since issue 23)
        r = self.y - (rows_times(self.rows, b[:, 0])[:, None] if b.shape[1] == 1 else rows_times(self.rows, b))
        if self.g == 1:                                  # a shared design: the row's weight times its axes' sum
            return self.w * np.einsum("ij,ij->i", r, r)
        return np.sum((self.w[:, None] * r * r).reshape(self.n, -1), axis=1)

    def inflation(self, fit_set: np.ndarray, ninv=_FIT) -> np.ndarray:
        """Per point, the factor of sigma^2 in the expected squared residual norm over its observations:
        ``1 - lev`` inside ``fit_set``, ``1 + lev`` outside it (``lev`` the mean leverage of the point's
        observations; ``ninv`` from :meth:`fit` on ``fit_set``, fitted here when not given; None: factor 1)."""
        if ninv is _FIT:
            ninv = self.fit(fit_set)[1]
        if ninv is None:
            return np.ones(self.n)
        lev = self.w * np.einsum("ij,ij->i", rows_times(self.rows, ninv), self.rows)     # per row
        if self.g > 1:
            lev = np.sum(lev.reshape(self.n, self.g), axis=1) / self.g
        return np.maximum(np.where(fit_set, 1.0 - lev, 1.0 + lev), 1e-6)


def _point_sq(a, y, w, x):
    """Weighted squared residual norm per point for each parameter set of ``x`` (K, q, c): (K, n).

    One (n, c K) matrix product per row of a point (g is 1 or 2): no (n, g, K) temporaries."""
    n_sets, q, c = x.shape
    xt = x.transpose(1, 2, 0).reshape(q, c * n_sets)                 # (q, c K): the K sets of each axis together
    out = None
    for j in range(a.shape[1]):
        r = y[:, j, :, None] - (a[:, j, :] @ xt).reshape(-1, c, n_sets)     # (n, c, K)
        r *= r
        r *= w[:, j, None, None]
        for i in range(c):
            out = r[:, i] if out is None else out + r[:, i]
    return out.T


def _layout(design, obs, weights):
    """``(a (n, g, q), y (n, g, c), w (n, g))`` of :func:`high_breakdown_start`'s input: a point's ``g`` design
    rows, each with ``c`` observations of its own parameters (``x`` (q, c)). A design ``(n, k, p)``: ``g = k``,
    ``c = 1``; a shared design ``(n, q)`` with ``obs`` (n, k), ``weights`` (n,): ``g = 1``, ``c = k``."""
    a = np.asarray(design, dtype=float)
    n = a.shape[0]
    if a.ndim == 2:
        w = np.ones(n) if weights is None else np.broadcast_to(np.asarray(weights, float), (n,))
        return a[:, None, :], np.asarray(obs, dtype=float).reshape(n, 1, -1), w.reshape(n, 1)
    k = a.shape[1]
    w = np.ones((n, k)) if weights is None else np.broadcast_to(np.asarray(weights, float), (n, k))
    return a, np.asarray(obs, dtype=float).reshape(n, k, 1), w


def _search(a, y, w, scale, m: int, n_subsets: int, seed: int, chunk: int):
    """The subset search of :func:`high_breakdown_start` on the points given (:func:`_layout`'s arrays): every
    subset's fit improved by one concentration step (refit on its ``h`` best points). Returns ``(x (q, c) of
    the best or None, its trimmed criterion, subsets searched, per-point products)``."""
    n = a.shape[0]
    h = min(n, max((n + m + 1) // 2, m + 1))
    parts = _normal_parts(a, y, w, scale)
    subs = _subsets(n, m, n_subsets, seed)
    best_crit, best_x = math.inf, None
    for c0 in range(0, len(subs), chunk):
        sub = subs[c0:c0 + chunk]
        mask = np.zeros((len(sub), n))
        np.put_along_axis(mask, sub, 1.0, axis=1)
        x, ok = _batched_fit(a, y, w, mask, scale, parts)
        if not ok.any():
            continue
        x = x[ok]
        r2 = _point_sq(a, y, w, x)
        keep = np.argpartition(r2, h - 1, axis=1)[:, :h]
        mask = np.zeros((len(x), n))
        np.put_along_axis(mask, keep, 1.0, axis=1)
        x2, ok2 = _batched_fit(a, y, w, mask, scale, parts)
        x = np.where(ok2[:, None, None], x2, x)
        r2 = _point_sq(a, y, w, x)
        crit = np.sum(np.partition(r2, h - 1, axis=1)[:, :h], axis=1)
        i = int(np.argmin(crit))
        if crit[i] < best_crit:
            best_crit, best_x = float(crit[i]), x[i]
    return best_x, best_crit, len(subs), parts


def high_breakdown_start(design, obs, weights=None, *, min_points: Optional[int] = None, n_subsets: int = 300,
                         seed: int = 0, chunk: int = 512, max_search: int = 120,
                         normal: bool = False) -> Tuple[np.ndarray, float, dict]:
    """High-breakdown start (least trimmed squares from minimal subsets), see the module docstring.

    Parameters
    ----------
    design : ndarray (n_points, k, p), or (n_points, q)
        A 2-D design is *shared*: each of the ``k`` axes of ``obs`` has its own ``q`` parameters on the same row
        (a compensation with the same terms on both axes; ``weights`` (n_points,)), the start of the
        block-diagonal ``(n_points, k, k q)`` design at the cost of one axis.
    obs, weights : ndarray (n_points, k)
    min_points : int, optional
        Points in a minimal subset (default :func:`min_subset_points`; ``q`` for a shared design).
    n_subsets : int
        Random subsets when ``C(n, m)`` exceeds :data:`MAX_EXHAUSTIVE` (seeded with ``seed``).
    max_search : int
        Above this many points the subsets are searched on a seeded sample of that size, and the best fit is
        then concentrated on all points (cost independent of ``n``). With 300 random subsets a clean minimal
        subset is near-certain up to 40 % blunders (P(miss) ~ 1e-32 for 3-point subsets, ~ 1e-6 for 6-point ones),
        and 120 searched points keep the start's cost near the M-estimator start it replaced.
    normal : bool
        One-set fits through :class:`_AllPoints`, BLAS on the calling thread
        (:func:`~gdal_gf4cal.threads.blas_serial`: OpenBLAS's threads cost more in synchronisation than the
        hundreds of small solves compute): 3x less CPU on 10,000 points, the same sets to rounding. Default: the
        per-point outer products, BLAS as set (the pan-MS crops' start depends on their rounding).

    Returns
    -------
    inliers : ndarray of bool (n_points,)
    scale : float
        Robust standard deviation of unit weight of the start.
    info : dict
        ``subsets`` (searched), ``exhaustive`` (bool), ``h``, ``lts_scale`` (the trimmed criterion's scale,
        corrected for the trimming; a floor for :func:`readmissible`).
    """
    with (blas_serial() if normal else nullcontext()):
        return _lts_start(*_layout(design, obs, weights), np.ndim(design) == 2, min_points, n_subsets, seed, chunk,
                          max_search, normal)


def _lts_start(a, y, w, shared: bool, min_points, n_subsets: int, seed: int, chunk: int, max_search: int,
               normal: bool):
    """:func:`high_breakdown_start` on :func:`_layout`'s arrays (``shared``: a 2-D design was given).

    (Long by design: one algorithm in coupled steps, the subset search (:func:`_search`), concentration on all
    points, the LTS scale and the reweighting with its all-points comparison, sharing a dozen arrays.)"""
    n, g, q = a.shape
    k, p = g * y.shape[2], q * y.shape[2]                           # observations per point, parameters
    m = int(min_points) if min_points else (q if shared else min_subset_points(a))
    if n <= m:
        return np.ones(n, bool), math.nan, {"subsets": 0, "exhaustive": True, "h": n}
    h = min(n, max((n + m + 1) // 2, m + 1))
    scale = np.sqrt(np.einsum("ngq,ng,ngq->q", a, w, a))
    scale = np.where(scale > 0, scale, 1.0)
    # Large sets: search on a seeded sample of ``max_search`` points (nested subsets, as FAST-LTS); the winner is
    # then concentrated on all points.
    search = np.arange(n) if n <= max_search else np.sort(
        np.random.default_rng(seed + 1).choice(n, max_search, replace=False))
    best_x, best_crit, n_subs, parts = _search(a[search], y[search], w[search], scale, m, n_subsets, seed, chunk)
    info = {"subsets": int(n_subs), "exhaustive": bool(math.comb(search.size, m) <= MAX_EXHAUSTIVE), "h": int(h),
            "searched_points": int(search.size)}
    if best_x is None:
        raise DegenerateGeometryError("no subset of the points determines the parameters; spread the points over "
                                      "the image or estimate fewer parameters")
    pts = _AllPoints(a, y, w, scale) if normal else _OuterFits(
        a, y, w, scale, _normal_parts(a, y, w, scale) if search.size < n else parts)
    r2 = pts.sq(best_x)
    if search.size < n:
        for _ in range(2):                                           # concentration steps on all points
            keep = np.zeros(n, bool)
            keep[np.argpartition(r2, h - 1)[:h]] = True
            x, _ = pts.fit(keep)
            if x is not None:
                best_x = x
                r2 = pts.sq(best_x)
        best_crit = float(np.sum(np.partition(r2, h - 1)[:h]))
    # LTS scale: E[chi2_k | chi2_k <= q] = k F_{k+2}(q) / F_k(q), q the h/n quantile.
    corr = _lts_consistency(h, n, k)
    s2 = best_crit / max(corr * h, 1e-300) * (h * k) / max(h * k - p, 1)
    info["lts_scale"] = float(math.sqrt(max(s2, 0.0)))
    tiny = 1e-18 * max(float(np.median(np.sum((w[:, :, None] * y * y).reshape(n, -1), axis=1))), 1e-300)
    fit_set = np.zeros(n, bool)
    fit_set[np.argpartition(r2, h - 1)[:h]] = True
    inl = r2 / pts.inflation(fit_set) <= _chi2_ppf(0.999, k) * max(s2, tiny)
    inl, s2 = _settle(pts, inl, s2, m, k, p, tiny)
    if search.size < n:
        # A large set: the trimmed half has ample redundancy, so the start cannot have over-fitted it.
        return inl, float(math.sqrt(max(s2, 0.0))), info
    # The same from all points: when its set is larger and its scale is not significantly larger (F test, 1 %),
    # the start only over-fitted a trimmed half (little redundancy) and the larger consensus is kept.
    all_inl, all_s2 = _settle(pts, np.ones(n, bool), s2, m, k, p, tiny)
    if all_inl.sum() > inl.sum():
        d1, d2 = max(int(all_inl.sum()) * k - p, 1), max(int(inl.sum()) * k - p, 1)
        if all_s2 <= _f_ppf(0.99, d1, d2) * max(s2, tiny):
            inl, s2 = all_inl, all_s2
            info["from_all_points"] = True
    return inl, float(math.sqrt(max(s2, 0.0))), info


def _settle(pts, inl, s2: float, m: int, k: int, p: int, tiny: float):
    """Reweighting of :func:`high_breakdown_start`: LS on the inliers ``inl``, plain scale; residuals normalised by
    their own variance (a point outside the fit has variance sigma^2 (1 + leverage), inside sigma^2
    (1 - leverage)), until the inlier set is stable. Returns ``(inliers, scale^2)``."""
    cut = _chi2_ppf(0.999, k)
    for _ in range(10):
        if inl.sum() <= m:
            break
        x, ninv = pts.fit(inl)
        if x is None:
            break
        r2 = pts.sq(x)
        s2 = float(np.sum(r2[inl]) / max(int(inl.sum()) * k - p, 1))
        new = r2 / pts.inflation(inl, ninv) <= cut * max(s2, tiny)
        if np.array_equal(new, inl):
            break
        inl = new
    return inl, s2


#: Median of ``|r| / sigma`` for a 2-D normal residual (Rayleigh), the consistency factor of the radial scale.
RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))


def tukey_weights(z, c: float = 4.685) -> np.ndarray:
    """Tukey's biweight ``(1 - (z/c)^2)^2`` of standardised sizes ``z >= 0``, 0 at and beyond ``c`` (the robust
    driver's :class:`~gdal_gf4cal.estimation.driver.Tukey` and the bundle's view priors)."""
    z = np.asarray(z, dtype=float)
    return np.where(z >= c, 0.0, (1.0 - (z / c) ** 2) ** 2)


def radial_huber_weights(res, sigma, n_params: int, *, huber_c: float = 2.5, reject_k: float = 4.0,
                         min_scale: float = 0.01):
    """Radial (2-D) robust scale and Huber weights of per-point residual pairs (METHODS §5 step 3, §6).

    The scale is MAD-like: the median radial residual ``|r| / sigma`` of a 2-D normal residual is
    ``sqrt(2 ln 2)`` sigma; it is corrected for the parameters' absorption of residual degrees of freedom.
    Residuals below ``min_scale`` (e.g. an RPC's own fitting accuracy, px) are never evidence of a blunder.

    Parameters
    ----------
    res : ndarray (n_points, 2)
    sigma : ndarray (n_points,)
        A-priori standard deviation of each point.

    Returns
    -------
    (weights (n,), reject (n,) bool: beyond ``reject_k``, scale: float, z (n,): radial residual / robust sigma)
    """
    r = np.asarray(res, dtype=float)
    radial_px = np.hypot(r[:, 0], r[:, 1])
    radial = radial_px / sigma
    n_obs = 2 * radial.size
    scale = float(np.median(radial)) / RAYLEIGH_MEDIAN * math.sqrt(n_obs / max(n_obs - n_params, 1))
    scale = max(scale, 1e-12)
    z = radial_px / np.maximum(sigma * scale, min_scale)
    w = np.where(z <= huber_c, 1.0, huber_c / np.maximum(z, 1e-300))
    return w, z > reject_k, scale, z
