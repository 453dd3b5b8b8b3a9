"""The RPC00B rational polynomial camera model (METHODS §1).

Pixel convention
----------------
Every public function takes and returns image coordinates in **GDAL's convention**: the centre of the first
pixel is at ``(0.5, 0.5)``. The RPC00B coefficients themselves (``LINE_OFF``/``SAMP_OFF``) use the raw convention
in which the centre of the first pixel is ``(0, 0)``; so ``gdal = raw + 0.5``. Pass ``pixel_convention="rpc"`` to
work in the raw convention instead.

Ground coordinates are geodetic longitude, latitude (degrees, WGS84) and ellipsoidal height (m), always in the
order ``(lon, lat, h)``.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Dict, Optional, Tuple, Union

import numpy as np

from .errors import RPCFormatError

log = logging.getLogger(__name__)

#: Offset between GDAL's pixel convention and the raw RPC00B convention (gdal = raw + GDAL_PIXEL_OFFSET).
GDAL_PIXEL_OFFSET = 0.5

#: The 20 terms in RPC00B order (P = normalised latitude, L = longitude, H = height).
TERMS = ("1", "L", "P", "H", "LP", "LH", "PH", "L2", "P2", "H2", "PLH", "L3", "LP2", "LH2", "L2P", "P3", "PH2",
         "L2H", "P2H", "H3")

_SCALARS = ("line_off", "samp_off", "lat_off", "long_off", "height_off",
            "line_scale", "samp_scale", "lat_scale", "long_scale", "height_scale")
_GDAL_SCALAR_KEYS = {name: name.upper() for name in _SCALARS}
_GDAL_COEFF_KEYS = {"line_num": "LINE_NUM_COEFF", "line_den": "LINE_DEN_COEFF",
                    "samp_num": "SAMP_NUM_COEFF", "samp_den": "SAMP_DEN_COEFF"}
_GDAL_OPTIONAL = {"err_bias": "ERR_BIAS", "err_rand": "ERR_RAND", "min_long": "MIN_LONG", "min_lat": "MIN_LAT",
                  "max_long": "MAX_LONG", "max_lat": "MAX_LAT"}

#: Exponents (of L, P, H) of the 20 terms, in RPC00B order.
_EXPONENTS = ((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1), (2, 0, 0), (0, 2, 0),
              (0, 0, 2), (1, 1, 1), (3, 0, 0), (1, 2, 0), (1, 0, 2), (2, 1, 0), (0, 3, 0), (0, 1, 2), (2, 0, 1),
              (0, 2, 1), (0, 0, 3))


def _derivative_matrix(axis: int) -> np.ndarray:
    """D (20, 20) with d(term_j)/d(axis) = sum_k D[j, k] term_k: derivatives stay in the 20-term basis."""
    index = {e: k for k, e in enumerate(_EXPONENTS)}
    D = np.zeros((20, 20))
    for j, e in enumerate(_EXPONENTS):
        if e[axis]:
            lowered = list(e)
            lowered[axis] -= 1
            D[j, index[tuple(lowered)]] = e[axis]
    return D


#: d/dL, d/dP, d/dH as (20, 20) basis maps: coefficients of the derivative polynomial = coeffs @ D.
DERIVATIVE_MATRICES = tuple(_derivative_matrix(a) for a in range(3))

#: Chunk of points processed at once: keeps the (20, chunk) monomial block in cache.
_CHUNK = 16384

ArrayLike = Union[float, np.ndarray]


def monomials(L: np.ndarray, P: np.ndarray, H: np.ndarray) -> np.ndarray:
    """The 20 RPC00B monomials of normalised (L, P, H), shape ``(20, N)`` (term-major, METHODS §1).

    Term-major layout makes each row a contiguous vector, so ``coeffs @ monomials(...)`` evaluates several
    polynomials at once with one BLAS call. Use ``.T`` for a point-major ``(N, 20)`` design matrix.
    """
    L = np.asarray(L, dtype=float).ravel()
    P = np.asarray(P, dtype=float).ravel()
    H = np.asarray(H, dtype=float).ravel()
    m = np.empty((20, L.size))
    m[0] = 1.0
    m[1] = L
    m[2] = P
    m[3] = H
    np.multiply(L, P, out=m[4])
    np.multiply(L, H, out=m[5])
    np.multiply(P, H, out=m[6])
    np.multiply(L, L, out=m[7])
    np.multiply(P, P, out=m[8])
    np.multiply(H, H, out=m[9])
    np.multiply(m[4], H, out=m[10])      # PLH
    np.multiply(m[7], L, out=m[11])      # L3
    np.multiply(m[8], L, out=m[12])      # LP2
    np.multiply(m[9], L, out=m[13])      # LH2
    np.multiply(m[7], P, out=m[14])      # L2P
    np.multiply(m[8], P, out=m[15])      # P3
    np.multiply(m[9], P, out=m[16])      # PH2
    np.multiply(m[7], H, out=m[17])      # L2H
    np.multiply(m[8], H, out=m[18])      # P2H
    np.multiply(m[9], H, out=m[19])      # H3
    return m


def monomial_derivatives(L: np.ndarray, P: np.ndarray, H: np.ndarray, with_h: bool = True):
    """Partial derivatives of :func:`monomials` with respect to L, P and H, each ``(20, N)``.

    With ``with_h=False`` the third item is ``None`` (saves a third of the work when H is fixed).
    """
    L = np.asarray(L, dtype=float).ravel()
    P = np.asarray(P, dtype=float).ravel()
    H = np.asarray(H, dtype=float).ravel()
    n = L.size
    one, zero = np.ones(n), np.zeros(n)
    LL, PP, HH, LP, LH, PH = L * L, P * P, H * H, L * P, L * H, P * H
    dL = np.stack([zero, one, zero, zero, P, H, zero, 2 * L, zero, zero, PH, 3 * LL, PP, HH, 2 * LP, zero, zero,
                   2 * LH, zero, zero])
    dP = np.stack([zero, zero, one, zero, L, zero, H, zero, 2 * P, zero, LH, zero, 2 * LP, zero, LL, 3 * PP, HH,
                   zero, 2 * PH, zero])
    if not with_h:
        return dL, dP, None
    dH = np.stack([zero, zero, zero, one, zero, L, P, zero, zero, 2 * H, LP, zero, zero, 2 * LH, zero, zero, 2 * PH,
                   LL, PP, 3 * HH])
    return dL, dP, dH


def _as_float_array(x) -> np.ndarray:
    return np.asarray(x, dtype=float)


def _shape_out(values: np.ndarray, shape: tuple):
    """Return a scalar for scalar input, else reshape to the broadcast input shape."""
    if shape == ():
        return float(values.reshape(-1)[0])
    return values.reshape(shape)


@dataclass(frozen=True)
class LocalizationStats:
    """How a vectorised localisation went: number of points and of points that did not converge (NaN)."""

    n_points: int
    n_failed: int
    max_iterations: int


@dataclass(frozen=True, eq=False)
class RPCModel:
    """An RPC00B model (METHODS §1), immutable.

    ``line_off``/``samp_off`` are stored in the raw RPC00B convention (as in the files); :meth:`project` and
    :meth:`localize` speak GDAL's pixel convention unless ``pixel_convention="rpc"``.
    Build one with :meth:`from_file`, :meth:`from_gdal_metadata` or directly from coefficients.
    """

    line_off: float
    samp_off: float
    lat_off: float
    long_off: float
    height_off: float
    line_scale: float
    samp_scale: float
    lat_scale: float
    long_scale: float
    height_scale: float
    line_num: np.ndarray
    line_den: np.ndarray
    samp_num: np.ndarray
    samp_den: np.ndarray
    err_bias: Optional[float] = None
    err_rand: Optional[float] = None
    min_long: Optional[float] = None
    min_lat: Optional[float] = None
    max_long: Optional[float] = None
    max_lat: Optional[float] = None
    source: Optional[str] = field(default=None, compare=False)

    def __post_init__(self):
        for name in _SCALARS:
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise RPCFormatError(f"RPC{self._where()}: {name.upper()} is not a finite number ({value!r})")
            object.__setattr__(self, name, value)
        for name in ("line_scale", "samp_scale", "lat_scale", "long_scale", "height_scale"):
            if getattr(self, name) == 0.0:
                raise RPCFormatError(f"RPC{self._where()}: {name.upper()} is zero; the RPC cannot be normalised")
        for name in _GDAL_COEFF_KEYS:
            arr = np.array(getattr(self, name), dtype=float).ravel()
            if arr.size != 20:
                raise RPCFormatError(f"RPC{self._where()}: {_GDAL_COEFF_KEYS[name]} has {arr.size} coefficients, "
                                     "20 are needed")
            if not np.all(np.isfinite(arr)):
                raise RPCFormatError(f"RPC{self._where()}: {_GDAL_COEFF_KEYS[name]} contains a non-finite value")
            arr.flags.writeable = False
            object.__setattr__(self, name, arr)
        if not (np.any(self.line_den) and np.any(self.samp_den)):
            raise RPCFormatError(f"RPC{self._where()}: a denominator is all zeros")

    def _where(self) -> str:
        return f" in {self.source}" if self.source else ""

    # ------------------------------------------------------------------ construction / serialisation
    @classmethod
    def from_gdal_metadata(cls, metadata: Dict[str, str], source: Optional[str] = None) -> "RPCModel":
        """Build from a GDAL ``RPC`` metadata-domain dict (``ds.GetMetadata('RPC')``).

        Raises :class:`RPCFormatError` naming the missing or malformed key.
        """
        where = f" in {source}" if source else ""
        if not metadata:
            raise RPCFormatError(f"no RPC metadata{where}")
        md = {str(k).upper(): v for k, v in metadata.items()}
        kwargs = {}
        for name, key in _GDAL_SCALAR_KEYS.items():
            if key not in md:
                raise RPCFormatError(f"RPC{where}: missing key {key}")
            kwargs[name] = _parse_number(md[key], key, where)
        for name, key in _GDAL_COEFF_KEYS.items():
            if key not in md:
                raise RPCFormatError(f"RPC{where}: missing key {key}")
            text = md[key]
            items = text.replace(",", " ").split() if isinstance(text, str) else list(text)
            values = [_parse_number(v, key, where) for v in items]
            if len(values) != 20:
                raise RPCFormatError(f"RPC{where}: {key} has {len(values)} coefficients, 20 are needed")
            kwargs[name] = np.array(values)
        for name, key in _GDAL_OPTIONAL.items():
            if key in md and str(md[key]).strip() not in ("", "nan"):
                try:
                    kwargs[name] = float(str(md[key]).split()[0])
                except ValueError:
                    pass  # optional informative keys: ignore garbage rather than refuse the RPC
        return cls(source=source, **kwargs)

    @classmethod
    def from_file(cls, path) -> "RPCModel":
        """Read an RPC from an image (TIFF tags, .RPB, _RPC.TXT, NITF) or a standalone sidecar / vendor XML / JSON.

        The format is detected by content as well as by name (see :mod:`gdal_gf4cal.rpc_io`).
        """
        from .rpc_io import read_rpc_metadata
        return cls.from_gdal_metadata(read_rpc_metadata(path), source=str(path))

    def to_gdal_metadata(self) -> Dict[str, str]:
        """The GDAL ``RPC`` metadata-domain dict, numbers written with 17 significant digits."""
        md = {key: _fmt(getattr(self, name)) for name, key in _GDAL_SCALAR_KEYS.items()}
        for name, key in _GDAL_COEFF_KEYS.items():
            md[key] = " ".join(_fmt(v) for v in getattr(self, name))
        for name, key in _GDAL_OPTIONAL.items():
            value = getattr(self, name)
            if value is not None:
                md[key] = _fmt(value)
        return md

    def replace(self, **changes) -> "RPCModel":
        """A copy with some fields changed (``dataclasses.replace``); caches are not carried over."""
        return dataclasses.replace(self, **changes)

    def write_rpb(self, path, overwrite: bool = False) -> "Path":
        """Write a ``.RPB`` sidecar atomically (see :func:`gdal_gf4cal.rpc_io.write_rpb`)."""
        from .rpc_io import write_rpb
        return write_rpb(self, path, overwrite=overwrite)

    def write_rpc_txt(self, path, overwrite: bool = False) -> "Path":
        """Write a ``_RPC.TXT`` sidecar atomically (see :func:`gdal_gf4cal.rpc_io.write_rpc_txt`)."""
        from .rpc_io import write_rpc_txt
        return write_rpc_txt(self, path, overwrite=overwrite)

    # ------------------------------------------------------------------ properties
    @property
    def height_range(self) -> Tuple[float, float]:
        """Valid height range ``HEIGHT_OFF ± HEIGHT_SCALE`` (m)."""
        return (self.height_off - abs(self.height_scale), self.height_off + abs(self.height_scale))

    @property
    def image_size(self) -> Tuple[int, int]:
        """Approximate image size (samples, lines) implied by the offsets and scales."""
        # Vendors centre the offsets: SAMP_OFF = (W - 1) / 2 (raw convention), SAMP_SCALE ~ W / 2.
        return (max(1, int(np.floor(self.samp_off + 0.5 + abs(self.samp_scale) + 0.5))),
                max(1, int(np.floor(self.line_off + 0.5 + abs(self.line_scale) + 0.5))))

    @cached_property
    def _coeffs(self) -> np.ndarray:
        """(4, 20) matrix: sample num, sample den, line num, line den."""
        return np.vstack([self.samp_num, self.samp_den, self.line_num, self.line_den])

    # ------------------------------------------------------------------ normalisation
    def _normalise_ground(self, lon, lat, h):
        dlon = np.asarray(lon, dtype=float) - self.long_off
        # Longitudes are compared modulo 360 so that scenes across the antimeridian work.
        dlon = np.where(np.abs(dlon) > 180.0, (dlon + 180.0) % 360.0 - 180.0, dlon)
        L = dlon / self.long_scale
        P = (np.asarray(lat, dtype=float) - self.lat_off) / self.lat_scale
        H = (np.asarray(h, dtype=float) - self.height_off) / self.height_scale
        return L, P, H

    def _pixel_shift(self, pixel_convention: str) -> float:
        if pixel_convention == "gdal":
            return GDAL_PIXEL_OFFSET
        if pixel_convention == "rpc":
            return 0.0
        raise ValueError(f"pixel_convention must be 'gdal' or 'rpc', not {pixel_convention!r}")

    # ------------------------------------------------------------------ ground -> image
    def _project_normalised(self, L, P, H):
        """Normalised (x, y) = (sample, line) ratios for flat normalised inputs, chunked."""
        n = L.size
        x = np.empty(n)
        y = np.empty(n)
        C = self._coeffs
        for i in range(0, n, _CHUNK):
            sl = slice(i, i + _CHUNK)
            v = C @ monomials(L[sl], P[sl], H[sl])
            np.divide(v[0], v[1], out=x[sl])
            np.divide(v[2], v[3], out=y[sl])
        return x, y

    def project(self, lon: ArrayLike, lat: ArrayLike, h: ArrayLike, *, pixel_convention: str = "gdal"):
        """Ground to image (METHODS §1): ``(lon, lat, h) -> (sample, line)``.

        Parameters
        ----------
        lon, lat : degrees WGS84; h : ellipsoidal height in metres. Scalars or arrays (broadcast).
        pixel_convention : ``"gdal"`` (centre of the first pixel at 0.5, default) or ``"rpc"`` (at 0).
        """
        lon, lat, h = np.broadcast_arrays(_as_float_array(lon), _as_float_array(lat), _as_float_array(h))
        shape = lon.shape
        L, P, H = (a.ravel() for a in self._normalise_ground(lon, lat, h))
        x, y = self._project_normalised(L, P, H)
        shift = self._pixel_shift(pixel_convention)
        sample = x * self.samp_scale + (self.samp_off + shift)
        line = y * self.line_scale + (self.line_off + shift)
        return _shape_out(sample, shape), _shape_out(line, shape)

    @cached_property
    def _coeffs_with_derivatives(self) -> np.ndarray:
        """(16, 20): the four polynomials, then their d/dL, d/dP and d/dH, all in the monomial basis."""
        C = self._coeffs
        return np.vstack([C] + [C @ D for D in DERIVATIVE_MATRICES])

    def _normalised_jacobian(self, L, P, H, with_h: bool = True):
        """x, y and their derivatives w.r.t. normalised L, P (and H), for flat inputs.

        One monomial evaluation per chunk: the derivative polynomials are expressed in the same basis.
        """
        Cx = self._coeffs_with_derivatives if with_h else self._coeffs_with_derivatives[:12]
        n = L.size
        V = np.empty((Cx.shape[0], n))
        for i in range(0, n, _CHUNK):
            sl = slice(i, i + _CHUNK)
            V[:, sl] = Cx @ monomials(L[sl], P[sl], H[sl])
        v, vL, vP = V[0:4], V[4:8], V[8:12]
        x = v[0] / v[1]
        y = v[2] / v[3]
        out = {"x": x, "y": y,
               "x_L": (vL[0] - x * vL[1]) / v[1], "x_P": (vP[0] - x * vP[1]) / v[1],
               "y_L": (vL[2] - y * vL[3]) / v[3], "y_P": (vP[2] - y * vP[3]) / v[3]}
        if with_h:
            vH = V[12:16]
            out["x_H"] = (vH[0] - x * vH[1]) / v[1]
            out["y_H"] = (vH[2] - y * vH[3]) / v[3]
        return out

    def project_jacobian(self, lon: ArrayLike, lat: ArrayLike, h: ArrayLike) -> np.ndarray:
        """Analytic Jacobian ``d(sample, line) / d(lon, lat, h)`` in pixels per degree / per metre (METHODS §1).

        The same in either pixel convention (they differ by a constant shift).

        Returns an array of shape ``(..., 2, 3)``: rows (sample, line), columns (lon, lat, h).
        """
        lon, lat, h = np.broadcast_arrays(_as_float_array(lon), _as_float_array(lat), _as_float_array(h))
        shape = lon.shape
        L, P, H = (a.ravel() for a in self._normalise_ground(lon, lat, h))
        d = self._normalised_jacobian(L, P, H)
        J = np.empty((L.size, 2, 3))
        J[:, 0, 0] = d["x_L"] * self.samp_scale / self.long_scale
        J[:, 0, 1] = d["x_P"] * self.samp_scale / self.lat_scale
        J[:, 0, 2] = d["x_H"] * self.samp_scale / self.height_scale
        J[:, 1, 0] = d["y_L"] * self.line_scale / self.long_scale
        J[:, 1, 1] = d["y_P"] * self.line_scale / self.lat_scale
        J[:, 1, 2] = d["y_H"] * self.line_scale / self.height_scale
        return J.reshape(shape + (2, 3))

    # ------------------------------------------------------------------ image -> ground
    @cached_property
    def _approximate_inverse(self) -> np.ndarray:
        """Cubic polynomial (normalised x, y, H) -> (L, P), least-squares fit over the normalised cube.

        It gives Newton a starting point within a small fraction of a pixel, so localisation needs 1-3 steps.
        """
        g = np.linspace(-1.0, 1.0, 11)
        L, P, H = (a.ravel() for a in np.meshgrid(g, g, np.linspace(-1.0, 1.0, 5), indexing="ij"))
        with np.errstate(all="ignore"):
            x, y = self._project_normalised(L, P, H)
        ok = np.isfinite(x) & np.isfinite(y) & (np.abs(x) < 10) & (np.abs(y) < 10)
        A = monomials(x[ok], y[ok], H[ok]).T
        coef, *_ = np.linalg.lstsq(A, np.column_stack([L[ok], P[ok]]), rcond=None)
        return coef.T  # (2, 20)

    def _localize_normalised(self, x, y, H, tol, max_iter):
        """Solve x(L, P, H) = x, y(L, P, H) = y for (L, P); returns L, P, converged mask, iterations.

        Chord-Newton: the Jacobian is evaluated at the starting point (within a fraction of a pixel of the
        solution thanks to the approximate inverse) and refreshed only every third step, so most steps cost
        a single projection. Steps longer than half the normalised cube are damped.
        """
        n = x.size
        L, P = np.empty(n), np.empty(n)
        A = self._approximate_inverse
        with np.errstate(all="ignore"):
            for i in range(0, n, _CHUNK):
                sl = slice(i, i + _CHUNK)
                L[sl], P[sl] = A @ monomials(x[sl], y[sl], H[sl])
        converged = np.zeros(n, dtype=bool)
        tol_x = tol / abs(self.samp_scale)   # tolerances in pixels -> normalised units per axis
        tol_y = tol / abs(self.line_scale)
        active = np.arange(n)
        iterations = 0
        with np.errstate(all="ignore"):
            d = self._normalised_jacobian(L, P, H, with_h=False)
            cx, cy = d["x"], d["y"]
            a, b, c, e = d["x_L"], d["x_P"], d["y_L"], d["y_P"]
            for iterations in range(1, max_iter + 1):
                rx = x[active] - cx
                ry = y[active] - cy
                done = (np.abs(rx) <= tol_x) & (np.abs(ry) <= tol_y)
                converged[active[done]] = True
                keep = ~done & np.isfinite(rx) & np.isfinite(ry)
                if not np.any(keep):
                    active = active[:0]
                    break
                active, rx, ry = active[keep], rx[keep], ry[keep]
                a, b, c, e = a[keep], b[keep], c[keep], e[keep]
                det = a * e - b * c
                dL_ = (e * rx - b * ry) / det
                dP_ = (a * ry - c * rx) / det
                step = np.maximum(np.abs(dL_), np.abs(dP_))
                f = np.where(step > 0.5, 0.5 / step, 1.0)
                L[active] += f * dL_
                P[active] += f * dP_
                if iterations % 3 == 0:
                    d = self._normalised_jacobian(L[active], P[active], H[active], with_h=False)
                    cx, cy = d["x"], d["y"]
                    a, b, c, e = d["x_L"], d["x_P"], d["y_L"], d["y_P"]
                else:
                    cx, cy = self._project_normalised(L[active], P[active], H[active])
        # Solutions far outside the model's normalised domain are polynomial artefacts, not localisations.
        converged &= (np.abs(L) <= 3.0) & (np.abs(P) <= 3.0)
        return L, P, converged, iterations

    def localize(self, sample: ArrayLike, line: ArrayLike, h: ArrayLike, *, pixel_convention: str = "gdal",
                 tol_px: float = 1e-8, max_iter: int = 20, full_output: bool = False):
        """Image to ground at a given height (METHODS §1): ``(sample, line, h) -> (lon, lat)``.

        Vectorised Newton iteration on the 2x2 system, started from a cubic approximate inverse.
        Points that do not converge to ``tol_px`` within ``max_iter`` steps are returned as NaN and counted
        (logged, and returned as :class:`LocalizationStats` when ``full_output=True``).
        """
        sample, line, h = np.broadcast_arrays(_as_float_array(sample), _as_float_array(line), _as_float_array(h))
        shape = sample.shape
        shift = self._pixel_shift(pixel_convention)
        x = (sample.ravel() - shift - self.samp_off) / self.samp_scale
        y = (line.ravel() - shift - self.line_off) / self.line_scale
        H = (h.ravel() - self.height_off) / self.height_scale
        L, P, ok, iters = self._localize_normalised(x, y, H, tol_px, max_iter)
        lon = L * self.long_scale + self.long_off
        lat = P * self.lat_scale + self.lat_off
        lon[~ok] = np.nan
        lat[~ok] = np.nan
        n_failed = int(np.count_nonzero(~ok))
        if n_failed:
            log.info("RPC localisation: %d of %d points did not converge (NaN)", n_failed, ok.size)
        out = (_shape_out(lon, shape), _shape_out(lat, shape))
        if full_output:
            return out + (LocalizationStats(ok.size, n_failed, iters),)
        return out

    def localize_dem(self, sample: ArrayLike, line: ArrayLike, dem, *, pixel_convention: str = "gdal",
                     tol_m: float = 1e-4, max_iter: int = 30, full_output: bool = False):
        """Intersect the lines of sight with a DEM (METHODS §1-§2): ``(sample, line, dem) -> (lon, lat, h)``.

        ``sample, line`` in GDAL's convention (centre of the first pixel at 0.5) unless ``pixel_convention="rpc"``.
        ``dem`` is a :class:`gdal_gf4cal.dem.DEM` or a constant height in metres. The returned point satisfies
        ``project(lon, lat, h) == (sample, line)`` to 1e-8 px and ``|DEM(lon, lat) - h| <= tol_m``; NaN where
        there is no intersection (off the DEM, in a void), counted with ``full_output=True``.

        Most points are solved by an RPC-specific fast path (a cubic model of the line of sight, exact in value and
        slope at one height; Newton steps for the height on it with DEM samples only; then an exact polish, see
        :meth:`_localize_dem_fast`); the rest go to the generic :func:`gdal_gf4cal.localization.localize_dem`
        (height iteration, bracketing on steep terrain).
        """
        from .dem import DEM
        from .localization import localize_dem
        dem = DEM.coerce(dem)
        if dem.is_constant:
            return localize_dem(self, sample, line, dem, pixel_convention=pixel_convention, tol_m=tol_m,
                                max_iter=max_iter, full_output=full_output)
        sample, line = np.broadcast_arrays(_as_float_array(sample), _as_float_array(line))
        shape = sample.shape
        s, l = sample.ravel(), line.ravel()
        lon, lat, h = self._localize_dem_fast(s, l, dem, self._pixel_shift(pixel_convention), tol_m)
        todo = np.flatnonzero(~np.isfinite(h))
        if todo.size:
            lo, la, hh = localize_dem(self, s[todo], l[todo], dem, pixel_convention=pixel_convention, tol_m=tol_m,
                                      max_iter=max_iter)
            lon[todo], lat[todo], h[todo] = lo, la, hh
        n_failed = int(np.count_nonzero(~np.isfinite(h)))
        out = (_shape_out(lon, shape), _shape_out(lat, shape), _shape_out(h, shape))
        return out + (n_failed,) if full_output else out

    def _localize_dem_fast(self, s, l, dem, shift, tol_m, ray_iter: int = 12, polish_iter: int = 4):
        """Fast path of :meth:`localize_dem` (METHODS §1-§2); NaN where it did not settle (the caller retries those).

        Per chunk of points (all temporaries stay in cache):

        1. *Ray.* The approximate inverse (cubic in x, y, H) gives, for fixed image point, (L, P) as a cubic in H
           around a scene start height h0; one Newton step with the exact Jacobian (incl. d/dH) at h0 corrects
           its value and slope, so the cubic ray is exact at h0 and within ~1e-3 px over 1.5 normalised heights.
        2. *Height on the ray* with DEM samples only: Newton on f(h) = DEM(ray(h)) - h with the analytic gradient
           of the bilinear surface (secant steps for DEMs sampled through pyproj/geoid/tiles).
        3. *Polish:* exact localisation at h by chord Newton (1e-8 px), DEM check |DEM - h| <= tol_m; points that
           miss it take a Newton step in h on the ray re-anchored at the exact point, and are polished again.
        """
        n = s.size
        out = np.full((3, n), np.nan)
        x = (s - shift - self.samp_off) / self.samp_scale
        y = (l - shift - self.line_off) / self.line_scale
        with np.errstate(all="ignore"):
            h0 = _dem_start_height(self, x, y, dem)
            basis = _ray_basis(self._approximate_inverse, (h0 - self.height_off) / self.height_scale)
            frame = _dem_frame(dem)
            for i in range(0, n, _DEM_CHUNK):
                sl = slice(i, i + _DEM_CHUNK)
                out[:, sl] = _dem_chunk(self, x[sl], y[sl], dem, frame, h0, basis, tol_m, ray_iter, polish_iter)
        return out[0], out[1], out[2]

    # ------------------------------------------------------------------ image-space corrections
    def with_image_affine(self, sample_shift: float = 0.0, line_shift: float = 0.0, sample_scale: float = 1.0,
                          line_scale: float = 1.0, *, pixel_convention: str = "gdal") -> "RPCModel":
        """Fold an exact image-space shift and per-axis scale into the offsets and scales (METHODS §4.2).

        The new model returns ``sample' = sample_shift + sample_scale * sample`` (and likewise for line), where
        ``sample`` is what this model returns, both in ``pixel_convention``.
        """
        # In the chosen convention s = SAMP_OFF + c0 + SAMP_SCALE * x, with c0 the convention's shift.
        c0 = self._pixel_shift(pixel_convention)
        new_samp_off = sample_shift + sample_scale * (self.samp_off + c0) - c0
        new_line_off = line_shift + line_scale * (self.line_off + c0) - c0
        return self.replace(samp_off=new_samp_off, line_off=new_line_off,
                            samp_scale=self.samp_scale * sample_scale, line_scale=self.line_scale * line_scale,
                            source=None)

    def __repr__(self) -> str:
        return (f"RPCModel(lon={self.long_off:.6f}±{abs(self.long_scale):.4f}, lat={self.lat_off:.6f}±"
                f"{abs(self.lat_scale):.4f}, h={self.height_off:.1f}±{abs(self.height_scale):.1f}, "
                f"size~{self.image_size[0]}x{self.image_size[1]}" + (f", source={self.source!r})" if self.source
                                                                    else ")"))


def _dem_nan(dem, lon, lat):
    """DEM heights with NaN off the DEM / in voids, whatever the DEM's own policy (used inside iterations)."""
    from .localization import _dem_height_nan
    return _dem_height_nan(dem, lon, lat)


