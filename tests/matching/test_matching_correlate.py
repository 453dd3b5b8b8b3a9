"""Batched phase correlation: sub-pixel accuracy on known shifts of textures, quality measures, texture test."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from gdal_gf4cal.matching.correlate import (block_reduce, correlate_spectra, null_result, phase_correlate, spectra, taper,
                                           texture_strength)


class Texture:
    """A continuous, band-limited random texture: exact values at any sub-pixel position, pixel-integrated.

    Sum of 400 plane waves with a 1/f amplitude spectrum (like natural images); each wave is multiplied by the
    transfer function of a unit box (sinc), so a sample is the exact mean over a pixel footprint.
    """

    def __init__(self, seed: int = 0, n: int = 400, fmax: float = 0.45):
        rng = np.random.default_rng(seed)
        f = rng.uniform(0.005, fmax, n)
        th = rng.uniform(0, 2 * np.pi, n)
        self.u, self.v = f * np.cos(th), f * np.sin(th)
        self.a = (1.0 / f) * np.sinc(self.u) * np.sinc(self.v) * np.exp(1j * rng.uniform(0, 2 * np.pi, n))

    def window(self, x0: float, y0: float, w: int) -> np.ndarray:
        x = np.arange(w) + x0
        y = np.arange(w) + y0
        ex = np.exp(2j * np.pi * self.u[:, None] * x[None, :])
        ey = np.exp(2j * np.pi * self.v[:, None] * y[None, :])
        return np.real(np.einsum("k,ky,kx->yx", self.a, ey, ex))


def _pairs(n, w, max_shift, noise, seed=1):
    tex = Texture(seed)
    rng = np.random.default_rng(seed + 100)
    dx = rng.uniform(-max_shift, max_shift, n)
    dy = rng.uniform(-max_shift, max_shift, n)
    fixed, moving = [], []
    for i in range(n):
        x0, y0 = rng.uniform(0, 2000, 2)
        f = tex.window(x0, y0, w)
        m = tex.window(x0 - dx[i], y0 - dy[i], w)  # moving(x) = fixed(x - d)
        s = f.std()
        fixed.append(f + noise * s * rng.standard_normal(f.shape))
        moving.append(3.0 * m + 100 + noise * 3.0 * s * rng.standard_normal(f.shape))  # other gain/offset
    return np.array(fixed), np.array(moving), dx, dy


@pytest.mark.parametrize("max_shift,tol", [(0.5, 0.01), (3.0, 0.03)])
def test_subpixel_accuracy_noise_free(max_shift, tol):
    f, m, dx, dy = _pairs(60, 64, max_shift, noise=0.0)
    r = phase_correlate(f, m)
    err = np.hypot(r.dx - dx, r.dy - dy)
    assert np.sqrt(np.mean(err ** 2)) < tol
    assert np.all(r.peak > 0.9) and np.all(r.ncc > 0.95) and np.all(r.peak_ratio > 10)


def test_accuracy_with_noise_and_precision_estimate():
    f, m, dx, dy = _pairs(120, 64, 0.5, noise=0.1, seed=3)
    r = phase_correlate(f, m)
    ex, ey = r.dx - dx, r.dy - dy
    rms_axis = np.sqrt(np.mean(np.r_[ex, ey] ** 2))
    assert rms_axis < 0.06
    # The precision estimate is a calibrated 1-sigma: within a factor 1.6 of the actual per-axis RMS.
    pred = np.sqrt(np.mean(r.precision_px ** 2))
    assert rms_axis / 1.6 < pred < rms_axis * 1.6, (rms_axis, pred)
    # Noisier windows report worse precision and lower peaks.
    f2, m2, _, _ = _pairs(40, 64, 0.5, noise=0.4, seed=3)
    r2 = phase_correlate(f2, m2)
    assert np.median(r2.precision_px) > 2 * np.median(r.precision_px)
    assert np.median(r2.peak) < np.median(r.peak)


def test_integer_shifts_and_sign_convention():
    rng = np.random.default_rng(5)
    big = rng.standard_normal((200, 200))
    fixed = big[50:114, 60:124]
    moving = big[50 - 7:114 - 7, 60 + 11:124 + 11]  # content moved by (-11, +7)
    r = phase_correlate(fixed, moving)
    # White noise, 11 px of 64 not overlapping: the taper keeps the bias small.
    assert r.dx == pytest.approx(-11, abs=0.03) and r.dy == pytest.approx(7, abs=0.03)
    assert r.dx.shape == ()


def test_unrelated_windows_have_low_quality():
    rng = np.random.default_rng(2)
    f = rng.standard_normal((20, 64, 64))
    m = rng.standard_normal((20, 64, 64))
    r = phase_correlate(f, m)
    assert np.all(r.peak < 0.25) and np.all(r.peak_ratio < 2.0) and np.all(np.abs(r.ncc) < 0.3)
    # collect_gcps' default checks (peak >= 0.2, ratio >= 2, ncc >= 0.3) accept none of them.
    assert not np.any((r.peak >= 0.2) & (r.peak_ratio >= 2.0) & (r.ncc >= 0.3))


def test_stack_shapes_and_bad_input():
    f, m, dx, dy = _pairs(6, 32, 0.4, noise=0.0)
    r = phase_correlate(f.reshape(2, 3, 32, 32), m.reshape(2, 3, 32, 32), window="tukey")
    assert r.dx.shape == (2, 3)
    np.testing.assert_allclose(r.dx.ravel(), dx, atol=0.05)
    with pytest.raises(ValueError):
        phase_correlate(f, m[:, :16])
    with pytest.raises(ValueError):
        taper((8, 8), "gauss")


def test_texture_strength_separates_texture_from_flat_noise():
    tex = Texture(4)
    rng = np.random.default_rng(0)
    textured = np.array([tex.window(x, 0, 64) for x in (0, 300, 900)])
    textured += 0.05 * textured.std() * rng.standard_normal(textured.shape)
    flat = 500 + rng.standard_normal((3, 64, 64))            # water: noise only
    edge = np.tile(np.where(np.arange(64) < 32, 0.0, 100.0), (64, 1))[None] + rng.standard_normal((1, 64, 64))
    t_tex, t_flat, t_edge = texture_strength(textured), texture_strength(flat), texture_strength(edge)
    assert np.all(t_tex > 5)
    assert np.all(t_flat < 1.2)  # collect_gcps skips windows below 1.5
    assert np.all(t_edge < 2)  # a single straight edge only fixes one direction
    # Independent of the radiometric scale.
    np.testing.assert_allclose(texture_strength(textured * 1000 + 7), t_tex, rtol=1e-6)
    assert texture_strength(np.zeros((64, 64))) == 0


def test_block_reduce():
    a = np.arange(16.0).reshape(4, 4)
    np.testing.assert_allclose(block_reduce(a, 2), [[2.5, 4.5], [10.5, 12.5]])
    np.testing.assert_allclose(block_reduce(a, 1), a)


def test_staged_correlation_equals_phase_correlate():
    """spectra -> correlate_spectra -> quality (on a subset, as the fine level's passes use them) gives exactly
    phase_correlate's results."""
    from gdal_gf4cal.matching.correlate import correlate_spectra, spectra
    f, m, dx, dy = _pairs(12, 32, 2.0, noise=0.05, seed=9)
    whole = phase_correlate(f, m)
    F, G = spectra(f), spectra(m)
    pk = correlate_spectra(F, G)
    np.testing.assert_array_equal(pk.dx, whole.dx)
    sub = np.array([1, 4, 7, 11])
    q = pk.quality(F, G, sub)
    for name in ("dx", "dy", "peak", "peak_ratio", "ncc", "precision_px"):
        np.testing.assert_allclose(getattr(q, name), getattr(whole, name)[sub], rtol=1e-6, err_msg=name)
    np.testing.assert_allclose(whole.dx, dx, atol=0.25)  # small noisy windows: a sanity check only
    # A zero window pair correlates to a zero surface: no shift, no peak, no overflow warning.
    z = phase_correlate(np.zeros((2, 32, 32)), np.zeros((2, 32, 32)))
    assert np.all(z.dx == 0) and np.all(z.peak == 0)


def test_a_window_gives_the_same_bits_in_any_stack():
    """The fine level correlates its windows a few at a time and re-correlates single windows: a window's results
    must not depend on the stack it is in (einsum sums a single row of >= 8192 values along another path: at
    128 px and more a window alone was ~1e-7 px off), nor its texture measures on the chunk or on ``which=`` (the
    windows measured in place, without a copy)."""
    from gdal_gf4cal.matching.correlate import window_measures
    f, m, dx, dy = _pairs(7, 128, 2.0, noise=0.05, seed=4)
    whole = phase_correlate(f, m)
    for k in range(7):
        one = phase_correlate(f[k:k + 1], m[k:k + 1])
        for name in ("dx", "dy", "peak", "peak_ratio", "ncc", "precision_px"):
            assert getattr(one, name)[0] == getattr(whole, name)[k], (k, name)
    pair = phase_correlate(f[2:4], m[2:4])
    assert np.array_equal(pair.ncc, whole.ncc[2:4]) and np.array_equal(pair.dx, whole.dx[2:4])
    tex, flat = window_measures(f, (32, 96))
    assert np.all(tex > 10)                                   # textured windows: the measures are not trivial
    idx = np.array([5, 0, 3])
    t_w, f_w = window_measures(f, (32, 96), which=idx)
    np.testing.assert_array_equal(t_w, tex[idx])
    np.testing.assert_array_equal(f_w, flat[idx])
    t_1, f_1 = window_measures(f[3:4], (32, 96))
    assert t_1[0] == tex[3] and f_1[0] == flat[3]
    # Zero windows (no usable pair) measure texture 0, flat 1: what collect gives them without measuring.
    t0, f0 = window_measures(np.zeros((2, 64, 64)), (16, 48))
    assert np.all(t0 == 0) and np.all(f0 == 1)


@pytest.mark.parametrize("shape, sigma", [((64, 64), 1.0), ((96, 128), 0.7)])
def test_null_result_is_what_a_pair_without_data_gives(shape, sigma):
    """The fine passes stop a window without a usable pair at null_result instead of transforming it: the results
    of the transform of that pair (the reference's spectrum zeroed, its energy kept; the raw window zero) inside a
    stack of real windows, field by field (NaN NCC, infinite peak ratio and precision, shift 0)."""
    rng = np.random.default_rng(5)
    ref = ndimage.gaussian_filter(rng.normal(size=(3,) + shape), (0, 2, 2)).astype(np.float32)
    raw = np.roll(ref, (1, 2), axis=(1, 2))
    raw[1] = 0.0                                   # window 1: no raw data (as zeroed by the fine passes)
    F, G = spectra(ref), spectra(raw)
    F.S[1] = 0
    q = correlate_spectra(F, G, sigma).quality(F, G)
    null = null_result(shape, sigma)
    for k in ("dx", "dy", "peak", "peak_ratio", "ncc", "precision_px"):
        assert np.array_equal(getattr(q, k)[1:2], getattr(null, k), equal_nan=True), k
    assert null.peak[0] == 0 and np.isnan(null.ncc[0]) and np.isinf(null.peak_ratio[0])
    assert abs(q.dx[0] - 2) < 0.2 and abs(q.dy[0] - 1) < 0.2    # the real windows were measured (wrapped)


def test_peak_only_correlation_is_the_same_bits_without_ncc():
    """``phase_correlate(full=False)`` (a coarse search: the peak alone) gives the shift, peak and peak ratio of the
    full correlation bit for bit, and NaN for what it does not compute (NCC, precision)."""
    rng = np.random.default_rng(5)
    a = ndimage.gaussian_filter(rng.normal(size=(70, 96, 96)), 1.5)
    b = ndimage.shift(a, (0, 1.3, -2.6), order=3, mode="wrap") + 0.05 * rng.normal(size=a.shape)
    full = phase_correlate(a[:, 16:80, 16:80], b[:, 16:80, 16:80])
    peak = phase_correlate(a[:, 16:80, 16:80], b[:, 16:80, 16:80], full=False)
    for f in ("dx", "dy", "peak", "peak_ratio"):
        np.testing.assert_array_equal(getattr(peak, f), getattr(full, f))
    assert np.all(np.isnan(peak.ncc)) and np.all(np.isnan(peak.precision_px))
    assert np.median(np.abs(full.dx + 2.6)) < 0.1 and np.median(full.ncc) > 0.5
