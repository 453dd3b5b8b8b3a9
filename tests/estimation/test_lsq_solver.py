"""weighted_lsq's two solvers (issue 23): the normal-equation one used in robust iterations gives the SVD's numbers
to rounding and refuses the same layouts."""
from __future__ import annotations

import numpy as np
import pytest

from gdal_gf4cal.errors import DegenerateGeometryError
from gdal_gf4cal.estimation import weighted_lsq


def _problem(n=500, seed=4):
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    a = np.column_stack([np.ones(n), u, v, u * v, u * u, v * v]) * [1.0, 300.0, 0.02, 5.0, 1e3, 1e-3]
    x_true = np.array([2.0, 0.01, -40.0, 0.3, 1e-4, 700.0])
    w = rng.uniform(0.5, 2.0, n)
    w[rng.random(n) < 0.1] = 0.0                                     # points out of the fit
    return a, a @ x_true + rng.normal(0, 0.5, n) / np.sqrt(np.maximum(w, 0.5)), w, x_true


def test_normal_solver_gives_the_svd_numbers():
    a, y, w, x_true = _problem()
    svd = weighted_lsq(a, y, w, prior=np.ones(y.size), apriori=True)
    nrm = weighted_lsq(a, y, w, prior=np.ones(y.size), apriori=True, solver="normal")
    np.testing.assert_allclose(nrm.x, svd.x, rtol=1e-9)
    np.testing.assert_allclose(nrm.cov, svd.cov, rtol=1e-8, atol=1e-14 * np.abs(svd.cov).max())
    np.testing.assert_allclose(nrm.normalised, svd.normalised, rtol=1e-8, atol=1e-10)
    assert nrm.condition_number == pytest.approx(svd.condition_number, rel=1e-6)
    assert nrm.sigma0 == pytest.approx(svd.sigma0, rel=1e-10) and nrm.dof == svd.dof
    assert np.max(np.abs(svd.x - x_true) / np.sqrt(np.diag(svd.cov))) < 5      # and the truth is found


@pytest.mark.parametrize("solver", ["svd", "normal"])
def test_both_solvers_refuse_a_collinear_layout(solver):
    a, y, w, _ = _problem()
    a[:, 2] = 3.0 * a[:, 1]                                          # two columns proportional
    with pytest.raises(DegenerateGeometryError, match="condition number"):
        weighted_lsq(a, y, w, solver=solver)


def test_unknown_solver_is_refused():
    a, y, w, _ = _problem(50)
    with pytest.raises(ValueError, match="solver must be 'svd' or 'normal'"):
        weighted_lsq(a, y, w, solver="qr")
