"""fit_rpc's chunked normal equations (issue 23): the same as the dense design's ``A^T A`` and ``A^T b``."""
from __future__ import annotations

import numpy as np

from gdal_gf4cal import rpc_fit
from gdal_gf4cal.rpc import monomials


def test_chunked_normal_equations_equal_the_dense_ones():
    rng = np.random.default_rng(5)
    n = 3 * rpc_fit._CHUNK + 123                                     # several chunks and a partial one
    Mt = monomials(*rng.uniform(-1, 1, (3, n)))
    r = rng.uniform(-1, 1, n)
    w = 1.0 / (1.0 + 0.05 * rng.uniform(-1, 1, n))
    design = rpc_fit._AxisDesign(Mt, w, -r * w)
    A = np.hstack([(Mt * w).T, (Mt[1:] * (-r * w)).T])               # the (n, 39) design, formed here only
    G, g = design.normal(r * w)
    np.testing.assert_allclose(G, A.T @ A, rtol=1e-12, atol=1e-12 * np.abs(G).max())
    np.testing.assert_allclose(g, A.T @ (r * w), rtol=1e-12, atol=1e-12 * np.abs(g).max())
    d = rng.normal(size=39)
    np.testing.assert_allclose(design.dot(d), A @ d, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(design.tdot(r), A.T @ r, rtol=1e-12, atol=1e-9)
    np.testing.assert_array_equal(design.dense(), A)
