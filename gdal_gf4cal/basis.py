"""Polynomial and trigonometric bases of the image-space models (METHODS §4.1, §4.3, §5, §9).

One home for every basis the estimators use; each function returns the design columns with the terms on the
LAST axis, shape ``(..., n_terms)``:

* :func:`monomials` / :func:`monomial_derivatives`: ``u^i v^j`` for given exponents (the compensation models of
  METHODS §4.1, e.g. affine ``1, u, v``; the HJ-1 detector polynomial of §4.3 is ``(k, 0)``, ``k = 0..n``);
* :func:`lookangle_cubic` / :func:`lookangle_cubic_derivatives`: the 10 look-angle terms of METHODS §5
  (``1, s, l, s·l, s², l², s²·l, s·l², s³, l³``, order :data:`LOOKANGLE_POWERS`);
* :func:`detector_polynomial`: ``1, y, ..., y^n`` of one coordinate (METHODS §4.3);
* :func:`piecewise_polynomial`: a polynomial per interval between breakpoints (pan-MS registration, METHODS §9);
* :func:`trigonometric`: ``sin/cos(2 pi f x)`` for given frequencies, optionally scaled by ``(1 + B s)`` (§9).

RPC00B's 20 ground monomials stay in :mod:`gdal_gf4cal.rpc` (their order is fixed by the format).
"""
from __future__ import annotations

from typing import Optional, Sequence, Tuple

import numpy as np

__all__ = ["LOOKANGLE_POWERS", "monomials", "monomial_derivatives", "term_name", "lookangle_cubic",
           "lookangle_cubic_derivatives", "detector_polynomial", "detector_terms", "piecewise_polynomial",
           "trigonometric"]

#: Exponents (i, j) of ``s^i l^j`` of the 10 look-angle terms (METHODS §5), in coefficient order.
LOOKANGLE_POWERS = ((0, 0), (1, 0), (0, 1), (1, 1), (2, 0), (0, 2), (2, 1), (1, 2), (3, 0), (0, 3))


def monomials(terms: Sequence[Tuple[int, int]], u, v) -> np.ndarray:
    """``u^i v^j`` for each ``(i, j)`` in ``terms``, shape ``(..., len(terms))`` (METHODS §4.1)."""
    return np.stack([u ** i * v ** j for (i, j) in terms], axis=-1)


def monomial_derivatives(terms: Sequence[Tuple[int, int]], u, v) -> Tuple[np.ndarray, np.ndarray]:
    """``d/du`` and ``d/dv`` of :func:`monomials`, shape ``(..., len(terms))`` each."""
    du = np.stack([(i * u ** (i - 1) * v ** j) if i else np.zeros_like(u) for (i, j) in terms], axis=-1)
    dv = np.stack([(j * u ** i * v ** (j - 1)) if j else np.zeros_like(u) for (i, j) in terms], axis=-1)
    return du, dv


def term_name(axis: str, term: Tuple[int, int]) -> str:
    """Parameter name of ``u^i v^j`` on ``axis``: ``sample_1``, ``line_u*v``, ``sample_u3``."""
    i, j = term
    parts = ([] if i == 0 else ["u" if i == 1 else f"u{i}"]) + ([] if j == 0 else ["v" if j == 1 else f"v{j}"])
    return f"{axis}_{'*'.join(parts) if parts else '1'}"


def lookangle_cubic(s, l) -> np.ndarray:
    """The 10 look-angle terms of ``(s, l)`` (METHODS §5), shape ``(..., 10)``, order :data:`LOOKANGLE_POWERS`."""
    s = np.asarray(s, dtype=float)
    l = np.asarray(l, dtype=float)
    ss, ll = s * s, l * l
    return np.stack([np.ones_like(s), s, l, s * l, ss, ll, ss * l, s * ll, ss * s, ll * l], axis=-1)


