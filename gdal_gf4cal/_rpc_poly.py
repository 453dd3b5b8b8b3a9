"""The 20 RPC00B terms and their derivatives (METHODS §1): the polynomial core shared by the RPC model, the RPC
fit and the DEM-intersection fast path of the localisation layer (kept apart so none of them imports another)."""
from __future__ import annotations

import threading
from contextlib import contextmanager
from typing import Iterator, Optional

import numpy as np

from .threads import blas_is_serial, matmul, product_into

#: The 20 terms in RPC00B order (P = normalised latitude, L = longitude, H = height).
TERMS = ("1", "L", "P", "H", "LP", "LH", "PH", "L2", "P2", "H2", "PLH", "L3", "LP2", "LH2", "L2P", "P3", "PH2",
         "L2H", "P2H", "H3")

#: Exponents (of L, P, H) of the 20 terms, in RPC00B order.
_EXPONENTS = ((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1), (2, 0, 0), (0, 2, 0),
              (0, 0, 2), (1, 1, 1), (3, 0, 0), (1, 2, 0), (1, 0, 2), (2, 1, 0), (0, 3, 0), (0, 1, 2), (2, 0, 1),
              (0, 2, 1), (0, 0, 3))


def _derivative_matrix(axis: int) -> np.ndarray:
    """D (20, 20) with d(term_j)/d(axis) = sum_k D[j, k] term_k: derivatives stay in the 20-term basis."""
    index = {e: k for k, e in enumerate(_EXPONENTS)}
    D = np.zeros((20, 20))
    for j, e in enumerate(_EXPONENTS):
        if e[axis]:
            lowered = list(e)
            lowered[axis] -= 1
            D[j, index[tuple(lowered)]] = e[axis]
    return D


#: d/dL, d/dP, d/dH as (20, 20) basis maps: coefficients of the derivative polynomial = coeffs @ D.
DERIVATIVE_MATRICES = tuple(_derivative_matrix(a) for a in range(3))

#: Chunk of points processed at once by the kernels' polynomial evaluations (each point is evaluated on its own: the
#: chunk size never changes a bit of the result). 8192 points (a 1.3 MB monomial block): as fast as 4096 per localised
#: point with half the NumPy calls (calls hold the GIL: what threads cannot share); 16384 was 2x slower (runs on the
#: loaded 2-core machine, RPCModel.localize solving chunks of 16384 points).
_CHUNK = 8192


def monomials(L: np.ndarray, P: np.ndarray, H: np.ndarray) -> np.ndarray:
    """The 20 RPC00B monomials of normalised (L, P, H), shape ``(20, N)`` (term-major, METHODS §1).

    Term-major layout makes each row a contiguous vector, so ``coeffs @ monomials(...)`` evaluates several
    polynomials at once with one BLAS call. Use ``.T`` for a point-major ``(N, 20)`` design matrix.
    """
    L = np.asarray(L, dtype=float).ravel()
    P = np.asarray(P, dtype=float).ravel()
    H = np.asarray(H, dtype=float).ravel()
    m = np.empty((20, L.size))
    m[0] = 1.0
    m[1] = L
    m[2] = P
    m[3] = H
    fill_monomials(m)
    return m


def fill_monomials(m: np.ndarray, views: Optional[tuple] = None) -> np.ndarray:
    """Rows 4..19 of the monomial matrix ``m`` (20, N) from its rows 1..3 (L, P, H), in place (row 0 is the
    caller's: 1), in 5 broadcast products (NumPy's per-call cost dominates a cache-sized chunk): a kernel can keep
    one buffer per chunk instead of allocating one. Each monomial is the same product of the same factors whatever
    the call grouping (``L3 = L * L2``, ``L2P = P * L2``, ``PLH = LP * H``...): the same bits. ``views``: the
    operands of the products, :func:`monomial_views` of ``m``, for a kernel filling one buffer several times."""
    v = monomial_views(m) if views is None else views
    for a, b, out in v:
        np.multiply(a, b, out=out)
    return m


def monomial_views(m: np.ndarray) -> tuple:
    """The operands of :func:`fill_monomials`' five products in ``m`` (20, N), in order."""
    lph = m[1:4]                                         # L, P, H
    return ((m[1], m[2:4], m[4:6]),                      # LP, LH
            (m[2], m[3], m[6]),                          # PH
            (lph, lph, m[7:10]),                         # L2, P2, H2
            (m[4], m[3], m[10]),                         # PLH
            # [L, P, H] x [L2, P2, H2]: L3, LP2, LH2, L2P, P3, PH2, L2H, P2H, H3 (splitting an axis: a view)
            (lph[:, None], m[7:10], m[11:20].reshape(3, 3, m.shape[1])))


