"""The one basis module (METHODS §4.1, §4.3, §5, §9)."""
from __future__ import annotations

import numpy as np
import pytest

from gdal_gf4cal.basis import (LOOKANGLE_POWERS, detector_polynomial, lookangle_cubic, lookangle_cubic_derivatives,
                               monomial_derivatives, monomials, piecewise_polynomial, term_name, trigonometric)


def test_lookangle_cubic_is_the_monomials_of_its_powers_and_derivatives_match_differences():
    rng = np.random.default_rng(0)
    s, l = rng.uniform(-1, 1, (2, 7))
    np.testing.assert_allclose(lookangle_cubic(s, l), monomials(LOOKANGLE_POWERS, s, l), rtol=1e-15)
    ds, dl = lookangle_cubic_derivatives(s, l)
    mu, mv = monomial_derivatives(LOOKANGLE_POWERS, s, l)
    np.testing.assert_allclose(ds, mu, atol=1e-15)
    np.testing.assert_allclose(dl, mv, atol=1e-15)
    e = 1e-6
    np.testing.assert_allclose(ds, (lookangle_cubic(s + e, l) - lookangle_cubic(s - e, l)) / (2 * e), atol=1e-8)
    assert lookangle_cubic(2.0, 3.0).tolist() == [1, 2, 3, 6, 4, 9, 12, 18, 8, 27]


def test_detector_polynomial_and_names():
    assert detector_polynomial(np.array([2.0]), 3).tolist() == [[1, 2, 4, 8]]
    assert term_name("sample", (0, 0)) == "sample_1" and term_name("line", (2, 1)) == "line_u2*v"


def test_piecewise_polynomial_fits_a_broken_line_exactly():
    x = np.linspace(0, 10, 101)
    y = np.where(x < 4, 1.0 + 0.5 * x, 3.0 - 0.2 * (x - 4)) + np.where(x >= 7, 0.3, 0.0)
    a = piecewise_polynomial(x, [4.0, 7.0], 1)
    assert a.shape == (101, 6)
    assert np.all(a[x < 4][:, 2:] == 0) and np.all(a[x >= 7][:, :4] == 0)
    c = np.linalg.lstsq(a, y, rcond=None)[0]
    np.testing.assert_allclose(a @ c, y, atol=1e-12)
    assert c[2] == pytest.approx(3.0) and c[3] == pytest.approx(-0.2)


def test_trigonometric_recovers_amplitude_and_phase_with_scaling():
    x = np.linspace(0, 1, 200)
    s = np.linspace(-1, 1, 200)
    y = (0.7 * np.sin(2 * np.pi * 3 * x) - 0.2 * np.cos(2 * np.pi * 3 * x)) * (1 + 0.1 * s)
    a = trigonometric(x, [3.0], s=s, b=0.1)
    c = np.linalg.lstsq(a, y, rcond=None)[0]
    np.testing.assert_allclose(c, [0.7, -0.2], atol=1e-12)
