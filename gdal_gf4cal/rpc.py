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

from ._rpc_poly import (_CHUNK, _EXPONENTS, DERIVATIVE_MATRICES, TERMS, fill_monomials,  # noqa: F401
                        monomial_chunks, monomial_derivatives, monomials, poly_product, scratch)
from .errors import RPCFormatError
from .rpc_io import read_rpc_metadata, write_rpb, write_rpc_txt
from .sensor import GDAL_PIXEL_OFFSET, LocalizationStats, SensorModelMixin, pixel_shift  # noqa: F401
from .threads import BLAS_SERIAL_SIZE, blas_is_serial, map_blocks, split_points

log = logging.getLogger(__name__)

_SCALARS = ("line_off", "samp_off", "lat_off", "long_off", "height_off",
            "line_scale", "samp_scale", "lat_scale", "long_scale", "height_scale")
_GDAL_SCALAR_KEYS = {name: name.upper() for name in _SCALARS}
_GDAL_COEFF_KEYS = {"line_num": "LINE_NUM_COEFF", "line_den": "LINE_DEN_COEFF",
                    "samp_num": "SAMP_NUM_COEFF", "samp_den": "SAMP_DEN_COEFF"}
_GDAL_OPTIONAL = {"err_bias": "ERR_BIAS", "err_rand": "ERR_RAND", "min_long": "MIN_LONG", "min_lat": "MIN_LAT",
                  "max_long": "MAX_LONG", "max_lat": "MAX_LAT"}

ArrayLike = Union[float, np.ndarray]

#: Localisations are accepted this many normalised units from the RPC's ground cube at most (METHODS §1): cropped
#: RPCs keep image offsets tens of scales away from their pixels, GDAL extrapolates there, so do we; beyond it a
#: root is an artefact of the polynomial.
_MAX_EXTRAPOLATION = 100.0


#: Points per Newton solve of :meth:`RPCModel.localize` (a block of the thread pool is solved in such chunks): the
#: solver's state (~30 arrays) stays within the cache: 1.5x less CPU per point than solving 32768 points at once
#: (230 against 360 ns per point, one run on the loaded machine), while its per-solve cost (~0.2 ms of NumPy calls,
#: which hold the GIL) stays a twentieth of the solve. Every point is solved on its own: the same bits for any size.
LOCALIZE_CHUNK = 16384

#: Columns of one (4, 20) x (20, k) product of the projection kernel outside a BLAS-serial scope: the most OpenBLAS
#: computes on the calling thread (:data:`~gdal_gf4cal.threads.BLAS_SERIAL_SIZE`: 80 k <= 4 x 65536); inside one
#: (:func:`~gdal_gf4cal.threads.blas_is_serial`) a chunk is one product: the same bits, fewer calls.
_PROJECT_GEMM = BLAS_SERIAL_SIZE // 80
#: Points per chunk of the projection kernel (five products): larger than L2 (the (20, chunk) monomials take 2.6 MB)
#: but ~2x faster than 3276-point chunks on the loaded 2-core machine (NumPy's per-call cost, ~1.5 us there, weighs on
#: small chunks), as fast as 8192 with half the calls per block (calls hold the GIL). A divisor of
#: :data:`~gdal_gf4cal.threads.BLOCK`: split or not, a point lies in the same product.
PROJECT_CHUNK = 16384


def _as_float_array(x) -> np.ndarray:
    return np.asarray(x, dtype=float)


def _shape_out(values: np.ndarray, shape: tuple):
    """Return a scalar for scalar input, else reshape to the broadcast input shape."""
    if shape == ():
        return float(values.reshape(-1)[0])
    return values.reshape(shape)


