"""Row series and sine spectra of pan-MS residuals along the MS line (METHODS §9): plots, spectrum peaks and
the noise of the row means for the jitter test."""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

def _row_series(l, r, w, n_rows: Optional[int] = None):
    """Weighted means of residuals ``r`` per cell row (``l`` value; binned when the cells are not on rows)."""
    ok = np.isfinite(r) & (w > 0)
    l, r, w = l[ok], r[ok], w[ok]
    if l.size == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    ul, inv = np.unique(np.round(l, 3), return_inverse=True)
    if ul.size > max(8, l.size // 3):
        nb = n_rows or max(8, int(math.sqrt(l.size)))
        edges = np.linspace(l.min(), l.max() + 1e-9, nb + 1)
        inv = np.clip(np.searchsorted(edges, l, side="right") - 1, 0, nb - 1)
        ul = 0.5 * (edges[1:] + edges[:-1])
    sw = np.bincount(inv, w, ul.size)
    keep = sw > 0
    y = np.bincount(inv, w * r, ul.size)[keep] / sw[keep]
    lc = np.bincount(inv, w * l, ul.size)[keep] / sw[keep]
    return lc, y, sw[keep]


def _freq_grid(lines, oversample: int = 10):
    span = float(lines.max() - lines.min()) if lines.size else 0.0
    if lines.size < 8 or span <= 0:
        return np.zeros(0), span
    dl = np.median(np.diff(np.sort(lines)))
    f_max = 0.45 / dl                 # short of Nyquist, where a sine fit on the rows is ill-conditioned
    f_min = 1.0 / span
    n = int(max(16, oversample * (f_max - f_min) * span))
    return np.linspace(f_min, f_max, n), span


def _sine_power(lines, y, w, freqs):
    """Weighted LS fit of ``c + a sin + b cos`` at each frequency: RSS reduction and amplitude (vectorised)."""
    ph = 2.0 * np.pi * freqs[:, None] * lines[None, :]
    S, C = np.sin(ph), np.cos(ph)
    one = np.ones_like(S)
    cols = np.stack([one, S, C], axis=-1)                     # (nf, n, 3)
    N = np.einsum("fni,n,fnj->fij", cols, w, cols)
    b = np.einsum("fni,n,n->fi", cols, w, y)
    x = np.linalg.solve(N + 1e-12 * np.eye(3), b[..., None])[..., 0]
    ym = np.sum(w * y) / np.sum(w)
    rss0 = np.sum(w * (y - ym) ** 2)
    rss1 = np.sum(w * y * y) - np.einsum("fi,fi->f", x, b)
    return rss0 - rss1, np.hypot(x[:, 1], x[:, 2]), rss0


def row_means(lines, residual):
    """``(lines, means)``: the residual's mean per cell row along the MS line (plots, METHODS §9)."""
    r = np.asarray(residual, float)
    lc, y, _ = _row_series(np.asarray(lines, float), r, np.isfinite(r).astype(float))
    return lc, y


def residual_spectrum(lines, residual, *, line_time_s: Optional[float] = None):
    """``(frequencies, amplitudes)`` of the residual row means: least-squares sine amplitude (px) per frequency
    (cycles per MS line, or Hz with ``line_time_s``)."""
    r = np.asarray(residual, float)
    lc, y, w = _row_series(np.asarray(lines, float), r, np.isfinite(r).astype(float))
    freqs, _ = _freq_grid(lc)
    if freqs.size == 0:
        return freqs, freqs
    _, amp, _ = _sine_power(lc, y, w, freqs)
    return (freqs / line_time_s if line_time_s else freqs), amp


def spectrum_peaks(lines, residual, weights, *, n_peaks: int = 3, line_time_s: Optional[float] = None):
    """The ``n_peaks`` largest peaks of the residual spectrum along the line (row means; METHODS §9)."""
    lc, y, sw = _row_series(np.asarray(lines, float), np.asarray(residual, float), np.asarray(weights, float))
    freqs, _ = _freq_grid(lc)
    if freqs.size == 0:
        return []
    gain, amp, _ = _sine_power(lc, y, sw, freqs)
    is_peak = np.r_[False, (gain[1:-1] >= gain[:-2]) & (gain[1:-1] >= gain[2:]), False]
    idx = np.flatnonzero(is_peak)
    idx = idx[np.argsort(gain[idx])[::-1][:n_peaks]]
    return [{"frequency_cycles_per_line": float(freqs[i]),
             "frequency_hz": float(freqs[i] / line_time_s) if line_time_s else None,
             "amplitude_px": float(amp[i])} for i in idx]


def _within_row_variance(lines, r, w):
    """Reduced chi-square of the cells about their row means (weights ``w``), and its degrees of freedom; None
    when the cells are not on rows with several cells each."""
    ok = np.isfinite(r) & (w > 0)
    l, r, w = lines[ok], r[ok], w[ok]
    ul, inv = np.unique(np.round(l, 3), return_inverse=True)
    dof = l.size - ul.size
    if ul.size < 8 or dof < 2 * ul.size:
        return None, 0
    ym = np.bincount(inv, w * r, ul.size) / np.bincount(inv, w, ul.size)
    return float(np.sum(w * (r - ym[inv]) ** 2) / dof), dof
