"""RANSAC's squared residuals of every candidate model (matching.filters._squared_residuals, issue 23): the bits of
the einsum they replace (the k products added in order, then the two squares), for the translation-free models
the matcher uses (affine, poly2, poly3: k = 3, 6, 10), at the sizes it sees (a tile's windows to a pan-MS band's
20,000), and the same outliers from reject_outliers on a field with blunders."""
from __future__ import annotations

import numpy as np
import pytest

from gdal_gf4cal.matching import filters, reject_outliers


def _einsum_residuals(A, d, coef):
    return ((d[None] - np.einsum("nk,mkc->mnc", A, coef)) ** 2).sum(axis=2)


@pytest.mark.parametrize("k", [3, 6, 10])
@pytest.mark.parametrize("n", [7, 64, 1000, 4099])
def test_the_bits_of_the_einsum(k, n):
    rng = np.random.default_rng(k * 10_000 + n)
    A = rng.normal(size=(n, k)) * rng.uniform(0.1, 10.0, k)
    d = rng.normal(size=(n, 2)) * 3.0
    coef = rng.normal(size=(64, k, 2)) * 10.0 ** rng.uniform(-3, 2, (64, 1, 1))
    got = filters._squared_residuals(np.ascontiguousarray(A.T), np.ascontiguousarray(d.T), coef)
    assert got.shape == (64, n)
    assert np.array_equal(got, _einsum_residuals(A, d, coef))


def test_reject_outliers_finds_the_blunders():
    rng = np.random.default_rng(5)
    s, l = rng.uniform(0, 2000, 3000), rng.uniform(0, 2000, 3000)
    ds = 0.4 + 1e-4 * s - 2e-4 * l + rng.normal(0, 0.05, s.size)
    dl = -0.3 + 3e-4 * s + rng.normal(0, 0.05, s.size)
    bad = rng.choice(s.size, 60, replace=False)
    ds[bad] += rng.choice([-1, 1], bad.size) * rng.uniform(5, 20, bad.size)
    r = reject_outliers(s, l, ds, dl, model="affine", threshold_px=3.0, mad_k=np.inf, seed=0)
    assert set(np.flatnonzero(r.outlier)) == set(bad)
    assert np.allclose(r.coefficients[0], [0.4 + 1e-4 * 1000 - 2e-4 * 1000, -0.3 + 3e-4 * 1000], atol=0.01)