@dataclass(frozen=True, eq=False)
class RPCModel(SensorModelMixin):
    """An RPC00B model (METHODS §1), immutable.

    ``line_off``/``samp_off`` are stored in the raw RPC00B convention (as in the files); :meth:`project` and
    :meth:`localize` speak GDAL's pixel convention unless ``pixel_convention="rpc"``.
    Build one with :meth:`from_file`, :meth:`from_gdal_metadata` or directly from coefficients.
    """

    #: The localisation layer intersects RPC lines of sight with a DEM by its RPC fast path
    #: (:func:`gdal_gf4cal.localization.localize_dem`); a class attribute, not a dataclass field.
    rational_polynomial = True

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
        return validate_rpc(cls(source=source, **kwargs))

    @classmethod
    def from_file(cls, path) -> "RPCModel":
        """Read an RPC from an image (TIFF tags, .RPB, _RPC.TXT, NITF) or a standalone sidecar / vendor XML / JSON.

        The format is detected by content as well as by name (see :mod:`gdal_gf4cal.rpc_io`).
        """
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
        return write_rpb(self, path, overwrite=overwrite)

    def write_rpc_txt(self, path, overwrite: bool = False) -> "Path":
        """Write a ``_RPC.TXT`` sidecar atomically (see :func:`gdal_gf4cal.rpc_io.write_rpc_txt`)."""
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
    def normalise_ground(self, lon, lat, h):
        """Normalised ``(L, P, H)`` of ground points (METHODS §1): offsets subtracted, scales divided out,
        longitudes taken modulo 360 about ``LONG_OFF`` (scenes across the antimeridian)."""
        dlon = np.asarray(lon, dtype=float) - self.long_off
        # Longitudes are compared modulo 360 so that scenes across the antimeridian work.
        dlon = np.where(np.abs(dlon) > 180.0, (dlon + 180.0) % 360.0 - 180.0, dlon)
        L = dlon / self.long_scale
        P = (np.asarray(lat, dtype=float) - self.lat_off) / self.lat_scale
        H = (np.asarray(h, dtype=float) - self.height_off) / self.height_scale
        return L, P, H

    @staticmethod
    def _pixel_shift(pixel_convention: str) -> float:
        return pixel_shift(pixel_convention)

    # ------------------------------------------------------------------ ground -> image
    def _project_normalised(self, L, P, H):
        """Normalised (x, y) = (sample, line) ratios for flat normalised inputs, chunked."""
        n = L.size
        x = np.empty(n)
        y = np.empty(n)
        C = self._coeffs
        with scratch(4, min(n, _CHUNK)) as buf:
            for i, j, m in monomial_chunks(L, P, H):
                v = poly_product(C, m, out=buf[:, :j - i])
                np.divide(v[0], v[1], out=x[i:j])
                np.divide(v[2], v[3], out=y[i:j])
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
        lon, lat, h = lon.ravel(), lat.ravel(), h.ravel()
        out = np.empty((2, lon.size))
        C = self._project_coeffs(self._pixel_shift(pixel_convention))
        # Each block writes its own columns of ``out`` (no per-block results joined afterwards).
        map_blocks(lambda sl: self._project_into(lon[sl], lat[sl], h[sl], C, out[:, sl]), lon.size)
        return _shape_out(out[0], shape), _shape_out(out[1], shape)

    def _project_into(self, lon, lat, h, C, out) -> None:
        """:meth:`project` of flat arrays into ``out`` (2, n) with the coefficients of :meth:`_project_coeffs`: per
        chunk of :data:`PROJECT_CHUNK` points, in one reused (20, chunk) monomial buffer, the ground offsets
        subtracted into its rows 1-3 (longitudes modulo 360 when a chunk spans the antimeridian), the monomials in
        place (:func:`fill_monomials`), the (4, 20) x (20, chunk) product into a reused (4, chunk) buffer (in
        slices of :data:`_PROJECT_GEMM` columns unless BLAS is held on the calling thread, :func:`blas_is_serial`),
        one division: 12 NumPy calls per chunk in two buffers the thread keeps (:func:`scratch`), the same bits
        (the same pixels as normalising whole arrays to 1e-11 px)."""
        c = max(1, min(lon.size, PROJECT_CHUNK))
        off = (self.long_off, self.lat_off, self.height_off)
        with scratch(20, c) as m, scratch(4, c) as v:
            m[0] = 1.0
            self._project_chunks(lon, lat, h, off, C, m, v, out)

    @staticmethod
    def _project_chunks(lon, lat, h, off, C, m, v, out) -> None:
        """The chunk loop of :meth:`_project_into` in the buffers ``m`` (20, chunk) and ``v`` (4, chunk)."""
        n, c = lon.size, m.shape[1]
        step = c if blas_is_serial() else _PROJECT_GEMM
        for i in range(0, n, c):
            j = min(i + c, n)
            if j - i < c:
                m, v = m[:, :j - i], v[:, :j - i]
            dlon = np.subtract(lon[i:j], off[0], out=m[1])
            if dlon.min() < -180.0 or dlon.max() > 180.0:    # across the antimeridian: longitudes modulo 360
                np.copyto(dlon, np.where(np.abs(dlon) > 180.0, (dlon + 180.0) % 360.0 - 180.0, dlon))
            np.subtract(lat[i:j], off[1], out=m[2])
            np.subtract(h[i:j], off[2], out=m[3])
            fill_monomials(m)
            for a in range(0, j - i, step):
                b = min(a + step, j - i)
                a = max(0, min(a, b - 2))                # never a one-column product (BLAS takes another kernel)
                np.matmul(C, m[:, a:b], out=v[:, a:b])
            np.divide(v[0::2], v[1::2], out=out[:, i:j])

    def _project_coeffs(self, shift: float) -> np.ndarray:
        """(4, 20) coefficients of the projection in ground offsets ``(lon - LONG_OFF, lat - LAT_OFF, h -
        HEIGHT_OFF)`` straight to pixels: each term divided by its power of the ground scales, the numerators times
        the image scale plus the image offset times the denominator (``s = num / den * scale + off``)."""
        key = float(shift)
        cache = self.__dict__.setdefault("_project_coeffs_cache", {})
        if key not in cache:
            e = np.array(_EXPONENTS, dtype=float)                         # (20, 3) powers of L, P, H
            ground = np.array([self.long_scale, self.lat_scale, self.height_scale])
            C = self._coeffs / np.prod(ground[None, :] ** e, axis=1)[None, :]
            C[0] = C[0] * self.samp_scale + (self.samp_off + key) * C[1]
            C[2] = C[2] * self.line_scale + (self.line_off + key) * C[3]
            cache[key] = C
        return cache[key]

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
        with scratch(Cx.shape[0], L.size) as V:
            for i, j, m in monomial_chunks(L, P, H):
                poly_product(Cx, m, out=V[:, i:j])
            return self._jacobian_from_values(V, with_h)

    @staticmethod
    def _jacobian_from_values(V, with_h):
        """The quotients and their derivatives from the 12 or 16 polynomial rows of :meth:`_normalised_jacobian`."""
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

    def project_jacobian(self, lon: ArrayLike, lat: ArrayLike, h: ArrayLike, *,
                         pixel_convention: str = "gdal") -> np.ndarray:
        """Analytic Jacobian ``d(sample, line) / d(lon, lat, h)`` in pixels per degree / per metre (METHODS §1).

        The same in either pixel convention (they differ by a constant shift).

        Returns an array of shape ``(..., 2, 3)``: rows (sample, line), columns (lon, lat, h).
        """
        return self.project_with_jacobian(lon, lat, h, pixel_convention=pixel_convention)[2]

    def project_with_jacobian(self, lon: ArrayLike, lat: ArrayLike, h: ArrayLike, *, pixel_convention: str = "gdal"):
        """``(sample, line, J)``: :meth:`project` and :meth:`project_jacobian` from one evaluation of the
        polynomials (values and derivatives share the monomials), in blocks over the thread pool (the same bits
        whatever ``GF4CAL_NUM_THREADS``); sample and line agree with :meth:`project` to 1e-9 px."""
        shift = self._pixel_shift(pixel_convention)
        lon, lat, h = np.broadcast_arrays(_as_float_array(lon), _as_float_array(lat), _as_float_array(h))
        shape = lon.shape
        out = split_points(lambda *g: self._project_jacobian_flat(*g, shift), lon.ravel(), lat.ravel(), h.ravel())
        J = np.stack(out[2:], axis=1).reshape(shape + (2, 3))
        return _shape_out(out[0], shape), _shape_out(out[1], shape), J

    def _project_jacobian_flat(self, lon, lat, h, shift: float):
        """Sample, line and the six Jacobian entries (s_lon, s_lat, s_h, l_lon, l_lat, l_h) of flat arrays."""
        d = self._normalised_jacobian(*self.normalise_ground(lon, lat, h))
        ss, ls = self.samp_scale, self.line_scale
        return (d["x"] * ss + (self.samp_off + shift), d["y"] * ls + (self.line_off + shift),
                d["x_L"] * ss / self.long_scale, d["x_P"] * ss / self.lat_scale, d["x_H"] * ss / self.height_scale,
                d["y_L"] * ls / self.long_scale, d["y_P"] * ls / self.lat_scale, d["y_H"] * ls / self.height_scale)

    # ------------------------------------------------------------------ image -> ground
    @cached_property
    def _inverse_fit(self):
        """Approximate inverses fitted over the RPC's *ground* cube (METHODS §1).

        A grid of the normalised ground cube ``[-1, 1]^3`` is projected; its image ``(x, y)`` defines an image
        frame (centre ``cx, cy``, half-spans ``sx, sy``) in which the fits are well conditioned even when the image
        offsets lie tens of scales away from the image points (cropped RPCs). Returns ``(frame, cubic, affine)``:
        ``frame = (cx, sx, cy, sy)``; ``cubic`` (2, 20) maps the 20 monomials of the framed ``(u, v, H)`` to
        ``(L, P)``; ``affine`` (2, 4) maps ``(1, u, v, H)`` to ``(L, P)`` and is what points outside the frame start
        from (a cubic extrapolates wildly there).
        """
        g = np.linspace(-1.0, 1.0, 11)
        L, P, H = (a.ravel() for a in np.meshgrid(g, g, np.linspace(-1.0, 1.0, 5), indexing="ij"))
        with np.errstate(all="ignore"):
            x, y = self._project_normalised(L, P, H)
        ok = np.isfinite(x) & np.isfinite(y)
        if np.count_nonzero(ok) < 40:
            raise RPCFormatError(f"RPC{self._where()}: its ground cube does not project to finite image points; "
                                 "the RPC is not usable")
        frame = []
        for v in (x[ok], y[ok]):
            lo, hi = np.percentile(v, [2.0, 98.0])
            c, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
            frame += [c, half if half > 0 else 1.0]
        cx, sx, cy, sy = frame
        u, v = (x - cx) / sx, (y - cy) / sy
        ok &= (np.abs(u) <= 4.0) & (np.abs(v) <= 4.0)   # a pole inside the cube must not drive the fit
        target = np.column_stack([L[ok], P[ok]])
        cubic, *_ = np.linalg.lstsq(monomials(u[ok], v[ok], H[ok]).T, target, rcond=None)
        A1 = np.column_stack([np.ones(np.count_nonzero(ok)), u[ok], v[ok], H[ok]])
        affine, *_ = np.linalg.lstsq(A1, target, rcond=None)
        return np.array(frame), cubic.T, affine.T

    @cached_property
    def _approximate_inverse(self) -> np.ndarray:
        """Cubic (normalised x, y, H) -> (L, P) in the RPC's own normalised image coordinates, (2, 20).

        The framed cubic of :attr:`_inverse_fit` with the frame substituted (exact binomial expansion), for callers
        that evaluate ``A @ monomials(x, y, H)`` directly (the DEM fast path of the localisation layer).
        """
        (cx, sx, cy, sy), cubic, _ = self._inverse_fit
        index = {e: k for k, e in enumerate(_EXPONENTS)}
        T = np.zeros((20, 20))          # framed monomial j = sum_k T[j, k] raw monomial k
        for j, (a, b, c) in enumerate(_EXPONENTS):
            for i in range(a + 1):
                wa = math.comb(a, i) * (-cx) ** (a - i) / sx ** a
                for k in range(b + 1):
                    wb = math.comb(b, k) * (-cy) ** (b - k) / sy ** b
                    T[j, index[(i, k, c)]] += wa * wb
        return cubic @ T

    def _start_normalised(self, x, y, H):
        """Newton start ``(L, P)`` for flat normalised image points: the cubic inverse inside the image of the
        ground cube (within a small fraction of a pixel), the ground-cube affine outside it."""
        (cx, sx, cy, sy), _, affine = self._inverse_fit
        A = self._approximate_inverse
        n = x.size
        L, P = np.empty(n), np.empty(n)
        x_lo, x_hi, y_lo, y_hi = cx - 1.25 * sx, cx + 1.25 * sx, cy - 1.25 * sy, cy + 1.25 * sy
        for i, j, m in monomial_chunks(x, y, H):
            xs, ys, hs = x[i:j], y[i:j], H[i:j]
            L[i:j], P[i:j] = poly_product(A, m)
            # Chunk-wise bounds first: the common case (every point inside) costs six reductions.
            if (xs.min(initial=x_lo) >= x_lo and xs.max(initial=x_hi) <= x_hi and ys.min(initial=y_lo) >= y_lo
                    and ys.max(initial=y_hi) <= y_hi and np.abs(hs).max(initial=0.0) <= 1.5):
                continue
            out = np.flatnonzero(~((xs >= x_lo) & (xs <= x_hi) & (ys >= y_lo) & (ys <= y_hi) & (np.abs(hs) <= 1.5)))
            uo, vo, ho = (xs[out] - cx) / sx, (ys[out] - cy) / sy, hs[out]
            L[i + out] = affine[0, 0] + affine[0, 1] * uo + affine[0, 2] * vo + affine[0, 3] * ho
            P[i + out] = affine[1, 0] + affine[1, 1] * uo + affine[1, 2] * vo + affine[1, 3] * ho
        return L, P

    def _localize_normalised(self, x, y, H, tol, max_iter):
        """Solve x(L, P, H) = x, y(L, P, H) = y for (L, P); returns L, P, converged mask, iterations.

        Started from the ground domain (:meth:`_start_normalised`). Chord-Newton: the Jacobian is evaluated at the
        starting point (within a fraction of a pixel of the solution inside the image of the ground cube) and
        refreshed every third step, every step after the third (points started outside the cube, cropped RPCs),
        so most steps cost a single projection. Steps are damped in ground space: at most half a normalised unit,
        or half the distance from the cube's centre when the point lies farther out. A solution is accepted
        within ``_MAX_EXTRAPOLATION`` normalised units of the cube and with the cube's orientation (the sign of
        the Jacobian determinant at its centre): other roots are polynomial artefacts.
        """
        L, P = self._start_normalised(x, y, H)
        n = x.size
        converged = np.zeros(n, dtype=bool)
        det_sign = None             # the orientation, checked for the points that need more than two steps
        tol_x = tol / abs(self.samp_scale)   # tolerances in pixels -> normalised units per axis
        tol_y = tol / abs(self.line_scale)
        active = np.arange(n)
        iterations = 0
        with np.errstate(all="ignore"):
            d = self._normalised_jacobian(L, P, H, with_h=False)
            cx, cy = d["x"], d["y"]
            a, b, c, e = d["x_L"], d["x_P"], d["y_L"], d["y_P"]
            for iterations in range(1, max_iter + 1):
                full = active.size == n              # every point still active: plain arrays, no gather/scatter
                rx = (x if full else x[active]) - cx
                ry = (y if full else y[active]) - cy
                done = (np.abs(rx) <= tol_x) & (np.abs(ry) <= tol_y)
                if full:                             # no gather and scatter of the indices
                    np.logical_or(converged, done, out=converged)
                else:
                    converged[active[done]] = True
                if iterations > 2:
                    if det_sign is None:
                        det_sign = np.full(n, self._orientation)
                    det_sign[active[done]] = np.sign(a[done] * e[done] - b[done] * c[done])
                if full and done.all():              # the common end: every point settled at once
                    active = active[:0]
                    break
                keep = ~done & np.isfinite(rx) & np.isfinite(ry)
                kept = np.count_nonzero(keep)
                if not kept:
                    active = active[:0]
                    break
                if kept < keep.size:
                    active, rx, ry = active[keep], rx[keep], ry[keep]
                    a, b, c, e = a[keep], b[keep], c[keep], e[keep]
                    full = False
                det = a * e - b * c
                dL_ = (e * rx - b * ry) / det
                dP_ = (a * ry - c * rx) / det
                step = np.maximum(np.abs(dL_), np.abs(dP_))
                big = np.flatnonzero(step > 0.5)
                if big.size:   # damping, in ground space: rare, so only these points pay for it
                    ab = active[big]
                    limit = 0.5 * np.maximum(1.0, np.maximum(np.abs(L[ab]), np.abs(P[ab])))
                    f = np.minimum(1.0, limit / step[big])
                    dL_[big] *= f
                    dP_[big] *= f
                if full:
                    L += dL_
                    P += dP_
                    La, Pa, Ha = L, P, H
                else:
                    L[active] += dL_
                    P[active] += dP_
                    La, Pa, Ha = L[active], P[active], H[active]
                if iterations % 3 == 0 or iterations > 3:
                    d = self._normalised_jacobian(La, Pa, Ha, with_h=False)
                    cx, cy = d["x"], d["y"]
                    a, b, c, e = d["x_L"], d["x_P"], d["y_L"], d["y_P"]
                else:
                    cx, cy = self._project_normalised(La, Pa, Ha)
        converged &= (np.abs(L) <= _MAX_EXTRAPOLATION) & (np.abs(P) <= _MAX_EXTRAPOLATION)
        if det_sign is not None:
            converged &= det_sign == self._orientation
        return L, P, converged, iterations

    @cached_property
    def _orientation(self) -> float:
        """Sign of ``det d(x, y)/d(L, P)`` at the ground cube's centre (+1 or -1)."""
        d = self._normalised_jacobian(np.zeros(1), np.zeros(1), np.zeros(1), with_h=False)
        return float(np.sign(d["x_L"][0] * d["y_P"][0] - d["x_P"][0] * d["y_L"][0]))

    def localize(self, sample: ArrayLike, line: ArrayLike, h: ArrayLike, *, pixel_convention: str = "gdal",
                 tol_px: float = 1e-8, max_iter: int = 20, full_output: bool = False):
        """Image to ground at a given height (METHODS §1): ``(sample, line, h) -> (lon, lat)``.

        Vectorised Newton iteration on the 2x2 system, started from the ground domain: a cubic inverse fitted over
        the RPC's ground cube inside its image, the cube's affine inverse outside it (cropped RPCs whose offsets
        lie far from the image), damped in ground space.
        Points that do not converge to ``tol_px`` within ``max_iter`` steps are returned as NaN and counted
        (logged, and returned as :class:`LocalizationStats` when ``full_output=True``).
        """
        sample, line, h = np.broadcast_arrays(_as_float_array(sample), _as_float_array(line), _as_float_array(h))
        shape = sample.shape
        shift = self._pixel_shift(pixel_convention)
        s_, l_, h_ = sample.ravel(), line.ravel(), h.ravel()
        lon, lat, ok = np.empty(s_.size), np.empty(s_.size), np.empty(s_.size, dtype=bool)
        iterations = []

        def block(sl):
            """Solve the points ``sl`` chunk by chunk, into their places in lon, lat, ok (no per-block arrays:
            fresh ones faulted in 1,700 pages per 200k points here, 12 % of the CPU)."""
            for i in range(sl.start, max(sl.stop, 1), LOCALIZE_CHUNK):
                c = slice(i, min(i + LOCALIZE_CHUNK, sl.stop))
                x = (s_[c] - shift - self.samp_off) / self.samp_scale
                y = (l_[c] - shift - self.line_off) / self.line_scale
                H = (h_[c] - self.height_off) / self.height_scale
                L, P, ok[c], iters = self._localize_normalised(x, y, H, tol_px, max_iter)
                iterations.append(iters)
                np.add(np.multiply(L, self.long_scale, out=L), self.long_off, out=lon[c])
                np.add(np.multiply(P, self.lat_scale, out=P), self.lat_off, out=lat[c])
                if not ok[c].all():
                    lon[c][~ok[c]] = np.nan
                    lat[c][~ok[c]] = np.nan

        map_blocks(block, s_.size)
        iters = max(iterations)
        n_failed = ok.size - int(np.count_nonzero(ok))
        if n_failed:
            log.info("RPC localisation: %d of %d points did not converge (NaN)", n_failed, ok.size)
        out = (_shape_out(lon, shape), _shape_out(lat, shape))
        if full_output:
            s_g = s_ - shift + GDAL_PIXEL_OFFSET
            l_g = l_ - shift + GDAL_PIXEL_OFFSET
            return out + (self._localization_stats(s_g, l_g, h_, lon, lat, iters),)
        return out

    # ------------------------------------------------------------------ SensorModelMixin hooks (flat, GDAL px)
    def _project_gdal(self, lon, lat, h):
        return self.project(lon, lat, h)

    def _localize_gdal(self, sample, line, h):
        return self.localize(sample, line, h)

    def localize_dem(self, sample: ArrayLike, line: ArrayLike, dem, *, pixel_convention: str = "gdal",
                     tol_m: float = 1e-4, max_iter: int = 30, full_output: bool = False):
        """Intersect the lines of sight with a DEM (METHODS §1-§2): ``(sample, line, dem) -> (lon, lat, h)``.

        ``sample, line`` in GDAL's convention (centre of the first pixel at 0.5) unless ``pixel_convention="rpc"``.
        ``dem`` is a :class:`gdal_gf4cal.dem.DEM` or a constant height in metres. The returned point satisfies
        ``project(lon, lat, h) == (sample, line)`` to 1e-8 px and ``|DEM(lon, lat) - h| <= tol_m``; NaN where
        there is no intersection (off the DEM, in a void), counted with ``full_output=True``.

        ``dem`` may be anything :meth:`gdal_gf4cal.dem.DEM.from_user_input` accepts. With ``full_output=True`` a
        fourth item, :class:`~gdal_gf4cal.sensor.LocalizationStats`.

        Delegates to :func:`gdal_gf4cal.localization.localize_dem`, whose RPC fast path (a cubic model of the line
        of sight, exact in value and slope at one height; Newton steps for the height on it with the DEM's public
        gradient sampler; then an exact polish) solves most points; the rest take its generic height iteration
        (bracketing on steep terrain).
        """
        return SensorModelMixin.localize_dem(self, sample, line, dem, pixel_convention=pixel_convention,
                                             full_output=full_output, tol_m=tol_m, max_iter=max_iter)

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


