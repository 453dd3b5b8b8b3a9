"""Blunders among the pan-MS window matches, found without a model of the field (METHODS §9)."""
from __future__ import annotations

import numpy as np

from ..matching import reject_outliers
from ..stats import grouped_trimmed_mean

#: Local consistency screen of the window matches (screen_matches): windows of one column in blocks of this many
#: rows, a window off its block's median by more than SCREEN_K robust standard deviations (floored) is a blunder.
SCREEN_ROWS = 16
SCREEN_K = 4.0
SCREEN_FLOOR_PX = 0.05
#: ... and a window farther than this from the scene's affine consensus (RANSAC) is a gross mismatch.
SCREEN_GROSS_PX = 3.0


def screen_matches(sample, line, d_sample, d_line, *, spacing_px: float, seed: int = 0) -> np.ndarray:
    """Blunders among the window matches (bool per window), found without a model of the field (METHODS §9): a
    window farther than :data:`SCREEN_GROSS_PX` from the affine consensus of all (RANSAC, no MAD stage), or off
    the median of the windows of its own column and nearby rows (blocks of :data:`SCREEN_ROWS` rows) by more than
    :data:`SCREEN_K` robust standard deviations (1.4826 MAD, at least :data:`SCREEN_FLOOR_PX`) on either axis.
    A sub-CCD jump runs along whole columns, so a screen within a column never flags one side of it (a global
    low-order model with a MAD cut rejects every column of the smaller side: the jump is then not found). NaN
    offsets are blunders."""
    s, l = np.asarray(sample, float), np.asarray(line, float)
    d = np.stack([np.asarray(d_sample, float), np.asarray(d_line, float)], axis=1)
    ok = np.isfinite(d).all(axis=1) & np.isfinite(s) & np.isfinite(l)
    out = ~ok
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return out
    if idx.size >= 8:
        gross = reject_outliers(s[idx], l[idx], d[idx, 0], d[idx, 1], model="affine", threshold_px=SCREEN_GROSS_PX,
                                mad_k=np.inf, seed=seed).outlier
        out[idx[gross]] = True
        idx = idx[~gross]
    _, col = np.unique(np.round(s[idx], 3), return_inverse=True)
    blk = np.floor((l[idx] - l[idx].min()) / (SCREEN_ROWS * float(spacing_px))).astype(np.int64)
    _, g = np.unique(col.astype(np.int64) * (int(blk.max()) + 1) + blk, return_inverse=True)
    n_g = int(g.max()) + 1
    dev = np.abs(d[idx] - grouped_trimmed_mean(g, d[idx], n_g).median[g])
    sig = np.maximum(1.4826 * grouped_trimmed_mean(g, dev, n_g).median, SCREEN_FLOOR_PX)
    out[idx[np.any(dev > SCREEN_K * sig[g], axis=1)]] = True
    return out
