"""Outlier rejection of matched offsets: seeded RANSAC + MAD against a low-order image-space model."""
from __future__ import annotations

import numpy as np
import pytest

from gdal_gf4cal.matching.filters import reject_outliers


def _field(n=300, seed=0, noise=0.05, frac_bad=0.25):
    rng = np.random.default_rng(seed)
    s = rng.uniform(0, 10240, n)
    l_ = rng.uniform(0, 10240, n)
    # A GF4-like systematic error: shift + rotation (~10 px at the edge) + scale.
    ds = 12.0 + 1e-3 * (l_ - 5120) + 2e-4 * (s - 5120)
    dl = -7.0 - 1e-3 * (s - 5120) + 3e-4 * (l_ - 5120)
    ds = ds + noise * rng.standard_normal(n)
    dl = dl + noise * rng.standard_normal(n)
    bad = rng.random(n) < frac_bad
    ds[bad] += rng.uniform(-40, 40, bad.sum())
    dl[bad] += rng.uniform(-40, 40, bad.sum())
    # Some gross errors are small (1-3 px): the MAD stage, not RANSAC's generous threshold, catches them.
    small = np.flatnonzero(bad)[:10]
    ds[small] = 12.0 + 1e-3 * (l_[small] - 5120) + 2e-4 * (s[small] - 5120) + 1.5
    return s, l_, ds, dl, bad


def test_affine_ransac_mad_finds_gross_errors():
    s, l_, ds, dl, bad = _field()
    r = reject_outliers(s, l_, ds, dl, model="affine", seed=0)
    assert r.model == "affine"
    np.testing.assert_array_equal(r.outlier, bad)
    assert max(r.sigma_px) < 0.08
    assert np.sqrt(np.mean(r.residual_sample[~bad] ** 2)) < 0.08


def test_seeded_and_reproducible():
    s, l_, ds, dl, bad = _field(seed=3, frac_bad=0.45)
    a = reject_outliers(s, l_, ds, dl, seed=11)
    b = reject_outliers(s, l_, ds, dl, seed=11)
    np.testing.assert_array_equal(a.outlier, b.outlier)
    np.testing.assert_array_equal(a.outlier, bad)   # 45% gross errors still found


def test_translation_model_leaves_rotation_as_spread():
    s, l_, ds, dl, bad = _field(seed=1, frac_bad=0.0)
    r = reject_outliers(s, l_, ds, dl, model="translation")
    # ~+-7 px of unmodelled rotation: larger than RANSAC's 3 px, so a translation flags many good points...
    assert r.outlier.sum() > 0.2 * s.size
    # ... whereas the affine model explains it.
    assert not reject_outliers(s, l_, ds, dl, model="affine").outlier.any()


def test_few_points_degrade_model_and_nan_is_outlier():
    s = np.array([100.0, 900.0, 500.0, 300.0, 700.0])
    l_ = np.array([100.0, 200.0, 800.0, 500.0, 600.0])
    ds = np.array([1.0, 1.02, 0.98, np.nan, 1.01])
    dl = np.full(5, -2.0)
    r = reject_outliers(s, l_, ds, dl, model="poly3")
    assert r.model == "translation"  # 4 finite points: not enough redundancy for more
    np.testing.assert_array_equal(r.outlier, [False, False, False, True, False])
    with pytest.raises(ValueError):
        reject_outliers(s, l_, ds, dl, model="spline")
    empty = reject_outliers([], [], [], [])
    assert empty.outlier.size == 0
