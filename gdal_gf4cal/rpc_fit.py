"""Terrain-independent RPC fitting (METHODS §3; Tao & Hu 2001).

Two entry points:

* :func:`fit_rpc` fits an RPC00B model to correspondences ``(lon, lat, h) <-> (sample, line)``;
* :func:`fit_rpc_from_model` builds those correspondences from any sensor model exposing
  ``localize(sample, line, h) -> (lon, lat)`` (a rigorous model, a simulator, another RPC): an image grid times
  height layers, then fits and checks on a second grid offset by half a cell, at intermediate heights.

Method
------
Each image axis is fitted separately (39 unknowns: numerator 20, denominator 19 with ``den[0] = 1``), which is
what makes the fit fast: every solve is a 39 x 39 system. With normalised ground monomials ``m`` (RPC00B order,
:func:`gdal_gf4cal.rpc.monomials`) and the normalised image coordinate ``r``, ``r = (a.m) / (1 + b.m[1:])`` is
linearised as ``a.m - r b.m[1:] = r`` and solved by iteratively reweighted least squares with row weights
``1 / D`` (``D`` the current denominator; Tao & Hu 2001), then polished by a few Gauss-Newton steps on the true
residual ``r - N/D`` (the reweighting fixed point is close to, but not exactly, the least-squares optimum).

Every solve uses column-equilibrated normal equations (each column scaled to unit norm, so the normal matrix has
unit diagonal and trace = number of unknowns) with Tikhonov regularisation ``lambda * I`` in that scaled space,
i.e. a penalty ``lambda * sum_j G_jj x_j**2`` relative to each unknown's own column energy (``G`` the normal
matrix), followed by iterative refinement against the unscaled residual. ``regularization="auto"`` takes the
smallest lambda from 1e-14 upwards for which the system is positive definite and the denominator stays well
away from zero over the fit points and the whole normalised domain; that keeps the bias far below the data's
own precision (it reproduces the least-squares optimum on the Sentinel-1 grids) while removing the classic
near-redundancy between numerator and ``r x denominator`` columns.

Pixel convention: image coordinates are GDAL's (centre of the first pixel at 0.5, 0.5) unless
``pixel_convention="rpc"``; the returned :class:`~gdal_gf4cal.rpc.RPCModel` stores ``LINE_OFF``/``SAMP_OFF`` in the
raw RPC00B convention as every RPC file does (so its ``project`` speaks GDAL's convention again).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np
import scipy.linalg as sla

from .errors import DegenerateGeometryError, GCPError
from .estimation import weighted_lsq
from .progress import ProgressCallback, report, scaled
from .rpc import GDAL_PIXEL_OFFSET, RPCModel, monomials

__all__ = ["FitErrors", "FitReport", "fit_rpc", "fit_rpc_from_model", "refit_numerators"]

#: Number of unknowns per image axis (numerator 20 + denominator 19).
N_UNKNOWNS = 39
#: Ladder of relative Tikhonov parameters tried by ``regularization="auto"`` (smallest first).
AUTO_REGULARIZATION = (1e-14, 1e-13, 1e-12, 1e-11, 1e-10, 1e-9, 1e-8, 1e-6)
#: The denominator must stay above this over the fit points and the normalised domain (1 + b.m[1:]; 1 = none).
_MIN_DENOMINATOR = 0.1
#: Relative change of the residual RMS below which the reweighting / Gauss-Newton iterations stop.
_REL_TOL = 1e-4
_GN_STEPS = 4
#: ... and changes of the RMS below this many pixels do not count (exactly representable data).
_ABS_TOL_PX = 1e-7


class _IllPosed(Exception):
    """Internal: with this lambda the system is numerically singular or the denominator nears zero."""


# ---------------------------------------------------------------------------------------------- reports
@dataclass(frozen=True)
class FitErrors:
    """Image-space errors of a fitted RPC against reference points, in pixels (METHODS §6).

    Residuals are ``reference - predicted`` per axis (only magnitudes are kept: RMS = sqrt(mean(x**2)) and
    max |x|); ``rms_px``/``max_px`` are planar (``sqrt(ds**2 + dl**2)``), the ``_sample_``/``_line_`` fields per axis.
    """

    n_points: int
    rms_sample_px: float
    rms_line_px: float
    rms_px: float
    max_sample_px: float
    max_line_px: float
    max_px: float

    @classmethod
    def from_residuals(cls, ds: np.ndarray, dl: np.ndarray) -> "FitErrors":
        ds = np.asarray(ds, dtype=float).ravel()
        dl = np.asarray(dl, dtype=float).ravel()
        if ds.size == 0:
            nan = float("nan")
            return cls(0, nan, nan, nan, nan, nan, nan)
        radial = np.hypot(ds, dl)
        return cls(n_points=int(ds.size),
                   rms_sample_px=float(np.sqrt(np.mean(ds * ds))),
                   rms_line_px=float(np.sqrt(np.mean(dl * dl))),
                   rms_px=float(np.sqrt(np.mean(radial * radial))),
                   max_sample_px=float(np.max(np.abs(ds))),
                   max_line_px=float(np.max(np.abs(dl))),
                   max_px=float(np.max(radial)))

    def to_dict(self) -> Dict[str, Any]:
        return {"n_points": self.n_points,
                "rms_sample_px": self.rms_sample_px, "rms_line_px": self.rms_line_px, "rms_px": self.rms_px,
                "max_sample_px": self.max_sample_px, "max_line_px": self.max_line_px, "max_px": self.max_px}


@dataclass(frozen=True)
class FitReport:
    """How an RPC fit went (METHODS §3).

    Attributes
    ----------
    fit : errors on the fit points themselves.
    check : errors on independent check points (``None`` if none were given); for :func:`fit_rpc_from_model`
        the second grid offset by half a cell at intermediate heights.
    n_points : number of fit correspondences.
    iterations : ``(sample, line)`` number of linear solves (reweighting + Gauss-Newton) of the accepted fit.
    regularization : ``(sample, line)`` relative Tikhonov parameter actually used.
    elapsed_s : wall time of the whole call (including the model's localisations for ``fit_rpc_from_model``).
    model_roundtrip_max_px : largest ``project(localize(x)) - x`` of the source model on the check grid
        (``fit_rpc_from_model`` with a model that has ``project``); the check errors cannot be trusted below it.
    notes : anything the caller should know (single height fallback, dropped points, ...).
    """

    fit: FitErrors
    check: Optional[FitErrors]
    n_points: int
    iterations: Tuple[int, int]
    regularization: Tuple[float, float]
    elapsed_s: float
    model_roundtrip_max_px: Optional[float] = None
    notes: Tuple[str, ...] = ()

    @property
    def rms_px(self) -> float:
        """Planar RMS error on the check points if any, else on the fit points (px)."""
        return (self.check if self.check is not None else self.fit).rms_px

    @property
    def max_px(self) -> float:
        """Planar max error on the check points if any, else on the fit points (px)."""
        return (self.check if self.check is not None else self.fit).max_px

    def to_dict(self) -> Dict[str, Any]:
        """Plain JSON-serialisable dict."""
        return {"fit": self.fit.to_dict(),
                "check": None if self.check is None else self.check.to_dict(),
                "n_points": self.n_points,
                "iterations": {"sample": self.iterations[0], "line": self.iterations[1]},
                "regularization": {"sample": self.regularization[0], "line": self.regularization[1]},
                "elapsed_s": self.elapsed_s,
                "model_roundtrip_max_px": self.model_roundtrip_max_px,
                "notes": list(self.notes)}


# ---------------------------------------------------------------------------------------------- linear algebra
#: Points per chunk when the normal equations are accumulated (keeps the (40, chunk) block in cache).
_CHUNK = 8192


class _AxisDesign:
    """The design of one image axis, ``A = [u * m, v * m[1:]]`` (n, 39) with per-point ``u``, ``v`` and the
    (20, n) monomials ``Mt`` (term-major), never formed whole: its normal equations are accumulated over chunks
    of points (each chunk's block ``[A_c | b_c]^T`` in cache, one symmetric product); ``A d`` and ``A^T q`` are
    two products with ``Mt``."""

    def __init__(self, Mt: np.ndarray, u: np.ndarray, v: np.ndarray):
        self.Mt, self.u, self.v = Mt, u, v

    def normal(self, b: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """``(A^T A, A^T b)``."""
        Mt, u, v = self.Mt, self.u, self.v
        n = Mt.shape[1]
        block = np.empty((N_UNKNOWNS + 1, min(n, _CHUNK)))
        Gb = np.zeros((N_UNKNOWNS + 1, N_UNKNOWNS + 1))
        for s in range(0, n, _CHUNK):
            e = min(n, s + _CHUNK)
            B = block[:, :e - s]
            np.multiply(Mt[:, s:e], u[s:e], out=B[:20])
            np.multiply(Mt[1:, s:e], v[s:e], out=B[20:N_UNKNOWNS])
            B[N_UNKNOWNS] = b[s:e]
            Gb += B @ B.T
        return Gb[:N_UNKNOWNS, :N_UNKNOWNS], Gb[:N_UNKNOWNS, N_UNKNOWNS].copy()

    def dot(self, d: np.ndarray) -> np.ndarray:
        """``A d``."""
        t = np.stack([d[:20], np.concatenate([[0.0], d[20:]])]) @ self.Mt
        return self.u * t[0] + self.v * t[1]

    def tdot(self, q: np.ndarray) -> np.ndarray:
        """``A^T q``."""
        t = self.Mt @ np.stack([self.u * q, self.v * q], axis=1)
        return np.concatenate([t[:, 0], t[1:, 1]])

    def dense(self) -> np.ndarray:
        """``A`` itself (n, 39), for the unregularised QR solve only."""
        return np.hstack([(self.Mt * self.u).T, (self.Mt[1:] * self.v).T])


def _solve_regularised(G: np.ndarray, g: np.ndarray, A: _AxisDesign, b: np.ndarray, lam: float,
                       x0: Optional[np.ndarray] = None) -> np.ndarray:
    """Solve ``min ||A d - b||^2 + lam * sum_j G_jj (x0 + d)_j^2`` for the step ``d`` (``G = A^T A``, ``g = A^T b``).

    Columns are equilibrated (unit diagonal) so ``lam`` is relative and the conditioning is that of the
    correlation structure only; one step of iterative refinement against the unscaled residual recovers the
    accuracy the normal equations lose. All-zero columns (e.g. the H terms when every height is the same) are
    left at zero. ``lam == 0`` solves the plain least-squares problem by QR instead.
    """
    n = G.shape[0]
    diag = np.diag(G).copy()
    active = diag > 0.0
    d = np.zeros(n)
    if not np.any(active):
        return d
    c = np.sqrt(diag[active])
    xs0 = np.zeros(c.size) if x0 is None else x0[active] * c
    if lam == 0.0:
        As = A.dense()[:, active] / c
        Rb = sla.qr(np.column_stack([As, b]), mode="r", check_finite=False)[0]
        k = c.size
        ds = sla.solve_triangular(Rb[:k, :k], Rb[:k, k], check_finite=False)
        d[active] = ds / c
        return d
    Gs = G[np.ix_(active, active)] / np.outer(c, c)
    Gs[np.diag_indices_from(Gs)] += lam
    try:
        cf = sla.cho_factor(Gs, check_finite=False)
    except np.linalg.LinAlgError:
        raise _IllPosed() from None
    ds = sla.cho_solve(cf, g[active] / c - lam * xs0, check_finite=False)
    # Iterative refinement: the residual of the *regularised* normal equations, formed from A itself.
    d[active] = ds / c
    res = A.tdot(b - A.dot(d))[active] / c - lam * (xs0 + ds)
    ds = ds + sla.cho_solve(cf, res, check_finite=False)
    if not np.all(np.isfinite(ds)):
        raise _IllPosed()
    d[active] = ds / c
    return d


@lru_cache(maxsize=2)
def _domain_monomials(single_height: bool) -> np.ndarray:
    """(N, 20) monomials of a lattice over the slightly enlarged normalised cube (the denominator guard).

    With a single height the RPC only means something at H = 0, so the lattice is the plane H = 0.
    """
    g = np.linspace(-1.1, 1.1, 7)
    L, P, H = np.meshgrid(g, g, [0.0] if single_height else g, indexing="ij")
    m = np.ascontiguousarray(monomials(L, P, H).T)
    m.flags.writeable = False
    return m


def _fit_axis(Mt: np.ndarray, r: np.ndarray, lam: float, max_iter: int, guard_M: np.ndarray, abs_tol: float,
              first: Tuple[np.ndarray, np.ndarray]):
    """Fit one image axis ``r ~ (a.m) / (1 + b.m[1:])`` (``Mt`` the (20, n) monomials); returns (num(20),
    den(20), n_solves). ``first``: the normal equations of the first, unweighted, step (the same for every
    lambda of the ladder, :func:`_first_normals`).

    Raises ``_IllPosed`` if lambda is too small for this system (the caller moves up the ladder).
    """
    w = np.ones(r.size)
    x = np.zeros(N_UNKNOWNS)
    prev = math.inf
    solves = 0
    # Tao & Hu: linearised equations weighted by 1/D of the previous iterate (D = 1 at the start).
    for _ in range(max(1, max_iter)):
        A, bw = _AxisDesign(Mt, w, -r * w), r * w
        x = _solve_regularised(*(first if solves == 0 else A.normal(bw)), A, bw, lam)
        solves += 1
        N, D = _num_den(Mt, x)
        if not np.all(np.isfinite(D)) or np.min(np.abs(D)) < 1e-12:
            raise _IllPosed()
        w = 1.0 / D
        e = r - N * w
        rms = float(np.sqrt(np.mean(e * e)))
        if abs(prev - rms) <= _REL_TOL * rms + abs_tol:
            break
        prev = rms
    x, gn_solves = _gauss_newton(Mt, r, lam, x, w, e, rms, abs_tol)
    num = x[:20].copy()
    den = np.concatenate([[1.0], x[20:]])
    # Denominator guard over the fit points and the normalised domain: a near-zero denominator anywhere in
    # the validity cube makes the RPC explode there, whatever the fit residuals say.
    Dmin = min(float(np.min(den @ Mt)), float(np.min(guard_M @ den)))
    if not Dmin > _MIN_DENOMINATOR:
        raise _IllPosed()
    return num, den, solves + gn_solves


def _gauss_newton(Mt: np.ndarray, r: np.ndarray, lam: float, x: np.ndarray, w: np.ndarray, e: np.ndarray,
                  rms: float, abs_tol: float):
    """Gauss-Newton on the true residual ``r - N/D`` from the reweighting's ``x`` (``w = 1/D``, ``e`` its
    residual); the Tikhonov term stays on x itself (not on the step). Returns (x, solves)."""
    solves = 0
    for _ in range(_GN_STEPS):
        if rms <= abs_tol:
            break
        p = r - e  # current prediction N/D
        A = _AxisDesign(Mt, w, -p * w)
        dx = _solve_regularised(*A.normal(e), A, e, lam, x0=x)
        solves += 1
        xn = x + dx
        Nn, Dn = _num_den(Mt, xn)
        if not np.all(np.isfinite(Dn)) or np.min(np.abs(Dn)) < 1e-12:
            break
        en = r - Nn / Dn
        rms_n = float(np.sqrt(np.mean(en * en)))
        if not rms_n < rms * (1.0 + 1e-12):
            break
        improved = rms - rms_n
        x, w, e, rms = xn, 1.0 / Dn, en, rms_n
        if improved <= _REL_TOL * rms + abs_tol:
            break
    return x, solves


def _num_den(Mt: np.ndarray, x: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Numerator ``a.m`` and denominator ``1 + b.m[1:]`` of the unknowns ``x = (a, b)`` at every point."""
    t = np.stack([x[:20], np.concatenate([[1.0], x[20:]])]) @ Mt
    return t[0], t[1]


def _first_normals(Mt: np.ndarray, r: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Normal equations of the first reweighting step (``w = 1``): computed once per axis for the whole ladder."""
    return _AxisDesign(Mt, np.ones(r.size), -r).normal(r)


# ---------------------------------------------------------------------------------------------- normalisation
def _offset_scale(values: np.ndarray) -> Tuple[float, float]:
    """Vendors' choice: offset = centre of the range, scale = half the range."""
    lo, hi = float(np.min(values)), float(np.max(values))
    return 0.5 * (lo + hi), 0.5 * (hi - lo)


def _wrap180(dlon: np.ndarray) -> np.ndarray:
    return np.where(np.abs(dlon) > 180.0, (dlon + 180.0) % 360.0 - 180.0, dlon)


def _lon_offset_scale(lon: np.ndarray) -> Tuple[float, float]:
    """Longitude offset/scale, across the antimeridian too (RPCModel compares longitudes modulo 360)."""
    off, scale = _offset_scale(lon)
    if 2.0 * scale > 180.0:
        off, scale = _offset_scale(lon % 360.0)
        off = (off + 180.0) % 360.0 - 180.0
        scale = float(np.max(np.abs(_wrap180(lon - off))))
    return off, scale


# ---------------------------------------------------------------------------------------------- fit_rpc
def _as_points(name: str, values, n: Optional[int] = None) -> np.ndarray:
    arr = np.asarray(values, dtype=float).ravel()
    if n is not None and arr.size != n:
        raise GCPError(f"fit_rpc: {name} has {arr.size} values but lon has {n}; pass arrays of equal length")
    return arr


def _check_points(check) -> Tuple[np.ndarray, ...]:
    if check is None:
        return None
    if isinstance(check, dict):
        check = [check[k] for k in ("lon", "lat", "h", "sample", "line")]
    if len(check) != 5:
        raise GCPError("fit_rpc: check must be (lon, lat, h, sample, line) arrays")
    lon = _as_points("check lon", check[0])
    pts = (lon,) + tuple(_as_points(f"check {k}", v, lon.size) for k, v in zip(("lat", "h", "sample", "line"),
                                                                                check[1:]))
    ok = np.all(np.isfinite(np.vstack(pts)), axis=0)
    if not np.all(ok):
        raise DegenerateGeometryError(f"fit_rpc: {int(np.count_nonzero(~ok))} check points are not finite "
                                      "(NaN/inf); remove them")
    return pts


def fit_rpc(lon, lat, h, sample, line, *, check=None, regularization="auto", max_iter: int = 20,
            pixel_convention: str = "gdal",
            progress: Optional[ProgressCallback] = None) -> Tuple[RPCModel, FitReport]:
    """Fit an RPC00B model to ground <-> image correspondences (METHODS §3; Tao & Hu 2001).

    Parameters
    ----------
    lon, lat, h : array_like
        Ground points: degrees WGS84 and ellipsoidal height (m). For a terrain-independent fit use several
        height layers (>= 6) over the scene's height range; with a single height the fit falls back to an RPC
        with all H terms exactly zero (see Notes).
    sample, line : array_like
        Image coordinates of the same points, GDAL convention (centre of the first pixel at 0.5, 0.5) unless
        ``pixel_convention="rpc"``.
    check : (lon, lat, h, sample, line) arrays or dict with those keys, optional
        Independent check points; their errors go to ``FitReport.check``.
    regularization : "auto" or float
        Relative Tikhonov parameter (penalty ``lambda * G_jj * x_j**2``, ``G`` the normal matrix, i.e. relative to
        its trace per unknown). ``"auto"`` takes the smallest of :data:`AUTO_REGULARIZATION` that gives a
        well-posed system and a denominator > 0.1 over the normalised domain. ``0`` solves by QR without
        regularisation.
    max_iter : int
        Maximum number of reweighting iterations per axis (convergence is usually reached in 2-5).
    progress : callable(fraction, message), optional
        Progress callback; raising :class:`~gdal_gf4cal.errors.CancelledError` from it cancels.

    Returns
    -------
    (RPCModel, FitReport)
        Offsets are the centres and scales the half ranges of the data (``LINE_OFF``/``SAMP_OFF`` in the raw RPC00B
        convention, as in files); errors in the report are in pixels.

    Raises
    ------
    DegenerateGeometryError
        Fewer than 39 points, non-finite values, points on a line (planimetrically degenerate) or constant
        image coordinates, or no regularisation giving a usable denominator.
    GCPError
        Arrays of different lengths.

    Notes
    -----
    Single height: when every ``h`` is equal the H columns of the design are identically zero; they are left out
    of the solve, so every coefficient with an H factor is exactly 0, ``HEIGHT_OFF`` is that height and
    ``HEIGHT_SCALE`` is 1 m (any non-zero value gives the same model). The RPC is then valid at that height only;
    ``FitReport.notes`` says so.
    """
    t0 = time.perf_counter()
    lon = _as_points("lon", lon)
    n = lon.size
    lat, h, sample, line = (_as_points(k, v, n) for k, v in
                            (("lat", lat), ("h", h), ("sample", sample), ("line", line)))
    if pixel_convention not in ("gdal", "rpc"):
        raise ValueError(f"pixel_convention must be 'gdal' or 'rpc', not {pixel_convention!r}")
    shift = GDAL_PIXEL_OFFSET if pixel_convention == "gdal" else 0.0
    check_pts = _check_points(check)
    _check_fit_points(lon, lat, h, sample, line)
    ladder = _regularization_ladder(regularization)
    (samp_off, samp_scale, rs), (line_off, line_scale, rl) = _image_normalisation(sample - shift, line - shift)
    ground, M, notes = _ground_monomials(lon, lat, h)
    guard = _domain_monomials(ground["single_height"])
    (sn, sd, s_it, s_lam), (ln, ld, l_it, l_lam) = (
        _fit_axis_on_ladder(M, r, ladder, max_iter, guard, scale, axis, progress, 0.05 + 0.45 * k)
        for k, (axis, r, scale) in enumerate((("sample", rs, samp_scale), ("line", rl, line_scale))))
    rpc = RPCModel(line_off=line_off, samp_off=samp_off, lat_off=ground["lat_off"], long_off=ground["long_off"],
                   height_off=ground["height_off"], line_scale=line_scale, samp_scale=samp_scale,
                   lat_scale=ground["lat_scale"], long_scale=ground["long_scale"],
                   height_scale=ground["height_scale"], line_num=ln, line_den=ld, samp_num=sn, samp_den=sd)
    report(progress, 0.95, "checking the fitted RPC")
    fit_err = _errors(rpc, (lon, lat, h, sample, line), pixel_convention)
    check_err = None if check_pts is None else _errors(rpc, check_pts, pixel_convention)
    report(progress, 1.0, "RPC fitted")
    rep = FitReport(fit=fit_err, check=check_err, n_points=n, iterations=(s_it, l_it),
                    regularization=(s_lam, l_lam), elapsed_s=time.perf_counter() - t0, notes=tuple(notes))
    return rpc, rep


def _errors(rpc: RPCModel, pts, pixel_convention: str = "gdal") -> FitErrors:
    """Image errors of ``rpc`` at ``pts = (lon, lat, h, sample, line)``."""
    lon, lat, h, sample, line = pts
    ps, pl = rpc.project(lon, lat, h, pixel_convention=pixel_convention)
    return FitErrors.from_residuals(sample - ps, line - pl)


def _image_normalisation(raw_s: np.ndarray, raw_l: np.ndarray):
    """``(offset, scale, normalised values)`` of the sample and of the line (raw RPC00B convention)."""
    samp_off, samp_scale = _offset_scale(raw_s)
    line_off, line_scale = _offset_scale(raw_l)
    if samp_scale == 0.0 or line_scale == 0.0:
        raise DegenerateGeometryError("fit_rpc: every point has the same "
                                      f"{'sample' if samp_scale == 0.0 else 'line'}; spread the points over the "
                                      "image")
    return ((samp_off, samp_scale, (raw_s - samp_off) / samp_scale),
            (line_off, line_scale, (raw_l - line_off) / line_scale))


def _check_fit_points(lon, lat, h, sample, line) -> None:
    """Refuse non-finite correspondences and fewer than :data:`N_UNKNOWNS` of them."""
    n = lon.size
    finite = np.isfinite(lon) & np.isfinite(lat) & np.isfinite(h) & np.isfinite(sample) & np.isfinite(line)
    if not np.all(finite):
        raise DegenerateGeometryError(f"fit_rpc: {int(np.count_nonzero(~finite))} of {n} correspondences are not "
                                      "finite (NaN/inf); remove them before fitting")
    if n < N_UNKNOWNS:
        raise DegenerateGeometryError(f"fit_rpc: {n} correspondences cannot determine the {N_UNKNOWNS} unknowns "
                                      f"per image axis; give at least {N_UNKNOWNS} (a grid of >= 20x20 x 6 heights "
                                      "is the norm)")


def _regularization_ladder(regularization) -> Tuple[float, ...]:
    """The relative Tikhonov parameters to try, smallest first: the auto ladder or the one value given."""
    if isinstance(regularization, str):
        if regularization != "auto":
            raise ValueError(f"regularization must be 'auto' or a number >= 0, not {regularization!r}")
        return AUTO_REGULARIZATION
    lam = float(regularization)
    if not (lam >= 0.0 and math.isfinite(lam)):
        raise ValueError(f"regularization must be 'auto' or a number >= 0, not {regularization!r}")
    return (lam,)


def _ground_monomials(lon: np.ndarray, lat: np.ndarray, h: np.ndarray):
    """Ground offsets/scales (dict, with ``single_height``), the (20, n) normalised monomials and notes.

    Refuses a constant longitude or latitude and points on a line (the cross terms are then undetermined).
    """
    long_off, long_scale = _lon_offset_scale(lon)
    lat_off, lat_scale = _offset_scale(lat)
    height_off, height_scale = _offset_scale(h)
    notes = []
    if long_scale == 0.0 or lat_scale == 0.0:
        raise DegenerateGeometryError("fit_rpc: every point has the same "
                                      f"{'longitude' if long_scale == 0.0 else 'latitude'}; spread the points "
                                      "over the scene")
    single_height = height_scale == 0.0
    if single_height:
        height_scale = 1.0
        notes.append(f"single height {height_off:g} m: H terms fixed at 0, the RPC is valid at that height only")
    L = _wrap180(lon - long_off) / long_scale
    P = (lat - lat_off) / lat_scale
    H = (h - height_off) / height_scale
    # Planimetric spread: points on a line (or a curve close to one) leave the cross terms undetermined.
    sv = np.linalg.svd(np.column_stack([L - L.mean(), P - P.mean()]), compute_uv=False)
    if not sv[-1] > 1e-6 * sv[0]:
        raise DegenerateGeometryError("fit_rpc: the ground points lie on a line; spread them over the scene "
                                      "(a grid over the whole image)")
    ground = {"long_off": long_off, "long_scale": long_scale, "lat_off": lat_off, "lat_scale": lat_scale,
              "height_off": height_off, "height_scale": height_scale, "single_height": single_height}
    return ground, monomials(L, P, H), notes


def _fit_axis_on_ladder(M: np.ndarray, r: np.ndarray, ladder: Sequence[float], max_iter: int, guard: np.ndarray,
                        scale: float, axis: str, progress: Optional[ProgressCallback], fraction: float):
    """:func:`_fit_axis` with the smallest lambda of the ladder that works; returns (num, den, solves, lambda)."""
    report(progress, fraction, f"fitting the {axis} polynomials")
    first = _first_normals(M, r)
    for lam in ladder:
        try:
            num, den, solves = _fit_axis(M, r, lam, max_iter, guard, _ABS_TOL_PX / scale, first)
            return num, den, solves, lam
        except _IllPosed:
            continue
    what = ("a larger regularization or 'auto'" if len(ladder) == 1 else
            "more points spread over the image and >= 6 height layers")
    raise DegenerateGeometryError(f"fit_rpc: the {axis} RPC is undetermined by these points (singular system "
                                  f"or a denominator near zero); use {what}")


# ---------------------------------------------------------------------------------------------- from a model
def _grid_axis(start: float, length: float, n: int, margin: float) -> np.ndarray:
    return np.linspace(start - margin * length, start + (1.0 + margin) * length, n)


def _midpoints(v: np.ndarray) -> np.ndarray:
    return 0.5 * (v[1:] + v[:-1]) if v.size > 1 else v.copy()


def _localize_grid(model, xs: np.ndarray, ys: np.ndarray, heights: np.ndarray,
                   progress: Optional[ProgressCallback], what: str, notes: list):
    """Localise the grid ``xs x ys`` at every height: (lon, lat, h, sample, line); a note for dropped points."""
    S, Lg = np.meshgrid(xs, ys)
    pts, n_bad, n_all = _localize_layers(model, S, Lg, heights, progress, what)
    if n_bad:
        notes.append(f"{n_bad} of {n_all} {what} grid points could not be localised by the model and were dropped")
    return pts


def _localize_layers(model, S: np.ndarray, Lg: np.ndarray, heights: np.ndarray,
                     progress: Optional[ProgressCallback], what: str):
    """Localise an image grid at every height; returns flat (lon, lat, h, sample, line) of the finite points."""
    out = []
    for i, hv in enumerate(heights):
        report(progress, i / len(heights), f"localising the {what} grid at {hv:.0f} m")
        lon, lat = model.localize(S, Lg, np.full(S.shape, float(hv)))
        out.append((np.asarray(lon, dtype=float).ravel(), np.asarray(lat, dtype=float).ravel(),
                    np.full(S.size, float(hv)), S.ravel(), Lg.ravel()))
    pts = [np.concatenate(c) for c in zip(*out)]
    ok = np.isfinite(pts[0]) & np.isfinite(pts[1])
    return [p[ok] for p in pts], int(np.count_nonzero(~ok)), ok.size


def refit_numerators(rpc: RPCModel, lon, lat, h, sample, line, *, pixel_convention: str = "gdal") -> RPCModel:
    """``rpc`` with its two numerators refitted to ground <-> image correspondences, its offsets, scales and
    denominators kept: a small image-space correction carried into the RPC (the pan-MS approximate RPC).

    With the denominators fixed the image error ``N / D - t`` is linear in the 20 numerator coefficients: one
    weighted least-squares solve per axis (rows ``m / D``), no iteration and no pole to chase. A free rational
    refit (:func:`fit_rpc`) of a field with steps (sub-CCD edges) moves its denominators to fit them; whether
    it stays above the guard then depends on rounding (the BLAS kernel), and the result with it.

    Raises :class:`~gdal_gf4cal.errors.DegenerateGeometryError` when the points do not determine the numerators
    (condition number, through :func:`~gdal_gf4cal.estimation.weighted_lsq`).
    """
    lon = _as_points("lon", lon)
    lat, h, sample, line = (_as_points(k, v, lon.size) for k, v in
                            (("lat", lat), ("h", h), ("sample", sample), ("line", line)))
    shift = GDAL_PIXEL_OFFSET if pixel_convention == "gdal" else 0.0
    M = monomials(*rpc.normalise_ground(lon, lat, h))                     # (20, n)
    num = {}
    for axis, values, off, scale, den in (("samp", sample, rpc.samp_off, rpc.samp_scale, rpc.samp_den),
                                          ("line", line, rpc.line_off, rpc.line_scale, rpc.line_den)):
        D = den @ M
        if not np.all(np.abs(D) > 1e-12):
            raise DegenerateGeometryError(f"refit_numerators: the RPC's {axis} denominator vanishes at a point")
        est = weighted_lsq((M / D).T, (values - shift - off) / scale, hint=f"the {axis} numerator refit")
        num[f"{axis}_num"] = est.x
    return rpc.replace(**num)


def fit_rpc_from_model(model, *, size: Optional[Sequence[float]] = None, window: Optional[Sequence[float]] = None,
                       height_range: Optional[Sequence[float]] = None, grid: Sequence[int] = (21, 21),
                       n_layers: int = 7, margin: float = 0.0, height_margin: float = 0.1,
                       regularization="auto", max_iter: int = 20,
                       progress: Optional[ProgressCallback] = None) -> Tuple[RPCModel, FitReport]:
    """Terrain-independent RPC of any sensor model (METHODS §3; Tao & Hu 2001).

    A regular grid of ``grid = (n_samples, n_lines)`` image points times ``n_layers`` heights evenly spread over
    ``height_range`` is localised with ``model.localize``; :func:`fit_rpc` fits the RPC to those points; the fit is
    checked on a second grid offset by half a cell, at the heights half-way between the layers.

    Parameters
    ----------
    model : object
        Anything with a vectorised ``localize(sample, line, h) -> (lon, lat)`` in GDAL's pixel convention
        (a rigorous sensor model, a simulator, an :class:`~gdal_gf4cal.rpc.RPCModel`). If it also has
        ``project(lon, lat, h) -> (sample, line)``, the model's own round-trip error on the check grid is reported.
    size : (width, height), optional
        Image size in pixels; the grid covers ``[0, width] x [0, height]`` (pixel edges, GDAL convention).
    window : (x_off, y_off, width, height), optional
        Instead of ``size``: a sub-window; the RPC stays in the model's image coordinates. If neither is given,
        ``model.size`` is used when the model has it.
    height_range : (h_min, h_max), optional
        Ellipsoidal heights (m) the RPC must cover; defaults to ``model.height_range`` if the model has one.
        ``h_min == h_max`` gives a single-height RPC (all H terms 0, see :func:`fit_rpc`).
    grid : (int, int)
        Fit grid nodes along sample and line, at least 20 each (METHODS §3).
    n_layers : int
        Height layers, at least 6 (METHODS §3).
    margin : float
        Fraction of the image size added on each side of the fitted (and checked) image domain. 0 by default, as
        vendors do: a margin costs accuracy inside the image for strongly distorted sensors.
    height_margin : float
        Fraction of the height range added at each end of the layers (default 0.1), so that DEM heights a little
        outside ``height_range`` are interpolated, not extrapolated; ``HEIGHT_OFF ± HEIGHT_SCALE`` covers the layers.
    regularization, max_iter, progress : see :func:`fit_rpc`.

    Returns
    -------
    (RPCModel, FitReport)
        ``SAMP_OFF``/``LINE_OFF`` are the window centre (raw RPC00B convention) and the scales half its size, as
        vendors write them; ground offsets/scales are the centre/half range of the fit points; the height scale
        covers every layer.

    Raises
    ------
    DegenerateGeometryError
        Grid or layers below the METHODS §3 minimum, an empty window, or too few points localised.
    """
    t0 = time.perf_counter()
    x0, y0, width, height = _image_window(model, size, window)
    gx, gy = _grid_nodes(grid, margin, height_margin)
    layers = _height_layers(model, height_range, n_layers, height_margin)
    check_layers = _midpoints(layers)

    xs = _grid_axis(x0, width, gx, margin)
    ys = _grid_axis(y0, height, gy, margin)
    notes = []
    fit_pts = _localize_grid(model, xs, ys, layers, scaled(progress, 0.0, 0.45), "fit", notes)
    check_pts = _localize_grid(model, _midpoints(xs), _midpoints(ys), check_layers, scaled(progress, 0.45, 0.8),
                               "check", notes)
    rpc, rep = fit_rpc(*fit_pts, check=check_pts, regularization=regularization,
                       max_iter=max_iter, progress=scaled(progress, 0.8, 0.97))
    # Vendors' image normalisation: the window centre and half size (the fit used the data's extent, which
    # includes the margin). An exact re-expression of the same rational functions, not a refit.
    rpc = _renormalise_image(rpc, x0 + 0.5 * width - GDAL_PIXEL_OFFSET, 0.5 * width,
                             y0 + 0.5 * height - GDAL_PIXEL_OFFSET, 0.5 * height)
    roundtrip = _model_roundtrip_max_px(model, check_pts)
    # Errors are recomputed with the final (renormalised) RPC: the report describes exactly what is returned.
    fit_err = _errors(rpc, fit_pts)
    check_err = _errors(rpc, check_pts)
    report(progress, 1.0, "RPC fitted")
    rep = FitReport(fit=fit_err, check=check_err, n_points=rep.n_points, iterations=rep.iterations,
                    regularization=rep.regularization, elapsed_s=time.perf_counter() - t0,
                    model_roundtrip_max_px=roundtrip, notes=tuple(notes) + rep.notes)
    return rpc, rep


def _grid_nodes(grid, margin: float, height_margin: float) -> Tuple[int, int]:
    """The fit grid's (samples, lines), at least 20 each (METHODS §3); the margins must be >= 0."""
    gx, gy = (int(v) for v in grid)
    if gx < 20 or gy < 20:
        raise DegenerateGeometryError(f"fit_rpc_from_model: grid {gx}x{gy} is too coarse; use at least 20x20 "
                                      "(METHODS §3)")
    if not (margin >= 0.0 and height_margin >= 0.0):
        raise ValueError(f"fit_rpc_from_model: margin and height_margin must be >= 0, not {margin!r}, "
                         f"{height_margin!r}")
    return gx, gy


def _model_roundtrip_max_px(model, check_pts) -> Optional[float]:
    """Largest ``project(localize(x)) - x`` of the model on the check grid (None if it cannot project)."""
    clon, clat, ch, cs, cl = check_pts
    if not (callable(getattr(model, "project", None)) and clon.size):
        return None
    ps, pl = model.project(clon, clat, ch)
    return float(np.nanmax(np.hypot(np.asarray(ps, dtype=float) - cs, np.asarray(pl, dtype=float) - cl)))


def _image_window(model, size, window) -> Tuple[float, float, float, float]:
    """The fitted image window (x_off, y_off, width, height) from ``size``, ``window`` or ``model.size``."""
    if window is not None and size is not None:
        raise ValueError("fit_rpc_from_model: give size or window, not both")
    if window is None:
        if size is None:
            size = getattr(model, "size", None)
            if size is None:
                raise ValueError("fit_rpc_from_model: give size=(width, height) or window=(x_off, y_off, width, "
                                 "height); the model has no 'size'")
        window = (0.0, 0.0, float(size[0]), float(size[1]))
    x0, y0, width, height = (float(v) for v in window)
    if not (width > 0 and height > 0 and all(map(math.isfinite, (x0, y0, width, height)))):
        raise DegenerateGeometryError(f"fit_rpc_from_model: empty or invalid image window {tuple(window)}")
    return x0, y0, width, height


def _height_layers(model, height_range, n_layers: int, height_margin: float) -> np.ndarray:
    """The fit heights: ``n_layers`` over ``height_range`` (or ``model.height_range``) widened by the margin."""
    if height_range is None:
        height_range = getattr(model, "height_range", None)
        if height_range is None:
            raise ValueError("fit_rpc_from_model: give height_range=(h_min, h_max) in metres")
    hmin, hmax = (float(v) for v in height_range)
    if not (math.isfinite(hmin) and math.isfinite(hmax) and hmin <= hmax):
        raise ValueError(f"fit_rpc_from_model: height_range must be finite (h_min, h_max) with h_min <= h_max, "
                         f"not {tuple(height_range)}")
    if hmax > hmin:
        if int(n_layers) < 6:
            raise DegenerateGeometryError(f"fit_rpc_from_model: {n_layers} height layers are too few; use at least "
                                          "6 (METHODS §3)")
        return _grid_axis(hmin, hmax - hmin, int(n_layers), height_margin)
    return np.array([hmin])


def _renormalise_image(rpc: RPCModel, samp_off: float, samp_scale: float, line_off: float,
                       line_scale: float) -> RPCModel:
    """Exactly re-express an RPC with other image offsets/scales (raw convention).

    ``x' = (x*s + o - o') / s'`` is affine in the normalised ratio, so ``num' = (s*num + (o - o')*den) / s'``
    with the denominator unchanged: no refit, no loss.
    """
    def redo(num, den, off, scale, new_off, new_scale):
        return (scale * np.asarray(num) + (off - new_off) * np.asarray(den)) / new_scale
    return rpc.replace(samp_num=redo(rpc.samp_num, rpc.samp_den, rpc.samp_off, rpc.samp_scale, samp_off, samp_scale),
                       line_num=redo(rpc.line_num, rpc.line_den, rpc.line_off, rpc.line_scale, line_off, line_scale),
                       samp_off=samp_off, samp_scale=samp_scale, line_off=line_off, line_scale=line_scale)
