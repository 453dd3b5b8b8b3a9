"""The fast paths of the normal equations (issue 23) give the numbers of the plain ones: ``lsq.gram`` (A^T B in
row chunks on the calling thread) equals ``A.T @ B``; the LTS start (the reference for a faster one) finds the
planted blunders whether the observation axes share no parameter (a compensation) or share one, and keeps the
good points but the 0.1 % beyond its chi-square bound; its ``normal`` evaluation and a shared design (one axis' rows for all axes) keep its start;
``weighted_lsq_many`` is each vector's own ``weighted_lsq``; ``threads.rows_times`` is the plain product."""
from __future__ import annotations

import numpy as np
import pytest

from gdal_gf4cal.estimation import Block, high_breakdown_start, subset_count, weighted_lsq
from gdal_gf4cal.estimation.robust import SEARCH_MISS
from gdal_gf4cal.estimation.lsq import gram, weighted_lsq_many
from gdal_gf4cal.threads import rows_times
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


@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("n", [40, 3000])
def test_lts_start_normal_evaluation_keeps_the_start(n, shared):
    """``normal=True`` (compensation's: one A^T W A per point set) keeps the default's start set and scale."""
    a, y, bad = _design(n, shared, seed=5)
    w = np.random.default_rng(1).uniform(0.5, 2.0, y.shape)
    inl, scale, info = high_breakdown_start(a, y, w)
    inl_n, scale_n, info_n = high_breakdown_start(a, y, w, normal=True)
    np.testing.assert_array_equal(inl_n, inl)
    assert not np.any(inl_n & bad)
    assert scale_n == pytest.approx(scale, rel=1e-12)
    assert info_n.pop("lts_scale") == pytest.approx(info.pop("lts_scale"), rel=1e-12)
    assert info_n == info


@pytest.mark.parametrize("normal", [False, True])
@pytest.mark.parametrize("n", [40, 3000])
def test_lts_start_shared_design_is_its_block_diagonal_one(n, normal):
    """A shared design ``(n, q)`` with ``obs`` (n, 2) (compensation's start when both axes have the same terms) keeps
    the start set, scale and info of its block-diagonal ``(n, 2, 2 q)`` design, at the cost of one axis."""
    a, y, bad = _design(n, False, seed=7)
    w = np.random.default_rng(2).uniform(0.5, 2.0, n)
    inl, scale, info = high_breakdown_start(a, y, np.repeat(w[:, None], 2, axis=1), normal=normal)
    inl_s, scale_s, info_s = high_breakdown_start(a[:, 0, :6], y, w, normal=normal)
    np.testing.assert_array_equal(inl_s, inl)
    assert not np.any(inl_s & bad)
    assert scale_s == pytest.approx(scale, rel=1e-12)
    assert info_s.pop("lts_scale") == pytest.approx(info.pop("lts_scale"), rel=1e-12)
    assert info_s == info


def test_subset_count_keeps_the_default_searchs_miss_probability():
    """Compensation's subset count (issue 23): the chance of no clean subset at 40 % blunders is at most that of the
    default 300 six-point subsets, and one subset fewer would exceed it."""
    assert [subset_count(m) for m in range(1, 8)] == [16, 33, 59, 104, 178, 300, 300]
    for m in range(1, 6):
        n = subset_count(m)
        assert (1 - 0.6 ** m) ** n <= SEARCH_MISS * (1 + 1e-9) < (1 - 0.6 ** m) ** (n - 1)


@pytest.mark.parametrize("n", [40, 3000])
def test_lts_start_with_the_counted_subsets_flags_the_planted_blunders(n):
    """59 subsets of 3 points (a shared affine design, 20 % blunders of 5-60 px) keep the start of 300."""
    rng = np.random.default_rng(11)
    aff = np.column_stack([np.ones(n), rng.uniform(-1, 1, (n, 2))])
    y = aff @ rng.normal(0, 5, (3, 2)) + rng.normal(0, 0.5, (n, 2))
    bad = rng.random(n) < 0.2
    y[bad] += rng.uniform(5, 60, (n, 2))[bad] * rng.choice([-1, 1], (n, 2))[bad]
    inl, scale, info = high_breakdown_start(aff, y, normal=True, n_subsets=subset_count(3))
    inl_300, scale_300, _ = high_breakdown_start(aff, y, normal=True)
    assert info["subsets"] == 59
    np.testing.assert_array_equal(inl, inl_300)
    assert not np.any(inl & bad) and scale == pytest.approx(scale_300, rel=1e-9)


@pytest.mark.parametrize("solver", ["svd", "normal"])
def test_weighted_lsq_many_is_each_vectors_own_fit(solver):
    """One decomposition for several observation vectors gives each vector's own weighted_lsq bit for bit (both
    solvers, a frozen block, points left out)."""
    rng = np.random.default_rng(4)
    n = 3000                                                     # above the serial row blocks of rows_times
    a = np.column_stack([np.ones(n), rng.uniform(-1, 1, (n, 3))])
    ys = [a @ rng.normal(0, 3, 4) + rng.normal(0, 0.5, n) for _ in range(2)]
    w = np.where(rng.random(n) < 0.1, 0.0, rng.uniform(0.5, 2.0, n))
    kw = dict(blocks=[Block("b", ("c",)), Block("s", ("u", "v", "uv"))], frozen=["b"], values=[0.3, 0, 0, 0],
              prior=np.ones(n), apriori=True, solver=solver)
    for one, many in zip([weighted_lsq(a, y, w, **kw) for y in ys], weighted_lsq_many(a, ys, w, **kw)):
        for name in ("x", "cov", "residuals", "normalised", "redundancy", "weights"):
            np.testing.assert_array_equal(getattr(many, name), getattr(one, name))
        assert (many.sigma0, many.dof, many.condition_number) == (one.sigma0, one.dof, one.condition_number)


@pytest.mark.parametrize("q", [None, 1, 6])
def test_rows_times_is_the_product(q):
    rng = np.random.default_rng(6)
    a = rng.normal(size=(50_000, 6))
    b = rng.normal(size=6) if q is None else rng.normal(size=(6, q))
    np.testing.assert_allclose(rows_times(a, b), a @ b, rtol=1e-13, atol=1e-13)
