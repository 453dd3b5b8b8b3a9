"""Batched sub-pixel phase correlation with quality measures (automatic GCP collection, issue 7).

Every function works on a *stack* of windows, shape ``(..., h, w)``, with one FFT call for the whole stack:
no Python loop per window. That is where the speed over a loop of ``skimage.registration.phase_cross_correlation``
comes from (see ``bench/bench_matching.py``), together with:

- single precision: windows are tapered and transformed in float32 with ``scipy.fft`` (``numpy.fft`` always
  computes in float64); the sub-pixel shift lives in the phases of a small spectrum, far above float32 rounding;
- no upsampled DFT: the sub-pixel peak is a closed-form 3-point fit on the low-passed surface (step 2 below);
- stages that can be reused: :func:`spectra` (the transform of a stack, reusable when one side does not move,
  as the reference windows across the fine level's passes), :func:`correlate_spectra` (the peak alone, all an
  intermediate pass needs) and :meth:`Peaks.quality` (second peak, NCC, precision for the final windows only).
  :func:`phase_correlate` chains the three.

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
from scipy import ndimage
import scipy.fft as sfft

#: Variance inflation of the phase-regression precision for the taper's correlation between frequencies.
_PRECISION_GAIN = 6.5

#: Noise floor of the texture tests, as a fraction of the window's standard deviation: a noise-free reference
#: (flat water but for interpolation ripples) is judged against this contrast instead of a zero noise level.
_FLOOR = 0.005

#: Windows per batch inside phase_correlate.
_CHUNK = 64

#: Bytes of float32 windows per chunk of :func:`window_measures` (about: :func:`chunks`): their temporaries (about 8
#: times as much) stay in the L2 and L3 caches (4 windows of 256 px, 64 of 64 px, 256 of 32 px). Against 512 kB
#: chunks (issue 23, one core): per window as fast or faster (32 px: 15.7 -> 14.7 us, 64 px: 67 -> 60 us, 256 px:
#: 0.80 -> 0.78 ms at 2 MB), and a half to a quarter of the NumPy calls (each holds the GIL a while).
_MEASURE_BYTES = 1 << 20

#: Smallest magnitude kept in the cross-power normalisation (float32 spectra): a zero window stays zero, and its
#: reciprocal times the low-pass weights stays far from float32 overflow.
_TINY = np.float32(1e-30)

__all__ = ["CorrelationResult", "phase_correlate", "taper", "texture_strength", "flat_fraction", "block_reduce",
           "window_measures", "spectra", "correlate_spectra", "Spectra", "Peaks", "null_result", "chunks"]


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


def _dot(a, v):
    """``a @ v`` for a stack ``a (n, k)`` and ``v (k,)`` or ``(k, m)`` without BLAS: the same rounding whatever the
    OpenBLAS kernel or thread count (a float32 ``sgemv`` differs by ~1e-7 px between them)."""
    if a.shape[0] == 1:
        # einsum sums a single row along another path (other bits): as the first row of a stack of two instead,
        # so that a window's results do not depend on how many windows share its stack.
        return _dot(np.concatenate([a, a]), v)[:1]
    if v.ndim == 1:
        return np.einsum("nk,k->n", a, v)
    return np.stack([np.einsum("nk,k->n", a, np.ascontiguousarray(v[:, j])) for j in range(v.shape[1])], axis=1)


@lru_cache(maxsize=16)
def _taper32(h: int, w: int, kind: str):
    """The taper in float32, flattened, and its sum (cached: built once per window size)."""
    win = taper((h, w), kind).astype(np.float32)
    return win, win.ravel(), np.float32(win.sum())


@dataclass
class Spectra:
    """Half spectra (``rfft2``, complex64) of a stack of prepared windows and their energies (sum of squares of
    the tapered, zero-mean windows). Built by :func:`spectra`; a fixed stack's spectra can be reused across
    calls of :func:`correlate_spectra` (the fine level re-reads only the moving window)."""

    S: np.ndarray
    energy: np.ndarray
    shape: Tuple[int, int]

    def take(self, idx) -> "Spectra":
        return Spectra(self.S[idx], self.energy[idx], self.shape)


def spectra(a: np.ndarray, window: str = "hann") -> Spectra:
    """Zero-mean (taper-weighted), tapered, float32 ``rfft2`` of a stack ``(n, h, w)``.

    float32 is ample: the sub-pixel estimate lives in the phases of a 64 x 64 spectrum (relative rounding 1e-7),
    and it halves memory traffic; ``scipy.fft`` transforms single precision natively (``numpy.fft`` does not).
    """
    a = np.asarray(a, dtype=np.float32)
    n, h, w = a.shape
    win, wflat, wsum = _taper32(h, w, window)
    mean = _dot(a.reshape(n, h * w), wflat) / wsum
    p = np.subtract(a, mean[:, None, None])
    p *= win
    # Row sums in float32, then their float64 sum (no cast inside a reduction: no buffers whose bounds depend on the
    # stack): the same bits for any stack; 5x faster than one float64 einsum, which casts every element.
    energy = np.einsum("nij,nij->ni", p, p).astype(np.float64).sum(axis=-1)
    return Spectra(sfft.rfft2(p, workers=1), energy, (h, w))


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
def _quality_weights(h: int, w: int, sigma: float):
    """float32 weights of the quality sums, as columns of one matrix per sum (one BLAS product each).

    ``K1 = [m, W (2 pi f_x)^2 m, W (2 pi f_y)^2 m]`` (m: Hermitian multiplicity) multiplies the cosines of the
    residual phases, ``K2 = W [W (2 pi f_x)^2 m, W (2 pi f_y)^2 m]`` their squared sines; plus the low-pass
    weight divided by the normaliser (applied to the cross-power spectrum before the inverse FFT).
    """
    fy, fx, weight, mult, norm = _freq_grids(h, w, sigma)
    m = np.broadcast_to(mult[None, :], weight.shape)
    wx = weight * (2 * np.pi * fx) ** 2 * m
    wy = weight * (2 * np.pi * fy) ** 2 * m
    K1 = np.stack([m.ravel(), wx.ravel(), wy.ravel()], axis=1).astype(np.float32)
    K2 = np.stack([(wx * weight).ravel(), (wy * weight).ravel()], axis=1).astype(np.float32)
    # irfft2 scales by 1/(h w); the normaliser makes a perfect match 1.
    wnorm = (weight / norm).astype(np.float32)
    return K1, K2, wnorm, fy.astype(np.float32), fx.astype(np.float32)


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
    return np.minimum(np.maximum(off, -0.5), 0.5)


@dataclass
class Peaks:
    """Peak stage of :func:`correlate_spectra` for a stack: the normalised cross-power spectrum, the surface and
    the sub-pixel peak. :meth:`quality` finishes the measures for any subset (only for the windows whose
    alignment is final: the fine level's intermediate passes need the shift alone)."""

    cross: np.ndarray
    inv: np.ndarray           # 1 / |cross| (floored): cross * inv is the unit cross-power spectrum
    surf: np.ndarray
    iy: np.ndarray
    ix: np.ndarray
    c0: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    peak: np.ndarray
    sigma: float

    def _second_peak(self, idx, exclude_px=None) -> np.ndarray:
        """The surface maximum outside the main lobe (a box of half-size r around the peak, wrap-around aware) of
        windows ``idx``: the maximum of every row, then of the lobe's rows outside the lobe's columns (no masked
        copy of the surfaces)."""
        n = idx.size
        h, w = self.surf.shape[-2:]
        r = int(np.ceil((3.0 * self.sigma + 1.0) if exclude_px is None else float(exclude_px)))
        off = np.arange(-r, r + 1)
        surf = self.surf if idx.size == self.dx.size and np.array_equal(idx, np.arange(n)) else self.surf[idx]
        rows = np.arange(n)[:, None]
        rowmax = surf.max(axis=-1)
        ly = (self.iy[idx][:, None] + off[None, :]) % h
        band = surf[rows, ly]  # (n, 2r + 1, w): the lobe's rows
        band[rows[:, :, None], np.arange(off.size)[None, :, None], (self.ix[idx][:, None, None] + off) % w] = -np.inf
        rowmax[rows, ly] = band.max(axis=-1)
        return rowmax.max(axis=1).astype(np.float64)

    def peak_ratio(self, idx, exclude_px=None) -> np.ndarray:
        """Peak over the surface's highest value outside the main lobe, of windows ``idx`` (:meth:`quality`'s)."""
        second = self._second_peak(idx, exclude_px)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(second > 0, self.c0[idx] / np.maximum(second, 1e-12), np.inf)

    def quality(self, F: Spectra, G: Spectra, idx=None, exclude_px: float = None) -> CorrelationResult:
        """Full :class:`CorrelationResult` for windows ``idx`` (all by default); ``F, G`` the same spectra
        (full stacks) the peaks were measured from."""
        if idx is None:
            idx = np.arange(self.dx.size)
        idx = np.asarray(idx)
        n = idx.size
        h, w = self.surf.shape[-2:]
        sigma = self.sigma
        dx, dy = self.dx[idx], self.dy[idx]
        if n == 0:
            e = np.zeros(0)
            return CorrelationResult(dx, dy, self.peak[idx], e, e, e)
        peak_ratio = self.peak_ratio(idx, exclude_px)
        # NCC of the tapered windows at the sub-pixel shift, by Parseval on the half spectrum, and the precision
        # from the residual phases. The phase ramp is separable: two 1-D exponentials, not one per frequency.
        K1, K2, _, fy, fx = _quality_weights(h, w, float(sigma))
        phase = (np.exp((2j * np.pi) * fy[None] * dy[:, None, None].astype(np.float32)).astype(np.complex64)
                 * np.exp((2j * np.pi) * fx[None] * dx[:, None, None].astype(np.float32)).astype(np.complex64))
        every = n == self.dx.size and np.array_equal(idx, np.arange(n))  # no copies of the whole stack
        # |cross| times the unit phasor of the residual phase (into the phases' array)
        z = np.multiply(self.cross if every else self.cross[idx], phase, out=phase)
        K = h * fx.size
        inv = (self.inv if every else self.inv[idx]).reshape(n, K)
        zr = np.ascontiguousarray(z.real).reshape(n, K)
        zc = zr * inv                        # cos(res)
        zs = np.multiply(z.imag.reshape(n, K), inv)  # sin(res)
        # |cross| cos(res) summed with the multiplicity: the cross term of Parseval.
        num = _dot(zr, K1[:, 0]).astype(np.float64)
        c1 = _dot(zc, K1[:, 1:]).astype(np.float64)            # sum W (2 pi f)^2 m cos(res), per axis
        s2 = _dot(zs * zs, K2).astype(np.float64)            # sum W^2 (2 pi f)^2 m sin^2(res), per axis
        # Parseval: the full spectrum's energy is h w times the window's sum of squares.
        ef = F.energy[idx] * (h * w)
        eg = G.energy[idx] * (h * w)
        with np.errstate(divide="ignore", invalid="ignore"):
            ncc = np.minimum(np.maximum(num / np.sqrt(ef * eg), -1.0), 1.0)
            # The peak maximises sum W cos(phi - 2 pi f.d); linearising at the optimum gives
            # var(d_x) = sum W^2 (2 pi f_x)^2 sin^2(res) / (sum W (2 pi f_x)^2 cos(res))^2, the sandwich variance
            # of a weighted phase regression. The taper correlates neighbouring frequencies, which
            # _PRECISION_GAIN (calibrated on simulated noisy textures, see tests) accounts for.
            var = _PRECISION_GAIN * (s2[:, 0] / c1[:, 0] ** 2 + s2[:, 1] / c1[:, 1] ** 2) / 2.0
            precision = np.sqrt(np.where(np.isfinite(var) & (var >= 0), var, np.inf))
        return CorrelationResult(dx, dy, self.peak[idx], peak_ratio, ncc, precision)


def correlate_spectra(F: Spectra, G: Spectra, sigma_px: float = 1.0) -> Peaks:
    """Peak stage of phase correlation from precomputed :func:`spectra` (stacks ``(n, h, w//2+1)``)."""
    n = F.S.shape[0]
    h, w = F.shape
    _, _, wnorm, _, _ = _quality_weights(h, w, float(sigma_px))
    cross = np.conj(F.S)
    cross *= G.S  # G F*, without a temporary
    inv = np.abs(cross)
    # Relative floor: frequencies with (numerically) no energy get no vote instead of a random phase.
    floor = np.maximum(np.float32(1e-12) * inv.reshape(n, -1).max(axis=1), _TINY)[:, None, None]
    np.maximum(inv, floor, out=inv)
    np.reciprocal(inv, out=inv)
    # Unit cross-power spectrum times the low-pass, in one complex-by-real product.
    surf = sfft.irfft2(cross * (inv * wnorm), s=(h, w), workers=1, overwrite_x=True)
    flat = surf.reshape(n, -1)
    idx = np.argmax(flat, axis=1)
    iy, ix = np.divmod(idx, w)
    # The peak and its four neighbours (wrap-around) in one gather, (5, n): centre, x - 1, y - 1, x + 1, y + 1;
    # the two axes' vertices in one call (elementwise: the bits of one call per axis).
    at = np.stack([idx, iy * w + (ix - 1) % w, (iy - 1) % h * w + ix, iy * w + (ix + 1) % w, (iy + 1) % h * w + ix])
    at += np.arange(0, n * h * w, h * w)
    v = flat.ravel().take(at).astype(np.float64)
    c0 = v[0]
    ox, oy = _logparabola(v[1:3], v[[0, 0]], v[3:5])
    # Peak value at the sub-pixel vertex (Gaussian model), so that quality does not depend on the phase.
    peak = np.minimum(c0 * np.exp(0.5 * (ox ** 2 + oy ** 2) / max(sigma_px, 0.5) ** 2), 1.0)
    dx = np.where(ix > w // 2, ix - w, ix) + ox
    dy = np.where(iy > h // 2, iy - h, iy) + oy
    return Peaks(cross, inv, surf, iy, ix, c0, dx, dy, peak, float(sigma_px))


def phase_correlate(fixed: np.ndarray, moving: np.ndarray, *, window: str = "hann", sigma_px: float = 1.0,
                    exclude_px: float = None, full: bool = True) -> CorrelationResult:
    """Sub-pixel shift of ``moving`` relative to ``fixed`` for a stack of windows (see module docstring).

    Parameters
    ----------
    fixed, moving : arrays ``(..., h, w)`` of the same shape (any real dtype). NaN is not allowed: check
        no-data before calling.
    window : taper, ``'hann'`` (default), ``'tukey'`` or ``'none'``.
    sigma_px : standard deviation (px) of the Gaussian correlation peak imposed by the spectral low-pass;
        about 1 px balances noise rejection and peak sharpness.
    exclude_px : radius of the main lobe excluded when looking for the second peak (default ``3 sigma_px + 1``).
    full : False leaves ``ncc`` and ``precision_px`` NaN (not computed: a coarse search needs the peak alone); the
        other fields are the same bits.

    Returns
    -------
    CorrelationResult with arrays of shape ``fixed.shape[:-2]``. Shifts are in ``(-w/2, w/2]``.
    """
    fixed = np.asarray(fixed)
    moving = np.asarray(moving)
    if fixed.shape != moving.shape or fixed.ndim < 2:
        raise ValueError(f"fixed {fixed.shape} and moving {moving.shape} must be stacks of equal-size windows")
    _taper_1d(2, window, 0.5)  # validates the window name
    lead = fixed.shape[:-2]
    h, w = fixed.shape[-2:]
    fixed = fixed.reshape((-1, h, w))
    moving = moving.reshape((-1, h, w))
    parts = []
    # Chunks keep the spectra of a batch in cache: large stacks are no slower per window than small ones.
    for k in range(0, max(fixed.shape[0], 1), _CHUNK):
        F = spectra(fixed[k:k + _CHUNK], window)
        G = spectra(moving[k:k + _CHUNK], window)
        pk = correlate_spectra(F, G, sigma_px)
        if full:
            parts.append(pk.quality(F, G, exclude_px=exclude_px))
            continue
        idx, nan = np.arange(pk.dx.size), np.full(pk.dx.size, np.nan)
        parts.append(CorrelationResult(pk.dx, pk.dy, pk.peak, pk.peak_ratio(idx, exclude_px), nan, nan))
    return CorrelationResult(*(np.concatenate([getattr(q, f) for q in parts]).reshape(lead)
                               for f in ("dx", "dy", "peak", "peak_ratio", "ncc", "precision_px")))


@lru_cache(maxsize=16)
def null_result(shape: Tuple[int, int], sigma_px: float = 1.0) -> CorrelationResult:
    """What :func:`phase_correlate` gives for a pair of zero windows of ``shape`` (one window: shift 0, peak 0,
    peak ratio inf, NCC NaN, precision inf): the results of a pair without data, which need not be
    transformed (also when only one of the two is zero: the cross-power spectrum is zero either way)."""
    z = spectra(np.zeros((1,) + tuple(int(v) for v in shape), dtype=np.float32))
    return correlate_spectra(z, z, float(sigma_px)).quality(z, z)


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
    gx, gy = _gradients(a)
    floor = None if noise_floor is None else np.asarray(noise_floor, dtype=float)
    return _texture(a, gx, gy, _noise_sigma(a), floor)


def _gradients(a: np.ndarray):
    """Central differences on the interior: ``gx, gy`` of shape ``(..., h - 2, w - 2)``."""
    return a[..., 1:-1, 2:] - a[..., 1:-1, :-2], a[..., 2:, 1:-1] - a[..., :-2, 1:-1]


def _texture(a, gx, gy, sigma, floor=None, std=None):
    """:func:`texture_strength` from precomputed gradients and noise estimate (shared with the flat test)."""
    # Row sums, then their sum: the same bits whatever the stack's length (a whole-window einsum takes another
    # path for a single window).
    sxx, syy, sxy = (np.einsum("...ij,...ij->...i", u, v).sum(axis=-1) / (gx.shape[-1] * gx.shape[-2])
                     for u, v in ((gx, gx), (gy, gy), (gx, gy)))
    sxx, syy, sxy = (np.asarray(v, dtype=np.float64) for v in (sxx, syy, sxy))
    lam_min = 0.5 * (sxx + syy) - np.sqrt(0.25 * (sxx - syy) ** 2 + sxy ** 2)
    if floor is None:
        floor = _FLOOR * (_std(a) if std is None else std)
    # Central differences of white noise have variance 2 sigma^2.
    noise_var = 2.0 * np.maximum(np.maximum(sigma, floor), 1e-12) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(sxx + syy > 0, np.maximum(lam_min, 0) / noise_var, 0.0)
    return out


def _std(a):
    return np.asarray(np.std(a, axis=(-1, -2)), dtype=np.float64)


def _noise_sigma(a: np.ndarray) -> np.ndarray:
    """Immerkaer's (1996) noise estimate per window: sqrt(pi/2) / 6 * mean|I * Laplacian-difference kernel|.

    The 3 x 3 kernel ``[[1, -2, 1], [-2, 4, -2], [1, -2, 1]]`` is the outer product of ``[1, -2, 1]`` with
    itself: two 1-D second differences instead of nine shifted copies.
    """
    # In place, in the same order as ``a0 - 2 a1 + a2`` (same bits): two temporaries instead of eight, which
    # halves the time on 256-px stacks.
    d2 = 2 * a[..., :, 1:-1]
    np.subtract(a[..., :, :-2], d2, out=d2)
    np.add(d2, a[..., :, 2:], out=d2)
    lap = 2 * d2[..., 1:-1, :]
    np.subtract(d2[..., :-2, :], lap, out=lap)
    np.add(lap, d2[..., 2:, :], out=lap)
    np.abs(lap, out=lap)
    return np.sqrt(np.pi / 2.0) / 6.0 * np.asarray(np.mean(lap, axis=(-1, -2)), dtype=np.float64)


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
    a = np.asarray(windows, dtype=np.float64)
    gx, gy = _gradients(a)
    return _flat(a, gx, gy, _noise_sigma(a), region, box, ratio, noise_factor)


def _flat(a, gx, gy, sigma, region=None, box: int = 5, ratio: float = 0.05, noise_factor: float = 3.0, std=None,
          parts=None):
    """:func:`flat_fraction` from precomputed gradients and noise estimate (shared with the texture test);
    ``parts``: the local energy on every other pixel of the interior and on the region, when already computed
    (:func:`_box_parts`)."""
    if parts is None:
        g2 = np.zeros_like(a)
        e = gx * gx
        e += gy * gy
        e /= 4.0
        g2[..., 1:-1, 1:-1] = e
        local = ndimage.uniform_filter(g2, size=(1,) * (a.ndim - 2) + (box, box), mode="nearest")
        parts = local[..., 1:-1:2, 1:-1:2], (local if region is None else local[..., region[0]:region[1],
                                                                                region[0]:region[1]])
    sampled, counted = parts
    # The 90th percentile of the local energy on every other pixel of each axis (the 5 x 5 box mean is smooth:
    # neighbours carry the same information), where the threshold depends on it.
    inner = np.ascontiguousarray(sampled).reshape((-1, sampled.shape[-2] * sampled.shape[-1]))
    # Central differences of white noise of std sigma have variance 2 sigma^2: local energy ~ sigma^2.
    sigma = np.maximum(sigma, _FLOOR * (_std(a) if std is None else std))
    cap = noise_factor * sigma ** 2
    thresh = np.minimum(ratio * _percentile90(inner, cap / ratio if ratio > 0 else None).reshape(np.shape(cap)), cap)
    below = np.count_nonzero(counted <= thresh[..., None, None].astype(counted.dtype), axis=(-1, -2))
    return below / float(counted.shape[-1] * counted.shape[-2])


def _percentile90(inner, bound=None):
    """The 90th percentile ('linear' interpolation, as np.percentile) of every row of ``inner`` (n, N), from a partial
    sort: two order statistics; +inf instead for the rows whose percentile is surely at least ``bound`` (per row, with
    a margin of 1e-3 for rounding: where :func:`_flat`'s threshold is its other term). One counting pass tells
    those rows (the textured windows, most: all 64-px windows of the bench collect scene, 99 % of the GF7 crop's
    32-px ones, 80 % of the Sentinel-2 pair's 256-px ones) and spares them the partial sort (170 us of a 256-px
    window's 725 in :func:`window_measures`, and np.partition holds the GIL); the other rows' percentiles are the
    same bits."""
    n, size = inner.shape
    pos = 0.9 * (size - 1)
    k = int(np.floor(pos))
    k1 = min(k + 1, size - 1)
    level = np.full(n, np.inf, dtype=inner.dtype)
    rest = np.ones(n, dtype=bool)
    if bound is not None:
        # the k-th smallest value is >= bound where at most k values are not (NaN counts as not: sorted last)
        b = np.broadcast_to(np.asarray(bound, dtype=float) * (1.0 + 1e-3), (n,)).astype(inner.dtype)[:, None]
        rest = np.count_nonzero(~(inner >= b), axis=-1) > k
    if rest.any():
        part = np.partition(inner if rest.all() else inner[rest], [k, k1], axis=-1)
        lo, hi = part[:, k], part[:, k1]
        level[rest] = lo + (pos - k) * (hi - lo)
    return level


def window_measures(windows: np.ndarray, region=None, *, which=None):
    """``(texture_strength(windows), flat_fraction(windows, region))`` sharing the gradients and the noise
    estimate, computed in float32 (the thresholds they feed are coarse; the ratio of two gradient energies
    does not need double precision), a few windows at a time: each chunk's temporaries (gradients, the local
    energy, the Laplacian) stay in the CPU cache instead of streaming stacks of them through memory (3 times
    faster on 256-px windows than whole stacks). Every window's measures depend on that window alone, so the
    chunk size does not change them. ``which``: indices of the windows of a stack ``(N, h, w)`` to measure (one
    result each; no copy of the stack)."""
    a = np.asarray(windows)
    lead, (h, w) = a.shape[:-2], a.shape[-2:]
    a = a.reshape((-1, h, w))
    if which is not None:
        which = np.asarray(which, dtype=np.intp).ravel()
        lead = which.shape
    n = a.shape[0] if which is None else which.size
    tex = np.empty(n)
    flat = np.empty(n)
    for sl in chunks(n, _MEASURE_BYTES // (4 * h * w)):
        c = np.asarray(a[sl] if which is None else a[which[sl]], dtype=np.float32)
        gx, gy = _gradients(c)
        sigma = _noise_sigma(c)
        std = _std(c)
        tex[sl] = _texture(c, gx, gy, sigma, std=std)
        flat[sl] = _flat(c, gx, gy, sigma, region, std=std, parts=_box_parts(gx, gy, region))
    return tex.reshape(lead), flat.reshape(lead)


def chunks(n: int, step: int):
    """Slices of ``range(n)`` in chunks of about ``step`` items (a cache-sized batch): ``round(n / step)`` chunks (at
    least one) of equal sizes within one, so that a stack a little larger than ``step`` is one chunk (one set of
    NumPy calls) and a larger one has no small last chunk. For computations of each item alone: the chunks change
    no bit."""
    k = max(1, int(n / max(int(step), 1) + 0.5))
    edges = [i * n // k for i in range(k + 1)]
    return [slice(edges[i], edges[i + 1]) for i in range(k) if edges[i + 1] > edges[i]]


def _box_parts(gx, gy, region=None):
    """The local gradient energy of :func:`_flat` (5 x 5 box mean of ``(gx^2 + gy^2) / 4``, zero on the border
    pixels, 'nearest' edges) of a float32 stack where :func:`_flat` reads it: on every other pixel of the interior
    (its percentile) and on ``region`` (its count; everywhere without one), about 40% of a 256-px window's pixels.
    Shifted sums in float32 (to ~3e-7 relative of ``ndimage.uniform_filter``, which works in float64 lines, at a
    third of its time), each value with the same additions whatever part it is computed in. The zero border padded
    by two more zeros is the 'nearest' extension of the zero border."""
    h, w = gx.shape[-2] + 2, gx.shape[-1] + 2
    P = np.zeros(gx.shape[:-2] + (h + 4, w + 4), dtype=gx.dtype)
    e = P[..., 3:h + 1, 3:w + 1]
    np.multiply(gx, gx, out=e)
    e += gy * gy
    e *= np.float32(0.25)
    sampled = _box_sums(P, 1, len(range(1, h - 1, 2)), 1, len(range(1, w - 1, 2)), 2)
    if region is None:
        return sampled, _box_sums(P, 0, h, 0, w, 1)
    r0, r1 = (min(max(int(v), 0), min(h, w)) for v in region)
    return sampled, _box_sums(P, r0, r1 - r0, r0, r1 - r0, 1)


def _box_sums(P, i0: int, ni: int, j0: int, nj: int, s: int):
    """Box means of 5 x 5 of the padded energy ``P`` (output pixel ``(i, j)`` averages ``P[i:i + 5, j:j + 5]``)
    at rows ``i0 + s k`` (``k < ni``) and columns ``j0 + s k`` (``k < nj``), ``s`` 1 or 2: a sum of 5 as
    ``(x0 + x1) + (x2 + x3) + x4``, three additions per axis, columns first."""
    sh = 2 // s    # x2 + x3 is the pair sum ``sh`` steps further
    rows = P[..., i0:i0 + s * (ni - 1) + 5, :]
    r2 = rows[..., j0:j0 + s * (nj + sh):s] + rows[..., j0 + 1:j0 + 1 + s * (nj + sh):s]
    r = r2[..., :nj] + r2[..., sh:sh + nj]
    r += rows[..., j0 + 4:j0 + 4 + s * nj:s]
    c2 = r[..., 0:s * (ni + sh):s, :] + r[..., 1:1 + s * (ni + sh):s, :]
    out = c2[..., :ni, :] + c2[..., sh:sh + ni, :]
    out += r[..., 4:4 + s * ni:s, :]
    out *= np.float32(1.0 / 25.0)
    return out


def block_reduce(a: np.ndarray, factor: int) -> np.ndarray:
    """Mean over ``factor x factor`` blocks of the last two axes (sizes must be multiples of ``factor``)."""
    if factor == 1:
        return np.asarray(a, dtype=np.float64)
    h, w = a.shape[-2:]
    b = np.asarray(a, dtype=np.float64).reshape(a.shape[:-2] + (h // factor, factor, w // factor, factor))
    return b.mean(axis=(-1, -3))