#: Plausibility limits of :func:`validate_rpc` (METHODS §1): generous, they only refuse what no sensor produces.
_LIMITS = {"lat_off": 90.0, "long_off": 360.0, "height_off": 1e5}
_SCALE_LIMITS = {"lat_scale": (1e-7, 90.0), "long_scale": (1e-7, 360.0), "height_scale": (1e-3, 1e5),
                 "line_scale": (1e-3, 1e8), "samp_scale": (1e-3, 1e8)}
#: Largest |coefficient| accepted: RPC00B coefficients act on normalised coordinates, real ones stay below ~10.
_MAX_COEFF = 1e6


def validate_rpc(rpc: "RPCModel") -> "RPCModel":
    """Refuse a physically implausible RPC with a one-line :class:`RPCFormatError` naming the reason (METHODS §1).

    Checks |LAT_OFF| <= 90, |LONG_OFF| <= 360, |HEIGHT_OFF| <= 1e5 m; scales finite and of plausible magnitude
    (negative scales stay legal; |LAT_SCALE| of 1e-300 does not: it makes localisation return finite wrong values);
    every coefficient finite and |c| <= 1e6; a 9 x 9 x 5 grid of the RPC's normalised ground cube projects to finite
    image points. Called by every reader path (:meth:`RPCModel.from_gdal_metadata`, hence
    :meth:`RPCModel.from_file`). Returns ``rpc``.
    """
    where = rpc._where()
    for name, limit in _LIMITS.items():
        value = getattr(rpc, name)
        if abs(value) > limit:
            raise RPCFormatError(f"RPC{where}: {name.upper()} = {value:g} is impossible (|{name.upper()}| must be "
                                 f"<= {limit:g}); check the file")
    for name, (lo, hi) in _SCALE_LIMITS.items():
        value = abs(getattr(rpc, name))
        if not lo <= value <= hi:
            raise RPCFormatError(f"RPC{where}: {name.upper()} = {getattr(rpc, name):g} is implausible (|"
                                 f"{name.upper()}| must lie in [{lo:g}, {hi:g}]); check the file")
    for name, key in _GDAL_COEFF_KEYS.items():
        worst = float(np.max(np.abs(getattr(rpc, name))))
        if worst > _MAX_COEFF:
            raise RPCFormatError(f"RPC{where}: {key} holds a coefficient of magnitude {worst:.3g} (> {_MAX_COEFF:g}"
                                 "); the RPC is corrupt")
    g = np.linspace(-1.0, 1.0, 9)
    L, P, H = (a.ravel() for a in np.meshgrid(g, g, np.linspace(-1.0, 1.0, 5), indexing="ij"))
    with np.errstate(all="ignore"):
        x, y = rpc._project_normalised(L, P, H)
    bad = ~(np.isfinite(x) & np.isfinite(y))
    if np.any(bad):
        raise RPCFormatError(f"RPC{where}: {int(bad.sum())} points of its ground cube do not project to finite "
                             "image points (a denominator vanishes); the RPC is corrupt")
    return rpc


def _parse_number(value, key: str, where: str) -> float:
    try:
        text = str(value).strip().split()[0] if isinstance(value, str) else value
        number = float(text)
    except (ValueError, IndexError, TypeError, OverflowError):
        raise RPCFormatError(f"RPC{where}: {key} is not a number ({str(value)[:40]!r})") from None
    if not math.isfinite(number):
        raise RPCFormatError(f"RPC{where}: {key} is not a finite number ({value!r})")
    return number


def _fmt(value: float) -> str:
    """17 significant digits: enough for a float64 to read back bit-identical."""
    return repr(float(value)) if abs(float(value)) >= 1e-4 or value == 0 else f"{float(value):.17g}"