#: Points per chunk of the DEM-intersection fast path. Small enough that its per-point state stays in cache and
#: that the temporaries are recycled by malloc instead of being fresh mmap'ed pages (page faults cost more than
#: the arithmetic on this kind of machine: 16384 was 30-100 % slower).
_DEM_CHUNK = 8192

#: Stage-2 (height on the ray) stopping value of |DEM - h| in metres: the Newton step still taken after it makes the
#: height exact to ~1e-6 m within a DEM cell, and the polish checks the real tolerance anyway.
_TOL_A = 1e-2

#: (x, y) exponents of the ten H-free RPC00B terms, and their term index.
_XY_TERMS = tuple((j, e[0], e[1]) for j, e in enumerate(_EXPONENTS) if e[2] == 0)


def _xy_monomials(x, y):
    """The ten H-free monomials ``1, x, y, xy, x², y², x³, xy², x²y, y³`` (rows, RPC00B order)."""
    m = np.empty((10, x.size))
    m[0] = 1.0
    m[1] = x
    m[2] = y
    np.multiply(x, y, out=m[3])
    np.multiply(x, x, out=m[4])
    np.multiply(y, y, out=m[5])
    np.multiply(m[4], x, out=m[6])
    np.multiply(m[5], x, out=m[7])
    np.multiply(m[4], y, out=m[8])
    np.multiply(m[5], y, out=m[9])
    return m


