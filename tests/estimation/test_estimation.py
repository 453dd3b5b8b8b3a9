"""The estimation core (METHODS §4, §7): weighted LS with frozen blocks, Schur elimination, robust estimator."""
from __future__ import annotations

import numpy as np
import pytest

from gdal_gf4cal.errors import DegenerateGeometryError
from gdal_gf4cal.estimation import (Block, critical_value, high_breakdown_start, min_subset_points, readmissible,
                                    robust_lsq, solve_with_points, weighted_lsq)


def _line_fit(seed=0, n=50):
    rng = np.random.default_rng(seed)
    t = rng.uniform(-1, 1, n)
    a = np.stack([np.ones(n), t, t * t], axis=1)
    x_true = np.array([2.0, -3.0, 0.5])
    return a, a @ x_true + rng.normal(0, 0.1, n), x_true


def test_weighted_lsq_matches_numpy_and_redundancy_sums_to_dof():
    a, y, x_true = _line_fit()
    w = np.full(len(y), 100.0)                        # sigma 0.1
    est = weighted_lsq(a, y, w, blocks=[Block("offset", ("c",)), Block("shape", ("b", "q"))])
    ref = np.linalg.lstsq(a, y, rcond=None)[0]
    np.testing.assert_allclose(est.x, ref, rtol=1e-12, atol=1e-12)
    assert est.dof == 47
    assert est.redundancy.sum() == pytest.approx(47.0, abs=1e-9)
    assert 0.8 < est.sigma0 < 1.2                     # a-priori sigma was right
    assert np.all(np.abs(est.x - x_true) < 4 * est.std)
    assert est.names == ["c", "b", "q"] and est.block("shape").shape == (2,)


def test_frozen_block_is_held_and_has_no_covariance():
    a, y, _ = _line_fit(1)
    est = weighted_lsq(a, y, blocks=[Block("offset", ("c",)), Block("shape", ("b", "q"))], frozen=["offset"],
                       values=[2.0, 0.0, 0.0])
    assert est.x[0] == 2.0 and np.all(est.cov[0] == 0) and est.dof == 48
    ref = np.linalg.lstsq(a[:, 1:], y - 2.0, rcond=None)[0]
    np.testing.assert_allclose(est.x[1:], ref, rtol=1e-12)


def test_degenerate_layout_names_the_condition_number():
    t = np.full(10, 0.3)                              # every point at the same place: slope undetermined
    a = np.stack([np.ones(10), t], axis=1)
    with pytest.raises(DegenerateGeometryError, match="condition number"):
        weighted_lsq(a, np.ones(10))


