"""The sparse assembly of :func:`solve_with_points` (METHODS §8 block adjustment) agrees with the dense one."""
import numpy as np
import scipy.sparse as sp

from gdal_gf4cal.estimation import solve_with_points


def _problem(seed=0, n=60, k=6, q=2, p=9):
    rng = np.random.default_rng(seed)
    jp = rng.normal(size=(n, k, q))
    jg = rng.normal(size=(n, k, p)) * (rng.random((n, k, p)) < 0.4)
    r = rng.normal(size=(n, k))
    w = rng.uniform(0.5, 2.0, (n, k))
    w[:, -1] = 0.0                                   # padded (missing) observations
    return jp, jg, r, w


def test_sparse_matches_dense():
    jp, jg, r, w = _problem()
    n, k, p = jg.shape
    dense = solve_with_points(jp, r, w, jg)
    sparse = solve_with_points(jp, r, w, sp.csr_matrix(jg.reshape(n * k, p)))
    np.testing.assert_allclose(sparse.dx_global, dense.dx_global, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(sparse.dx_points, dense.dx_points, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(sparse.cov_global, dense.cov_global, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(sparse.cov_points, dense.cov_points, rtol=1e-8, atol=1e-12)


def test_extra_global_observations_are_added():
    """Global-only observations (GCPs) = a point-free system stacked under the point system."""
    jp, jg, r, w = _problem(1)
    n, k, p = jg.shape
    rng = np.random.default_rng(5)
    je, re_, we = rng.normal(size=(30, p)), rng.normal(size=30), rng.uniform(0.5, 2, 30)
    got = solve_with_points(jp, r, w, sp.csr_matrix(jg.reshape(n * k, p)), extra=(je, re_, we))
    # the same as dense least squares over [points | globals] with every observation
    a = np.zeros((n * k + 30, n * 2 + p))
    for i in range(n):
        a[i * k:(i + 1) * k, 2 * i:2 * i + 2] = jp[i]
    a[:n * k, 2 * n:] = jg.reshape(n * k, p)
    a[n * k:, 2 * n:] = je
    ww = np.concatenate([w.ravel(), we])
    y = np.concatenate([r.ravel(), re_])
    x = np.linalg.lstsq(a * np.sqrt(ww)[:, None], y * np.sqrt(ww), rcond=None)[0]
    np.testing.assert_allclose(got.dx_global, x[2 * n:], rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(got.dx_points.ravel(), x[:2 * n], rtol=1e-8, atol=1e-10)