def _ray_basis(A: np.ndarray, Hm: float) -> np.ndarray:
    """(8, 10) matrix B: ``B @ _xy_monomials(x, y)`` = coefficients of t^0..t^3 of L, then P, of ``A(x, y, Hm + t)``.

    ``A`` is the (2, 20) approximate inverse (normalised x, y, H) -> (L, P); (Hm + t)^e is expanded binomially.
    """
    col = {(ex, ey): k for k, (_, ex, ey) in enumerate(_XY_TERMS)}
    B = np.zeros((8, 10))
    for j, (ex, ey, eh) in enumerate(_EXPONENTS):
        q = col[(ex, ey)]
        for k in range(eh + 1):
            w = math.comb(eh, k) * Hm ** (eh - k)
            B[k, q] += A[0, j] * w
            B[4 + k, q] += A[1, j] * w
    return B


def _horner(c, u):
    """c[0] + c[1] u + c[2] u² + c[3] u³ for rows c (4, N)."""
    r = c[3] * u
    r += c[2]
    r *= u
    r += c[1]
    r *= u
    r += c[0]
    return r


def _dem_frame(dem):
    """How the ray stage samples the DEM: ``(ox, sx, oy, sy, sampler)``.

    The sampler takes ``(p, q) = (ox + sx * lon, oy + sy * lat)`` and returns ``(z, dz/dp, dz/dq)``; for a small
    geographic DEM without geoid those are pixel coordinates sampled in memory with the analytic gradient, for
    every other DEM ``p, q = lon, lat`` through :meth:`DEM.height` and the gradients are ``None`` (secant steps).
    """
    fast = (dem._to_dem is None and dem._geoid is None and dem.width * dem.height_px <= dem._whole_limit
            and dem.width >= 2 and dem.height_px >= 2)
    if fast:
        gt = dem._gt
        return (-gt[0] / gt[1] - 0.5, 1.0 / gt[1], -gt[3] / gt[5] - 0.5, 1.0 / gt[5],
                lambda p, q: dem._sample_whole(p, q, gradient=True))
    return 0.0, 1.0, 0.0, 1.0, lambda p, q: (_dem_nan(dem, p, q), None, None)


