"""The fast paths of the normal equations (issue 23) give the numbers of the plain ones: ``lsq.gram`` (A^T B in
row chunks on the calling thread) equals ``A.T @ B``; the LTS start (the reference for a faster one) finds the
planted blunders whether the observation axes share no parameter (a compensation) or share one, and keeps the
good points but the 0.1 % beyond its chi-square bound."""
from __future__ import annotations

import numpy as np
import pytest

from gdal_gf4cal.estimation import high_breakdown_start
from gdal_gf4cal.estimation.lsq import gram
from gdal_gf4cal.threads import BLAS_SERIAL_SIZE


@pytest.mark.parametrize("extra", [-1, 0, 1, 7 * BLAS_SERIAL_SIZE])
def test_gram_is_the_plain_product(extra):
    rng = np.random.default_rng(3)
    n = max(1, BLAS_SERIAL_SIZE // 36 + extra)
    a, b = rng.normal(size=(n, 6)), rng.normal(size=(n, 6))
    np.testing.assert_allclose(gram(a, b), a.T @ b, rtol=1e-11, atol=1e-11 * np.sqrt(n))


def _design(n, shared: bool, seed=2):
    """Two axes (sample, line), a poly2 of normalised (u, v) each; ``shared``: the line axis also depends on the
    first sample parameter."""
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    mono = np.column_stack([np.ones(n), u, v, u * v, u * u, v * v])
    a = np.zeros((n, 2, 12))
    a[:, 0, :6], a[:, 1, 6:] = mono, mono
    if shared:
        a[:, 1, 0] = 0.5 * u
    x = rng.normal(0, 5, 12)
    y = np.einsum("nkp,p->nk", a, x) + rng.normal(0, 0.5, (n, 2))
    bad = rng.random(n) < 0.05
    ang = rng.uniform(0, 2 * np.pi, n)
    mag = rng.uniform(20, 60, n)
    y[bad] += np.column_stack([mag * np.cos(ang), mag * np.sin(ang)])[bad]
    return a, y, bad


@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("n", [40, 3000])
def test_lts_start_flags_the_planted_blunders(n, shared):
    a, y, bad = _design(n, shared)
    inliers, scale, info = high_breakdown_start(a, y)
    assert not np.any(inliers & bad)                 # every blunder out of the start
    # good points beyond the start's 99.9 % chi-square bound: 0.1 % expected
    assert int(np.sum(~inliers & ~bad)) <= 1 + 0.003 * n
    assert 0.4 < scale < 0.6                       # the 0.5 px noise
    assert info["searched_points"] == min(n, 120)