def lookangle_cubic_derivatives(s, l) -> Tuple[np.ndarray, np.ndarray]:
    """``d/ds`` and ``d/dl`` of :func:`lookangle_cubic`, shape ``(..., 10)`` each."""
    s = np.asarray(s, dtype=float)
    l = np.asarray(l, dtype=float)
    z, o = np.zeros_like(s), np.ones_like(s)
    ds = np.stack([z, o, z, l, 2 * s, z, 2 * s * l, l * l, 3 * s * s, z], axis=-1)
    dl = np.stack([z, z, o, s, z, 2 * l, s * s, 2 * s * l, z, 3 * l * l], axis=-1)
    return ds, dl


def detector_terms(order: int, axis: str = "sample") -> Tuple[Tuple[int, int], ...]:
    """Exponents of the detector polynomial ``k0 + k1 y + ... + kn y^n`` along ``axis`` (METHODS §4.3)."""
    return tuple((k, 0) if axis == "sample" else (0, k) for k in range(int(order) + 1))


def detector_polynomial(y, order: int) -> np.ndarray:
    """``1, y, ..., y^order`` of the normalised detector position ``y`` (METHODS §4.3), shape ``(..., order+1)``."""
    y = np.asarray(y, dtype=float)
    return np.stack([y ** k for k in range(int(order) + 1)], axis=-1)


def piecewise_polynomial(x, breakpoints: Sequence[float], order: int, *,
                         domain: Optional[Tuple[float, float]] = None) -> np.ndarray:
    """A separate polynomial ``sum_k c_jk (x - b_j)^k`` on each interval ``[b_j, b_{j+1})`` (METHODS §9).

    ``breakpoints`` are the interior breakpoints ``b_1 < ... < b_m`` (intervals ``(-inf, b_1)``, ...,
    ``[b_m, inf)``; the first interval is developed about ``b_1``). Shape ``(..., (m + 1) (order + 1))``, interval
    by interval; each column is zero outside its interval.

    With ``domain=(lo, hi)`` the outer intervals end at ``lo`` and ``hi`` and each interval is developed in its
    own normalised variable ``u_j = (x - mid_j) / half_j`` (in [-1, 1] inside it): ``sum_k c_jk u_j^k``, the
    well-conditioned form of the pan-MS sub-CCD quartics.
    """
    x = np.asarray(x, dtype=float)
    b = np.asarray(sorted(float(t) for t in breakpoints), dtype=float)
    j = np.searchsorted(b, x, side="right")                        # interval index 0..m
    if domain is not None:
        ends = np.concatenate([[float(domain[0])], b, [float(domain[1])]])
        mid, half = 0.5 * (ends[1:] + ends[:-1]), 0.5 * (ends[1:] - ends[:-1])
        d = (x - mid[j]) / half[j]
    else:
        origin = np.concatenate([b[:1] if b.size else np.zeros(1), b])[j] if b.size else np.zeros_like(x)
        d = x - origin
    cols = []
    for k in range(b.size + 1):
        inside = (j == k)
        cols.extend(np.where(inside, d ** p, 0.0) for p in range(int(order) + 1))
    return np.stack(cols, axis=-1)


def trigonometric(x, frequencies: Sequence[float], *, s=None, b: Optional[float] = None) -> np.ndarray:
    """``sin(2 pi f x), cos(2 pi f x)`` for each frequency ``f`` (cycles per unit of ``x``; METHODS §9).

    With ``s`` and ``b`` every column is scaled by ``(1 + b s)`` (an amplitude growing along the CCD line).
    Shape ``(..., 2 len(frequencies))``: sin, cos of the first frequency, then of the next.
    """
    x = np.asarray(x, dtype=float)
    cols = []
    for f in frequencies:
        ph = 2.0 * np.pi * float(f) * x
        cols.extend((np.sin(ph), np.cos(ph)))
    out = np.stack(cols, axis=-1)
    if s is not None and b is not None:
        out = out * (1.0 + float(b) * np.asarray(s, dtype=float))[..., None]
    return out