def _dem_start_height(rpc, x, y, dem) -> float:
    """One start height for the scene: middle of the DEM heights under a subsample of the points (approximate)."""
    lo, hi = dem.height_range()
    mid = 0.5 * (lo + hi)
    step = max(1, x.size // 512)
    xs, ys = x[::step], y[::step]
    A = rpc._approximate_inverse
    L, P = A @ monomials(xs, ys, np.full(xs.size, (mid - rpc.height_off) / rpc.height_scale))
    z = _dem_nan(dem, L * rpc.long_scale + rpc.long_off, P * rpc.lat_scale + rpc.lat_off)
    z = z[np.isfinite(z)]
    return 0.5 * (float(z.min()) + float(z.max())) if z.size else mid


def _dem_chunk(rpc, x, y, dem, frame, h0, basis, tol_m, ray_iter, polish_iter):
    """One chunk of :meth:`RPCModel._localize_dem_fast`: returns (3, m) lon, lat, h with NaN where unsettled."""
    m = x.size
    out = np.full((3, m), np.nan)
    hs = rpc.height_scale
    Hm = (h0 - rpc.height_off) / hs
    # 1. Ray: cubic in t = H - Hm from the approximate inverse, value and slope corrected by one exact Newton step.
    R = basis @ _xy_monomials(x, y)                       # rows L0..L3, P0..P3
    L0, P0 = R[0], R[4]
    V = rpc._coeffs_with_derivatives @ monomials(L0, P0, np.full(m, Hm))
    xe, ye = V[0] / V[1], V[2] / V[3]
    xL, xP, xH = (V[4] - xe * V[5]) / V[1], (V[8] - xe * V[9]) / V[1], (V[12] - xe * V[13]) / V[1]
    yL, yP, yH = (V[6] - ye * V[7]) / V[3], (V[10] - ye * V[11]) / V[3], (V[14] - ye * V[15]) / V[3]
    det = xL * yP - xP * yL
    # Inverse Jacobian d(L, P)/d(x, y), reused for every chord-Newton step of the polish.
    J = np.empty((4, m))
    np.divide(yP, det, out=J[0])
    np.divide(-xP, det, out=J[1])
    np.divide(-yL, det, out=J[2])
    np.divide(xL, det, out=J[3])
    rx, ry = x - xe, y - ye
    L0 += J[0] * rx + J[1] * ry
    P0 += J[2] * rx + J[3] * ry
    R[1] = -(J[0] * xH + J[1] * yH)                        # exact d(L, P)/dH along the line of sight
    R[5] = -(J[2] * xH + J[3] * yH)
    # The ray in the DEM sampler's frame, as cubics in u = h - h0 metres.
    ox, sx, oy, sy, sample = frame
    G = np.empty((8, m))
    ks = sx * rpc.long_scale
    kq = sy * rpc.lat_scale
    for k in range(4):
        G[k] = R[k] * (ks / hs ** k)
        G[4 + k] = R[4 + k] * (kq / hs ** k)
    G[0] += ox + sx * rpc.long_off
    G[4] += oy + sy * rpc.lat_off

    # 2. Height on the ray, DEM samples only.
    tol_a = max(tol_m, _TOL_A)
    u = np.zeros(m)
    slope = np.full(m, -1.0)
    ready = np.zeros(m, dtype=bool)
    idx = np.flatnonzero(np.isfinite(G[0]) & np.isfinite(G[4]) & np.isfinite(R[1]) & np.isfinite(R[5]))
    Ga = G[:, idx]
    uu = np.zeros(idx.size)
    f_prev = np.full(idx.size, np.nan)
    u_prev = np.full(idx.size, np.nan)
    for it in range(ray_iter):
        if idx.size == 0:
            break
        z, zp, zq = sample(_horner(Ga[0:4], uu), _horner(Ga[4:8], uu))
        f = z - uu
        f -= h0
        if zp is not None:
            d = zp * Ga[1]
            d += zq * Ga[5]
            d -= 1.0
        else:
            d = (f - f_prev) / (uu - u_prev)
            d[~np.isfinite(d) | (d == 0)] = -1.0               # first step: plain fixed point h <- DEM
        af = np.abs(f)
        # Terrain rising along the ray at least as fast as the ray (d >= 0: |slope x tan(view)| >= 1) may hide
        # this root behind another; such points, and steps that stop shrinking |f| (oscillation, grazing rays),
        # go to the generic fallback, which brackets the first crossing seen from above.
        front = d < 0
        done = (af <= tol_a) & front
        good = ~done & front & ((af < np.abs(f_prev)) if it else np.isfinite(f))
        unew = uu - f / d                                       # also a free last step for the settled points
        j = idx[done]
        u[j], slope[j], ready[j] = unew[done], d[done], True
        keep = np.flatnonzero(good)
        idx, Ga, f_prev, u_prev, uu = idx[keep], Ga[:, keep], f[keep], uu[keep], unew[keep]

    # 3. Polish: exact localisation at h, then the DEM check; re-anchor the ray at the exact point and step in h.
    idx = np.flatnonzero(ready)
    if idx.size == 0:
        return out
    Rp, Jp, xp, yp = R[:, idx], J[:, idx], x[idx], y[idx]
    up, sp = u[idx], slope[idx]
    dL = np.zeros(idx.size)
    dP = np.zeros(idx.size)
    tol_x, tol_y = 1e-8 / abs(rpc.samp_scale), 1e-8 / abs(rpc.line_scale)
    for _ in range(polish_iter):
        if idx.size == 0:
            break
        t = up / hs
        H = t + Hm
        Lr, Pr = _horner(Rp[0:4], t), _horner(Rp[4:8], t)
        L, P = Lr + dL, Pr + dP
        # Chord Newton on the points not yet within 1e-8 px (L, P hold the last evaluated position of each point).
        act = np.arange(idx.size)
        La, Pa, Ha, Ja, xa, ya = L, P, H, Jp, xp, yp
        for _ in range(6):
            cx, cy = rpc._project_normalised(La, Pa, Ha)
            rx, ry = xa - cx, ya - cy
            off = np.flatnonzero((np.abs(rx) > tol_x) | (np.abs(ry) > tol_y))
            L[act], P[act] = La, Pa
            if off.size == 0:
                act = act[:0]
                break
            act, rx, ry, Ja = act[off], rx[off], ry[off], Ja[:, off]
            La = L[act] + Ja[0] * rx + Ja[1] * ry
            Pa = P[act] + Ja[2] * rx + Ja[3] * ry
            Ha, xa, ya = H[act], xp[act], yp[act]
        exact = np.ones(idx.size, dtype=bool)
        exact[act] = False
        exact &= (np.abs(L) <= 3.0) & (np.abs(P) <= 3.0)
        lon = L * rpc.long_scale + rpc.long_off
        lat = P * rpc.lat_scale + rpc.lat_off
        h = up + h0
        f = _dem_nan(dem, lon, lat) - h
        done = exact & (np.abs(f) <= tol_m)
        j = idx[done]
        out[0, j], out[1, j], out[2, j] = lon[done], lat[done], h[done]
        keep = np.flatnonzero(~done & exact & np.isfinite(f))
        idx, Rp, Jp, xp, yp, sp = idx[keep], Rp[:, keep], Jp[:, keep], xp[keep], yp[keep], sp[keep]
        dL, dP = (L - Lr)[keep], (P - Pr)[keep]
        up = up[keep] - f[keep] / sp
    return out


def _parse_number(value, key: str, where: str) -> float:
    try:
        text = str(value).strip().split()[0] if isinstance(value, str) else value
        number = float(text)
    except (ValueError, IndexError, TypeError):
        raise RPCFormatError(f"RPC{where}: {key} is not a number ({str(value)[:40]!r})") from None
    if not math.isfinite(number):
        raise RPCFormatError(f"RPC{where}: {key} is not a finite number ({value!r})")
    return number


def _fmt(value: float) -> str:
    """17 significant digits: enough for a float64 to read back bit-identical."""
    return repr(float(value)) if abs(float(value)) >= 1e-4 or value == 0 else f"{float(value):.17g}"