def test_schur_elimination_equals_the_full_solve():
    rng = np.random.default_rng(3)
    n, r, q, p = 30, 4, 3, 5
    jp, jg = rng.normal(size=(n, r, q)), rng.normal(size=(n, r, p))
    res, w = rng.normal(size=(n, r)), rng.uniform(0.5, 2.0, (n, r))
    sol = solve_with_points(jp, res, w, jg)
    full = np.zeros((n * r, n * q + p))
    for i in range(n):
        full[i * r:(i + 1) * r, i * q:(i + 1) * q] = jp[i]
    full[:, n * q:] = jg.reshape(n * r, p)
    nmat = full.T @ (w.ravel()[:, None] * full)
    dx = np.linalg.solve(nmat, full.T @ (w.ravel() * res.ravel()))
    cov = np.linalg.inv(nmat)
    np.testing.assert_allclose(sol.dx_global, dx[n * q:], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(sol.dx_points.ravel(), dx[:n * q], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(sol.cov_global, cov[n * q:, n * q:], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(sol.cov_points[7], cov[21:24, 21:24], rtol=1e-9, atol=1e-12)
    # the sparse path gives the same answer
    import gdal_gf4cal.estimation.schur as schur
    old, schur.SPARSE_ABOVE = schur.SPARSE_ABOVE, 0
    try:
        sp = solve_with_points(jp, res, w, jg)
    finally:
        schur.SPARSE_ABOVE = old
    np.testing.assert_allclose(sp.dx_global, dx[n * q:], rtol=1e-9, atol=1e-12)


def test_critical_value_is_the_t_quantile_of_the_normal_probability():
    assert critical_value(4.0, 10 ** 6) == pytest.approx(4.0, abs=1e-3)
    assert critical_value(4.0, 8) == pytest.approx(7.595, abs=1e-3)   # t_8 quantile of P(|z| > 4)
    assert critical_value(4.0, 0) == np.inf


def _points(seed, n, frac, coherent=False):
    """Per-point 2-D affine observations (k = 2, p = 6) with a share of blunders."""
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    base = np.stack([np.ones(n), u, v], axis=1)
    a = np.zeros((n, 2, 6))
    a[:, 0, :3], a[:, 1, 3:] = base, base
    x = np.array([5.0, 2.0, -1.0, -3.0, 0.5, 4.0])
    y = a @ x + rng.normal(0, 0.5, (n, 2))
    bad = rng.choice(n, int(round(frac * n)), replace=False)
    if coherent:
        y[bad] += [9.0, -8.0]
    else:
        ang = rng.uniform(0, 2 * np.pi, bad.size)
        y[bad] += rng.uniform(20, 100, bad.size)[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
    return a, y, x, bad


@pytest.mark.parametrize("n, frac, coherent", [(7, 2 / 7, False), (40, 0.3, False), (200, 0.4, True),
                                               (5000, 0.3, False)])
def test_robust_lsq_flags_every_blunder(n, frac, coherent):
    a, y, x_true, bad = _points(n, n, frac, coherent)
    est = robust_lsq(a, y, min_points=3)
    assert set(bad) <= set(np.flatnonzero(est.outlier))
    assert est.outlier.sum() <= bad.size + max(1, n // 100)
    assert np.all(np.abs(est.x - x_true) < 5 * est.std + 1e-9)
    assert set(est.outlier_level[est.outlier]) <= {"start", "snooping"}
    inl, scale, info = high_breakdown_start(a, y, min_points=3)
    assert info["exhaustive"] == (n <= 7) and 0.3 < scale < 0.8


def test_robust_lsq_flags_check_points_too():
    a, y, _, bad = _points(11, 30, 0.0)
    y[3] += [30.0, 0.0]
    cand = np.ones(30, bool)
    cand[:5] = False                                   # points 0-4 are check points
    est = robust_lsq(a, y, candidates=cand, min_points=3)
    assert np.flatnonzero(est.outlier).tolist() == [3] and est.outlier_level[3] == "snooping"
    assert np.all(est.weights.reshape(30, 2)[:5] == 0)


def test_minimal_subsets_per_independently_estimated_axis():
    """A block-diagonal affine (3 + 3 parameters, one axis each) needs 3 points, a detector polynomial with 4 sample
    and 1 line parameters 4, shared parameters ceil(p / k), one axis p."""
    a, _, _, _ = _points(1, 10, 0.0)
    assert min_subset_points(a) == 3
    det = np.zeros((10, 2, 5))
    det[:, 0, :4], det[:, 1, 4] = np.random.default_rng(0).normal(size=(10, 4)), 1.0
    assert min_subset_points(det) == 4
    assert min_subset_points(np.ones((10, 2, 6))) == 3
    assert min_subset_points(np.ones((10, 1, 4))) == 4


def _clustered_two_in_seven(seed):
    """7 affine points in a third of the frame, 2 px noise, blunders of 60 and 54 px on points 1 and 4 (the real
    SPOT-6 set of issue 19, in the estimation core's terms)."""
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(0, 0.58, 7), rng.uniform(0, 0.58, 7)
    base = np.stack([np.ones(7), u, v], axis=1)
    a = np.zeros((7, 2, 6))
    a[:, 0, :3], a[:, 1, 3:] = base, base
    y = a @ np.array([2.5, 1.5, -0.8, -2.0, 0.7, 1.0]) + rng.normal(0, 2.0, (7, 2))
    for i, mag in ((1, 60.0), (4, 54.0)):
        ang = rng.uniform(0, 2 * np.pi)
        y[i] += mag * np.array([np.cos(ang), np.sin(ang)])
    return a, y


@pytest.mark.parametrize("seed", [0, 2, 3, 4, 7])
def test_two_clustered_blunders_in_seven_stay_out(seed):
    """The high-breakdown start finds both blunders; with 4 redundant observations the Student-t snooping
    threshold is 17.4, and without the re-admission test the farther blunder came back (its prediction variance
    inflated by extrapolation), inflated sigma and pulled the other in (seeds 0, 2, 4, 7 here). Over seeds 0-19
    three sets stay undecided (1, 14: a blunder within the re-admission bound of the 5-point fit; 12: the start
    keeps a blunder): 5 points and 4 redundant observations cannot always tell."""
    a, y = _clustered_two_in_seven(seed)
    est = robust_lsq(a, y)
    assert np.flatnonzero(est.outlier).tolist() == [1, 4]


def test_readmission_is_strict_with_little_redundancy_and_the_threshold_with_much():
    w = np.array([[4.0, 10.6], [2.5, 4.5], [0.7, 4.0]])
    # 4 degrees of freedom: F(2, 4) 99 %, sum(w^2) / 2 <= 18 (the Student-t threshold is |w| 17.4 per axis)
    assert readmissible(w, 4).tolist() == [False, True, True]
    # 400: the snooping threshold 4 with known sigma (chi-square, sum(w^2) / 2 <= 9.0)
    assert readmissible(w, 400).tolist() == [False, False, True]
    assert readmissible(w, 0).all()
    # a plain scale biased low by trimming is floored by the start's LTS scale
    assert readmissible(w[:1], 4, sigma=1.0, start_sigma=2.0).tolist() == [True]
