"""Batched sub-pixel phase correlation with quality measures (automatic GCP collection, issue 7).

Every function works on a *stack* of windows, shape ``(..., h, w)``, with one FFT call for the whole stack:
no Python loop per window. That is where the speed over a loop of ``skimage.registration.phase_cross_correlation``
comes from (see ``bench/bench_matching.py``).

Method
------
1. Each window is made zero-mean and tapered with a separable Hann (or Tukey) window, which removes the
   wrap-around edges of the FFT.
2. Normalised cross-power spectrum ``C = G F* / |G F*|`` (pure phase), multiplied by a Gaussian low-pass
   ``W(f) = exp(-2 pi^2 s^2 |f|^2)``. Without noise the inverse transform of ``W e^{-2 pi i f.d}`` is a sampled
   Gaussian of standard deviation ``s`` px centred on the shift ``d``; the log of a sampled Gaussian is exactly a
   parabola, so a 3-point log-parabola fit per axis gives the sub-pixel peak without upsampling and without the
   bias of a plain parabola fit on a sinc-like peak. The low-pass also de-weights the noisy high frequencies.
3. Quality: ``peak`` (surface value at the peak, 1 for identical windows), ``peak_ratio`` (peak over the highest
   value outside the main lobe), ``ncc`` (correlation coefficient of the tapered windows at the sub-pixel shift,
   from the spectra by Parseval) and ``precision_px`` (Foerstner's matching precision: noise variance implied by
   ``ncc`` over the gradient energy of the window, per axis).

Sign convention: the returned ``(dx, dy)`` is the displacement of ``moving`` relative to ``fixed``:
``moving(x, y) ~= fixed(x - dx, y - dy)`` (a feature at ``(x, y)`` in ``fixed`` is at ``(x + dx, y + dy)`` in
``moving``). x is the sample (column) axis and y the line (row) axis.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Tuple

import numpy as np

#: Variance inflation of the phase-regression precision for the taper's correlation between frequencies.
_PRECISION_GAIN = 6.5

#: Noise floor of the texture tests, as a fraction of the window's standard deviation: a noise-free reference
#: (flat water but for interpolation ripples) is judged against this contrast instead of a zero noise level.
_FLOOR = 0.005

#: Windows per batch inside phase_correlate.
_CHUNK = 64

__all__ = ["CorrelationResult", "phase_correlate", "taper", "texture_strength", "flat_fraction", "block_reduce"]


@dataclass(frozen=True)
class CorrelationResult:
    """Per-window results of :func:`phase_correlate` (arrays of the stack's leading shape).

    ``dx, dy`` displacement of ``moving`` relative to ``fixed`` (px); ``peak`` correlation-surface maximum in
    [0, 1]; ``peak_ratio`` peak over the highest secondary value; ``ncc`` normalised cross-correlation of the
    tapered windows at the sub-pixel shift; ``precision_px`` estimated 1-sigma per-axis precision of the shift.
    """

    dx: np.ndarray
    dy: np.ndarray
    peak: np.ndarray
    peak_ratio: np.ndarray
    ncc: np.ndarray
    precision_px: np.ndarray


@lru_cache(maxsize=16)
def _taper_1d(n: int, kind: str, alpha: float) -> np.ndarray:
    if kind == "hann":
        # Periodic-free "symmetric" Hann without the zero end points: every pixel keeps some weight.
        return np.sin(np.pi * (np.arange(n) + 0.5) / n) ** 2
    if kind == "tukey":
        x = (np.arange(n) + 0.5) / n
        w = np.ones(n)
        edge = alpha / 2.0
        lo = x < edge
        hi = x > 1.0 - edge
        w[lo] = 0.5 * (1 - np.cos(np.pi * x[lo] / edge))
        w[hi] = 0.5 * (1 - np.cos(np.pi * (1.0 - x[hi]) / edge))
        return w
    if kind == "none":
        return np.ones(n)
    raise ValueError(f"unknown window {kind!r}: use 'hann', 'tukey' or 'none'")


def taper(shape: Tuple[int, int], kind: str = "hann", alpha: float = 0.5) -> np.ndarray:
    """Separable 2-D taper of ``shape`` (``'hann'``, ``'tukey'`` with ``alpha``, or ``'none'``)."""
    return np.outer(_taper_1d(int(shape[0]), kind, alpha), _taper_1d(int(shape[1]), kind, alpha))


def _prepare(a: np.ndarray, win: np.ndarray) -> np.ndarray:
    """Subtract the taper-weighted mean (so the tapered window has no DC) and apply the taper."""
    a = np.asarray(a, dtype=np.float64)
    mean = np.einsum("...ij,ij->...", a, win) / win.sum()
    return (a - mean[..., None, None]) * win


@lru_cache(maxsize=16)
def _freq_grids(h: int, w: int, sigma: float):
    """rfft2 frequency grids, the Gaussian weight, the Hermitian multiplicity and the weights' normaliser."""
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    weight = np.exp(-2.0 * np.pi ** 2 * sigma ** 2 * (fx ** 2 + fy ** 2)) if sigma > 0 else np.ones((h, fx.size))
    weight = np.broadcast_to(weight, (h, fx.size)).copy()
    weight[0, 0] = 0.0  # DC carries no shift information (and is zero after mean removal)
    # Columns of the half spectrum that stand for two columns of the full one.
    mult = np.full(fx.size, 2.0)
    mult[0] = 1.0
    if w % 2 == 0:
        mult[-1] = 1.0
    norm = float((weight * mult[None, :]).sum()) / (h * w)  # surface value of a perfect match
    return fy, fx, weight, mult, norm


@lru_cache(maxsize=16)
def _grad_weights(h: int, w: int, sigma: float):
    """``W (2 pi f_x)^2 m`` and ``W (2 pi f_y)^2 m`` on the half spectrum (m: Hermitian multiplicity)."""
    fy, fx, weight, mult, _ = _freq_grids(h, w, sigma)
    wx = weight * (2 * np.pi * fx) ** 2 * mult[None, :]
    wy = weight * (2 * np.pi * fy) ** 2 * mult[None, :]
    return wx, wy


def _logparabola(cm: np.ndarray, c0: np.ndarray, cp: np.ndarray) -> np.ndarray:
    """Sub-pixel vertex offset from three samples: Gaussian (log-parabola) fit, parabola where a value is <= 0."""
    with np.errstate(all="ignore"):
        pos = (cm > 0) & (c0 > 0) & (cp > 0)
        lm, l0, lp = np.log(np.where(pos, cm, 1.0)), np.log(np.where(pos, c0, 1.0)), np.log(np.where(pos, cp, 1.0))
        den_g = lm - 2 * l0 + lp
        off_g = 0.5 * (lm - lp) / den_g
        den_p = cm - 2 * c0 + cp
        off_p = 0.5 * (cm - cp) / den_p
        off = np.where(pos & (den_g < 0), off_g, np.where(den_p < 0, off_p, 0.0))
    return np.clip(off, -0.5, 0.5)


def phase_correlate(fixed: np.ndarray, moving: np.ndarray, *, window: str = "hann", sigma_px: float = 1.0,
                    exclude_px: float = None) -> CorrelationResult:
    """Sub-pixel shift of ``moving`` relative to ``fixed`` for a stack of windows (see module docstring).

    Parameters
    ----------
    fixed, moving : arrays ``(..., h, w)`` of the same shape (any real dtype). NaN is not allowed: check
        no-data before calling.
    window : taper, ``'hann'`` (default), ``'tukey'`` or ``'none'``.
    sigma_px : standard deviation (px) of the Gaussian correlation peak imposed by the spectral low-pass;
        about 1 px balances noise rejection and peak sharpness.
    exclude_px : radius of the main lobe excluded when looking for the second peak (default ``3 sigma_px + 1``).

    Returns
    -------
    CorrelationResult with arrays of shape ``fixed.shape[:-2]``. Shifts are in ``(-w/2, w/2]``.
    """
    fixed = np.asarray(fixed)
    moving = np.asarray(moving)
    if fixed.shape != moving.shape or fixed.ndim < 2:
        raise ValueError(f"fixed {fixed.shape} and moving {moving.shape} must be stacks of equal-size windows")
    lead = fixed.shape[:-2]
    h, w = fixed.shape[-2:]
    fixed = fixed.reshape((-1, h, w))
    moving = moving.reshape((-1, h, w))
    if fixed.shape[0] > _CHUNK:
        # Chunks keep the spectra of a batch in cache: large stacks are no slower per window than small ones.
        parts = [phase_correlate(fixed[k:k + _CHUNK], moving[k:k + _CHUNK], window=window, sigma_px=sigma_px,
                                 exclude_px=exclude_px) for k in range(0, fixed.shape[0], _CHUNK)]
        return CorrelationResult(*(np.concatenate([getattr(q, f) for q in parts]).reshape(lead)
                                   for f in ("dx", "dy", "peak", "peak_ratio", "ncc", "precision_px")))
    n = fixed.shape[0]
    win = taper((h, w), window)
    F = np.fft.rfft2(_prepare(fixed, win))
    G = np.fft.rfft2(_prepare(moving, win))
    fy, fx, weight, mult, norm = _freq_grids(h, w, float(sigma_px))
    cross = G * np.conj(F)
    mag = np.abs(cross)
    # Relative floor: frequencies with (numerically) no energy get no vote instead of a random phase.
    floor = 1e-12 * mag.reshape(n, -1).max(axis=1)[:, None, None] + 1e-300
    unit = cross / np.maximum(mag, floor)
    surf = np.fft.irfft2(unit * weight, s=(h, w)) / norm

    flat = surf.reshape(n, -1)
    idx = np.argmax(flat, axis=1)
    iy, ix = np.divmod(idx, w)
    rows = np.arange(n)
    c0 = flat[rows, idx]
    cxm = surf[rows, iy, (ix - 1) % w]
    cxp = surf[rows, iy, (ix + 1) % w]
    cym = surf[rows, (iy - 1) % h, ix]
    cyp = surf[rows, (iy + 1) % h, ix]
    ox = _logparabola(cxm, c0, cxp)
    oy = _logparabola(cym, c0, cyp)
    # Peak value at the sub-pixel vertex (Gaussian model), so that quality does not depend on the phase.
    peak = c0 * np.exp(0.5 * (ox ** 2 + oy ** 2) / max(sigma_px, 0.5) ** 2)
    peak = np.minimum(peak, 1.0)
    dx = np.where(ix > w // 2, ix - w, ix) + ox
    dy = np.where(iy > h // 2, iy - h, iy) + oy

    # Second peak: the maximum outside the main lobe (a box of half-size r around the peak, wrap-around aware).
    r = int(np.ceil((3.0 * sigma_px + 1.0) if exclude_px is None else float(exclude_px)))
    off = np.arange(-r, r + 1)
    ly = (iy[:, None, None] + off[None, :, None]) % h
    lx = (ix[:, None, None] + off[None, None, :]) % w
    masked = surf.copy()
    masked[rows[:, None, None], ly, lx] = -np.inf
    second = masked.reshape(n, -1).max(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        peak_ratio = np.where(second > 0, c0 / np.maximum(second, 1e-12), np.inf)

    # NCC of the tapered windows at the sub-pixel shift, by Parseval on the half spectrum. The phase ramp is
    # separable: two 1-D exponentials instead of one over the whole spectrum.
    phase = (np.exp(2j * np.pi * fy[None] * dy[:, None, None])
             * np.exp(2j * np.pi * fx[None] * dx[:, None, None]))
    z = unit * phase                      # unit phasors of the residual phase: cos = Re, sin = Im
    zc, zs = z.real, z.imag
    m = mult[None, None, :]
    num = (mag * zc * m).sum(axis=(1, 2))
    ef = ((F.real ** 2 + F.imag ** 2) * m).sum(axis=(1, 2))
    eg = ((G.real ** 2 + G.imag ** 2) * m).sum(axis=(1, 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        ncc = np.clip(num / np.sqrt(ef * eg), -1.0, 1.0)
        # Precision from the residual phases: the peak maximises sum W cos(phi - 2 pi f.d); linearising at the
        # optimum gives var(d_x) = sum W^2 (2 pi f_x)^2 sin^2(res) / (sum W (2 pi f_x)^2 cos(res))^2, the
        # sandwich variance of a weighted phase regression. The taper correlates neighbouring frequencies,
        # which _PRECISION_GAIN (calibrated on simulated noisy textures, see tests) accounts for.
        wx, wy = _grad_weights(h, w, float(sigma_px))
        s2 = zs * zs
        var_x = (wx * weight * s2).sum(axis=(1, 2)) / (wx * zc).sum(axis=(1, 2)) ** 2
        var_y = (wy * weight * s2).sum(axis=(1, 2)) / (wy * zc).sum(axis=(1, 2)) ** 2
        var = _PRECISION_GAIN * (var_x + var_y) / 2.0
        precision = np.sqrt(np.where(np.isfinite(var) & (var >= 0), var, np.inf))
    shape = lead
    return CorrelationResult(dx.reshape(shape), dy.reshape(shape), peak.reshape(shape),
                             peak_ratio.reshape(shape), ncc.reshape(shape), precision.reshape(shape))


def texture_strength(windows: np.ndarray, noise_floor=None) -> np.ndarray:
    """Texture-to-noise ratio of each window of a stack ``(..., h, w)``: larger means better to match.

    The weaker eigenvalue of the mean structure tensor (gradient energy in the worst direction, so a single
    straight edge scores low) divided by the gradient variance that white noise of the window's noise level
    would give. The noise level is Immerkaer's Laplacian-based estimate, floored at ``noise_floor`` (per window;
    default 0.5% of the window's standard deviation) so that noise-free images (a clean orthophoto, where water is
    exactly flat but for interpolation ripples) are judged against a sensible contrast. The ratio does not depend
    on the radiometric scale: ~1 or less on featureless areas (water, flat cloud); texture scores well above.
    A window with no variation at all scores 0.
    """
    a = np.asarray(windows, dtype=np.float64)
    gx = a[..., 1:-1, 2:] - a[..., 1:-1, :-2]
    gy = a[..., 2:, 1:-1] - a[..., :-2, 1:-1]
    sxx = (gx * gx).mean(axis=(-1, -2))
    syy = (gy * gy).mean(axis=(-1, -2))
    sxy = (gx * gy).mean(axis=(-1, -2))
    lam_min = 0.5 * (sxx + syy) - np.sqrt(0.25 * (sxx - syy) ** 2 + sxy ** 2)
    sigma = _noise_sigma(a)
    floor = _FLOOR * a.std(axis=(-1, -2)) if noise_floor is None else np.asarray(noise_floor, dtype=float)
    # Central differences of white noise have variance 2 sigma^2.
    noise_var = 2.0 * np.maximum(np.maximum(sigma, floor), 1e-12) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(sxx + syy > 0, np.maximum(lam_min, 0) / noise_var, 0.0)
    return out


def _noise_sigma(a: np.ndarray) -> np.ndarray:
    """Immerkaer's (1996) noise estimate per window: sqrt(pi/2) / 6 * mean|I * Laplacian-difference kernel|."""
    lap = (a[..., :-2, :-2] - 2 * a[..., :-2, 1:-1] + a[..., :-2, 2:]
           - 2 * a[..., 1:-1, :-2] + 4 * a[..., 1:-1, 1:-1] - 2 * a[..., 1:-1, 2:]
           + a[..., 2:, :-2] - 2 * a[..., 2:, 1:-1] + a[..., 2:, 2:])
    return np.sqrt(np.pi / 2.0) / 6.0 * np.abs(lap).mean(axis=(-1, -2))


def flat_fraction(windows: np.ndarray, region=None, box: int = 5, ratio: float = 0.05,
                  noise_factor: float = 3.0) -> np.ndarray:
    """Fraction of featureless pixels (water, flat cloud) in each window of a stack ``(N, h, w)``.

    A pixel is flat when its local gradient energy (``box x box`` mean of ``gx^2 + gy^2``, over 4) is both

    - below ``ratio`` times the window's 90th percentile of it: water or cloud next to land, whose gradients are
      at the noise level (or exactly zero in a clean orthophoto), fall far below the land's texture; and
    - below ``noise_factor`` times the window's noise variance (Immerkaer's estimate, floored like
      :func:`texture_strength`): flat water or cloud has the local energy of noise (~sigma^2), while ordinary land
      texture next to a few much stronger edges (a road, a field border) also falls below the relative threshold
      but stays well above the noise. Without this second test a road crossing a window made its land "flat".

    A window that is flat *everywhere* has no contrast to compare with: :func:`texture_strength` judges it.
    ``region = (r0, r1)`` restricts the count to ``[r0:r1, r0:r1]`` (e.g. the window centre, where the GCP is).
    """
    from scipy import ndimage
    a = np.asarray(windows, dtype=np.float64)
    g2 = np.zeros_like(a)
    g2[..., 1:-1, 1:-1] = ((a[..., 1:-1, 2:] - a[..., 1:-1, :-2]) ** 2
                           + (a[..., 2:, 1:-1] - a[..., :-2, 1:-1]) ** 2) / 4.0
    local = ndimage.uniform_filter(g2, size=(1,) * (a.ndim - 2) + (box, box), mode="nearest")
    level = np.percentile(local[..., 1:-1, 1:-1].reshape(local.shape[:-2] + (-1,)), 90, axis=-1)
    # Central differences of white noise of std sigma have variance 2 sigma^2: local energy ~ sigma^2.
    sigma = np.maximum(_noise_sigma(a), _FLOOR * a.std(axis=(-1, -2)))
    thresh = np.minimum(ratio * level, noise_factor * sigma ** 2)
    flat = local <= thresh[..., None, None]
    if region is not None:
        r0, r1 = region
        flat = flat[..., r0:r1, r0:r1]
    return flat.mean(axis=(-1, -2))


def block_reduce(a: np.ndarray, factor: int) -> np.ndarray:
    """Mean over ``factor x factor`` blocks of the last two axes (sizes must be multiples of ``factor``)."""
    if factor == 1:
        return np.asarray(a, dtype=np.float64)
    h, w = a.shape[-2:]
    b = np.asarray(a, dtype=np.float64).reshape(a.shape[:-2] + (h // factor, factor, w // factor, factor))
    return b.mean(axis=(-1, -3))