#: Largest scratch buffer (columns) a thread keeps between calls (:func:`scratch`).
_SCRATCH_MAX_COLS = 65536
_local = threading.local()


@contextmanager
def scratch(rows: int, cols: int) -> Iterator[np.ndarray]:
    """A (rows, cols) float buffer of the calling thread, kept between calls (one per row count, up to
    :data:`_SCRATCH_MAX_COLS` columns): the kernels' per-call work buffers of a megabyte or more were fresh memory at
    every call, ~900 page faults (4 us each here) per Jacobian of 16384 points, 4x its arithmetic. A nested request
    for the same row count while the buffer is in use gets a fresh one; contents are undefined."""
    pool = _local.__dict__.setdefault("free", {})
    buf = pool.pop(rows, None)
    if buf is None or buf.shape[1] < cols:
        buf = np.empty((rows, cols))
    try:
        yield buf[:, :cols]
    finally:
        if buf.shape[1] <= _SCRATCH_MAX_COLS:
            pool[rows] = buf


def poly_product(a: np.ndarray, b: np.ndarray, out: Optional[np.ndarray] = None) -> np.ndarray:
    """``a @ b`` of a kernel's (k, 20) (or fewer terms) coefficients and its (20, n) monomials: one product when
    BLAS is held on the calling thread (:func:`~gdal_gf4cal.threads.blas_is_serial`: inside ``limit``, ``serial``,
    every block on the pool and every ``gf4cal`` command), else :func:`~gdal_gf4cal.threads.matmul`'s slices BLAS
    keeps on the calling thread. Each column is the same short dot product either way: the same bits (tested), a
    tenth of the calls of a (12, 20) Jacobian, ~8 % less CPU per localised point."""
    if blas_is_serial():
        return product_into(a, b, np.empty((a.shape[0], b.shape[1]), np.result_type(a, b)) if out is None else out)
    return matmul(a, b, out=out)


def monomial_chunks(L: np.ndarray, P: np.ndarray, H: np.ndarray, chunk: Optional[int] = None):
    """``(i, j, m)`` for the points ``i:j`` of flat L, P, H, chunk by chunk (of :data:`_CHUNK` points by default):
    ``m`` their (20, j - i) monomials (the bits of :func:`monomials`) in one buffer reused for every chunk (valid
    until the next one): no allocation per chunk in the kernels' loops."""
    n = L.size
    c = max(1, min(n, _CHUNK if chunk is None else chunk))
    with scratch(20, c) as m:
        m[0] = 1.0
        for i in range(0, n, c):
            j = min(i + c, n)
            if j - i < c:
                m = m[:, :j - i]
            m[1] = L[i:j]
            m[2] = P[i:j]
            m[3] = H[i:j]
            yield i, j, fill_monomials(m)


def monomial_derivatives(L: np.ndarray, P: np.ndarray, H: np.ndarray, with_h: bool = True):
    """Partial derivatives of :func:`monomials` with respect to L, P and H, each ``(20, N)``.

    With ``with_h=False`` the third item is ``None`` (saves a third of the work when H is fixed).
    """
    L = np.asarray(L, dtype=float).ravel()
    P = np.asarray(P, dtype=float).ravel()
    H = np.asarray(H, dtype=float).ravel()
    n = L.size
    one, zero = np.ones(n), np.zeros(n)
    LL, PP, HH, LP, LH, PH = L * L, P * P, H * H, L * P, L * H, P * H
    dL = np.stack([zero, one, zero, zero, P, H, zero, 2 * L, zero, zero, PH, 3 * LL, PP, HH, 2 * LP, zero, zero,
                   2 * LH, zero, zero])
    dP = np.stack([zero, zero, one, zero, L, zero, H, zero, 2 * P, zero, LH, zero, 2 * LP, zero, LL, 3 * PP, HH,
                   zero, 2 * PH, zero])
    if not with_h:
        return dL, dP, None
    dH = np.stack([zero, zero, zero, one, zero, L, P, zero, zero, 2 * H, LP, zero, zero, 2 * LH, zero, zero, 2 * PH,
                   LL, PP, 3 * HH])
    return dL, dP, dH
