"""The one robust driver (estimation/driver.py): norms, the problem protocol, sigma0 and covariance from lsq.py."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from gdal_gf4cal.errors import GCPError
from gdal_gf4cal.estimation import (Huber, LinearProblem, RadialHuber, Snooping, Tukey, robust_fit, robust_lsq,
                                    sigma0_and_cov, weighted_lsq)


def _affine(seed=0, n=60, n_bad=8, sigma=0.1, blunder=25.0):
    """Per point a sample and a line observation of a 6-parameter affine; ``n_bad`` points off by ``blunder``."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(-1, 1, (n, 2))
    a = np.zeros((n, 2, 6))
    a[:, 0, :3] = np.c_[np.ones(n), t]
    a[:, 1, 3:] = np.c_[np.ones(n), t]
    x_true = np.array([3.0, -2.0, 0.5, 1.0, 0.2, -4.0])
    y = a @ x_true + rng.normal(0, sigma, (n, 2))
    bad = rng.choice(n, n_bad, replace=False)
    y[bad] += blunder * np.array([1.0, -0.6])
    return a, y, x_true, np.isin(np.arange(n), bad)


@pytest.mark.parametrize("norm, start, level", [(Snooping(4.0), "lts", {"start", "snooping"}),
                                                (RadialHuber(sigma=np.full(60, 0.1)), "lts", {"start", "reject"}),
                                                (Tukey(4.685), "lts", {"start", "reject"})])
def test_every_rejecting_norm_flags_exactly_the_blunders(norm, start, level):
    a, y, x_true, bad = _affine()
    est = robust_fit(LinearProblem(a, y, np.full((60, 2), 100.0)), norm=norm, start=start, max_iter=100)
    assert est.outlier.tolist() == bad.tolist()
    assert set(est.outlier_level[est.outlier]) <= level and set(est.outlier_level[~est.outlier]) == {""}
    assert np.all(est.point_weights[bad] == 0)
    assert np.max(np.abs(est.x - x_true)) < 0.06                      # sigma 0.1 px over 52 clean points


def test_huber_bounds_the_blunders_pull_and_beats_least_squares():
    a, y, x_true, bad = _affine(1, n_bad=4, blunder=5.0)
    ls = robust_fit(LinearProblem(a, y), norm=Huber(), start=None, max_iter=0)     # no reweighting: plain LS
    hub = robust_fit(LinearProblem(a, y), norm=Huber(), start=None, max_iter=100)
    err_ls, err_hub = np.max(np.abs(ls.x - x_true)), np.max(np.abs(hub.x - x_true))
    assert err_hub < 0.5 * err_ls and err_hub < 0.08
    assert not hub.outlier.any() and np.all(hub.point_weights[bad] < 0.2)


class _OwnProblem:
    """A problem implementing only the required protocol (no start design, no redundancy): the driver must work
    with it and give LinearProblem's numbers."""

    def __init__(self, a, y, w):
        self.lin = LinearProblem(a, y, w, solver="normal")
        self.n_points, self.k, self.n_params = a.shape[0], a.shape[1], a.shape[2]

    def fit(self, point_weights):
        return self.lin.fit(point_weights)


def test_a_problem_with_the_bare_protocol_plugs_in():
    a, y, _, bad = _affine(2)
    w = np.full((60, 2), 100.0)
    norm = RadialHuber(sigma=np.full(60, 0.1))
    own = robust_fit(_OwnProblem(a, y, w), norm=norm, start=None, max_iter=100, tol=1e-9)
    ref = robust_fit(LinearProblem(a, y, w, solver="normal"), norm=norm, start=None, max_iter=100, tol=1e-9)
    assert own.outlier.tolist() == bad.tolist() == ref.outlier.tolist()
    np.testing.assert_allclose(own.x, ref.x, rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="start_design|'lts'"):
        robust_fit(_OwnProblem(a, y, w), norm=norm, start="sometimes")


def test_too_few_points_left_names_the_cause():
    a, y, _, _ = _affine(3)                                           # 8 blunders in 60 points
    with pytest.raises(GCPError, match="only 52 points left after rejecting outliers; check"):
        robust_fit(LinearProblem(a, y), norm=RadialHuber(sigma=np.full(60, 0.1), min_points=55, too_few="; check"),
                   start=None, max_iter=100)


def test_snooping_is_robust_lsq_and_tests_each_axis_with_its_own_dof():
    a, y, _, bad = _affine(4, n=12, n_bad=2)
    est = robust_fit(LinearProblem(a, y), norm=Snooping(4.0))
    ref = robust_lsq(a, y)
    assert np.array_equal(est.x, ref.x) and est.outlier.tolist() == ref.outlier.tolist() == bad.tolist()
    sn = Snooping(4.0)
    est.axis_dof = (3, 300)
    p = stats.norm.sf(4.0)                                            # the t quantiles of P(|z| > 4)
    np.testing.assert_allclose(sn.critical(est, 2), [stats.t.isf(p, 3), stats.t.isf(p, 300)], rtol=1e-12)
    assert sn.critical(est, 2)[0] > 30 > 4.1 > sn.critical(est, 2)[1]


def test_sigma0_and_cov_is_weighted_lsqs():
    a, y, _, _ = _affine(5, n_bad=0)
    a2, y2, w = a.reshape(-1, 6), y.ravel(), np.full(120, 100.0)
    est = weighted_lsq(a2, y2, w)
    sigma0, cov = sigma0_and_cov((a2 * w[:, None]).T @ a2, float(np.sum(w * est.residuals ** 2)), est.dof)
    assert sigma0 == pytest.approx(est.sigma0, rel=1e-12)
    np.testing.assert_allclose(cov, est.cov, rtol=1e-9, atol=1e-18)
    assert np.isnan(sigma0_and_cov(np.eye(2), 1.0, 0)[0])
