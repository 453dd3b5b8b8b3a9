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
from typing import Dict, NamedTuple, Optional, Tuple, Union

import numpy as np

from ._rpc_poly import (_CHUNK, _EXPONENTS, DERIVATIVE_MATRICES, TERMS, fill_monomials,  # noqa: F401
                        monomial_chunks, monomial_derivatives, monomial_views, monomials, poly_product, scratch)
from .errors import RPCFormatError
from .rpc_io import read_rpc_metadata, write_rpb, write_rpc_txt
from .sensor import GDAL_PIXEL_OFFSET, LocalizationStats, SensorModelMixin, pixel_shift  # noqa: F401
from .threads import (BLAS_SERIAL_SIZE, COLUMN_GROUP, blas_is_serial, block_slices, map_blocks, num_threads,
                      product_into, split_points)

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


#: Points per Newton solve of :meth:`RPCModel.localize` (a block of the thread pool is solved in such chunks,
#: :func:`_localize_chunk`): its buffer (41 rows, 5.4 MB) stays in the last-level cache: as fast as 8192 and 5 %
#: faster than 32768 (107, 108, 114 ms per 1e6 points, least CPU of 11 runs of one thread on the loaded machine),
#: while its Python (~0.1 ms a solve: ~50 NumPy calls, which hold the GIL) stays a twentieth of the solve's ~2 ms.
#: Chunks small enough for a core's 512 KB L2 (<= ~1,400 points at ~370 bytes a point) do not pay: 1-4k points
#: cost 1.7-2.6x CPU per point on one thread, and 2 threads inflate them more (GIL hand-offs per NumPy call);
#: beside a twin process 16384 cost ~1.1x its CPU alone, 2-4k ~1.04x (bench/bench_chunks.py, loaded machine).
#: Every point is solved on its own: the same bits for any size.
LOCALIZE_CHUNK = 16384

#: Columns of one (4, 20) x (20, k) product of the projection kernel outside a BLAS-serial scope: the most OpenBLAS
#: computes on the calling thread (:data:`~gdal_gf4cal.threads.BLAS_SERIAL_SIZE`: 80 k <= 4 x 65536); inside one
#: (:func:`~gdal_gf4cal.threads.blas_is_serial`) a chunk is one product: the same bits (every product a
#: :func:`~gdal_gf4cal.threads.product_into`, in whole column groups), fewer calls.
_PROJECT_GEMM = BLAS_SERIAL_SIZE // 80 // COLUMN_GROUP * COLUMN_GROUP
#: Points per chunk of the projection kernel (five products) when its blocks run over the thread pool: a whole block
#: of the pool, one chunk (12-14 NumPy calls, which hold the GIL): larger than L2 (the (20, chunk) monomials take
#: 5.2 MB) but with 2 threads 1.3-1.5x the speed of 8192-point chunks (2e6 points: 2 threads / 1 thread 1.57-1.62x
#: against 1.09-1.22x; the threads wait for each other's NumPy calls, four times as many). A divisor of
#: :data:`~gdal_gf4cal.threads.BLOCK`: split or not, a point lies in the same product.
PROJECT_CHUNK = 32768
#: Points per chunk of the projection kernel on one thread (``GF4CAL_NUM_THREADS=1``, a Dask worker, a block or a
#: tile already on the pool, fewer points than a block): the (20, chunk) monomials (1.3 MB) stay near L2 and every
#: product is at least NumPy's buffer size (``np.getbufsize()``, 8192: below it a broadcast product is copied through
#: buffers, 2-4x the cost per element): 1.2-2x the one-thread speed of 32768-point chunks (2e6 and 2e5 points), 4096
#: 0.6x of 8192. A divisor of :data:`PROJECT_CHUNK`.
SERIAL_PROJECT_CHUNK = 8192


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
        """Normalised (x, y) = (sample, line) ratios for flat normalised inputs, chunked (one chunk: fresh arrays,
        without the reused buffers' context managers, a small call's fixed cost; the same product on each column)."""
        n = L.size
        if n <= 64:
            v = poly_product(self._coeffs, monomials(L, P, H))
            return v[0] / v[1], v[2] / v[3]
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
        threaded = len(block_slices(lon.size)) > 1 and num_threads() > 1
        chunk = PROJECT_CHUNK if threaded else SERIAL_PROJECT_CHUNK
        # Each block writes its own columns of ``out`` (no per-block results joined afterwards).
        map_blocks(lambda sl: self._project_into(lon[sl], lat[sl], h[sl], C, out[:, sl], chunk), lon.size)
        return _shape_out(out[0], shape), _shape_out(out[1], shape)

    def _project_into(self, lon, lat, h, C, out, chunk: int) -> None:
        """:meth:`project` of flat arrays into ``out`` (2, n) with the coefficients of :meth:`_project_coeffs`: per
        chunk of ``chunk`` points (:data:`PROJECT_CHUNK` over the pool, :data:`SERIAL_PROJECT_CHUNK` alone), in one
        reused (20, chunk) monomial buffer, the ground offsets subtracted into its rows 1-3 (longitudes modulo 360
        when a chunk spans the antimeridian), the monomials in place (:func:`fill_monomials`), the (4, 20) x (20,
        chunk) product into a reused (4, chunk) buffer (in slices of :data:`_PROJECT_GEMM` columns unless BLAS is
        held on the calling thread, :func:`blas_is_serial`; :func:`~gdal_gf4cal.threads.product_into` keeps each
        within BLAS's small-matrix kernel), one division: 12-14 NumPy calls per chunk in two buffers
        the thread keeps (:func:`scratch`), the same bits (the same pixels as normalising whole arrays to 1e-11
        px)."""
        c = max(1, min(lon.size, chunk))
        off = (self.long_off, self.lat_off, self.height_off)
        with scratch(20, c) as m, scratch(4, c) as v:
            m[0] = 1.0
            self._project_chunks(lon, lat, h, off, C, m, v, out)

    @staticmethod
    def _project_chunks(lon, lat, h, off, C, m, v, out) -> None:
        """The chunk loop of :meth:`_project_into` in the buffers ``m`` (20, chunk) and ``v`` (4, chunk)."""
        n, c = lon.size, m.shape[1]
        step = c if blas_is_serial() else _PROJECT_GEMM
        views = monomial_views(m)
        for i in range(0, n, c):
            j = min(i + c, n)
            if j - i < c:
                m, v = m[:, :j - i], v[:, :j - i]
                views = monomial_views(m)
            dlon = np.subtract(lon[i:j], off[0], out=m[1])
            if dlon.min() < -180.0 or dlon.max() > 180.0:    # across the antimeridian: longitudes modulo 360
                np.copyto(dlon, np.where(np.abs(dlon) > 180.0, (dlon + 180.0) % 360.0 - 180.0, dlon))
            np.subtract(lat[i:j], off[1], out=m[2])
            np.subtract(h[i:j], off[2], out=m[3])
            fill_monomials(m, views)
            for a in range(0, j - i, step):
                product_into(C, m[:, a:a + step], v[:, a:a + step])
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

    def _localize_kernel(self, shift: float) -> "_LocalizeKernel":
        """The coefficients of :meth:`localize`'s chunk solver (:func:`_localize_chunk`) for a pixel shift, in the
        raw offsets ``(s - SAMP_OFF - shift, l - LINE_OFF - shift, h - HEIGHT_OFF)`` the solver's monomials hold
        (the scales folded into the coefficients: no normalising pass over the points): the start cubic
        (:attr:`_approximate_inverse`) and its frame, and the (12, 20) rows of the sample and line numerators times
        their image scales (pixels), the denominators, and their d/dL and d/dP (normalised L, P; heights in metres)."""
        key = float(shift)
        cache = self.__dict__.setdefault("_localize_kernel_cache", {})
        if key in cache:
            return cache[key]
        e = np.array(_EXPONENTS, dtype=float)
        ss, ls, hs = self.samp_scale, self.line_scale, self.height_scale
        (cx, sx, cy, sy), _, affine = self._inverse_fit
        start = self._approximate_inverse / np.prod(np.array([ss, ls, hs]) ** e, axis=1)
        bounds = np.array([[(cx - 1.25 * sx) * ss, (cx + 1.25 * sx) * ss], [(cy - 1.25 * sy) * ls,
                           (cy + 1.25 * sy) * ls], [-1.5 * abs(hs), 1.5 * abs(hs)]])
        bounds.sort(axis=1)                                      # negative scales swap a frame's bounds
        C = self._coeffs
        values = np.vstack([C[0] * ss, C[2] * ls, C[1], C[3]])   # sample and line numerators in pixels, dens
        dL, dP = values @ DERIVATIVE_MATRICES[0], values @ DERIVATIVE_MATRICES[1]
        rows = np.vstack([values, dL[0:2], dP[0:2], dL[2:4], dP[2:4]]) / hs ** e[:, 2]
        v = rows[:, 0]                                           # at the cube's centre: its orientation
        q = v[0:2] / v[2:4]
        J = (v[4:8].reshape(2, 2) - q * v[8:12].reshape(2, 2)) / v[2:4]
        kernel = _LocalizeKernel(
            offsets=(self.samp_off + key, self.line_off + key, self.height_off), start=start,
            lo=tuple(bounds[:, 0].tolist()), hi=tuple(bounds[:, 1].tolist()), frame=(cx, sx, cy, sy), affine=affine,
            scales=(ss, ls, hs), rows=rows, values=rows[0:4].copy(),
            ground=np.array([[self.long_scale], [self.lat_scale]]), ground_off=np.array([[self.long_off],
                                                                                          [self.lat_off]]),
            orientation=float(np.sign(J[0, 0] * J[1, 1] - J[1, 0] * J[0, 1])))
        cache[key] = kernel
        return kernel

    def localize(self, sample: ArrayLike, line: ArrayLike, h: ArrayLike, *, pixel_convention: str = "gdal",
                 tol_px: float = 1e-8, max_iter: int = 20, full_output: bool = False):
        """Image to ground at a given height (METHODS §1): ``(sample, line, h) -> (lon, lat)``.

        Vectorised Newton iteration on the 2x2 system, started from the ground domain: a cubic inverse fitted over
        the RPC's ground cube inside its image, the cube's affine inverse outside it (cropped RPCs whose offsets
        lie far from the image), damped in ground space (:func:`_localize_chunk`).
        Points that do not converge to ``tol_px`` within ``max_iter`` steps are returned as NaN and counted
        (logged, and returned as :class:`LocalizationStats` when ``full_output=True``).
        """
        sample, line, h = np.broadcast_arrays(_as_float_array(sample), _as_float_array(line), _as_float_array(h))
        shape = sample.shape
        shift = self._pixel_shift(pixel_convention)
        kernel = self._localize_kernel(shift)
        s_, l_, h_ = sample.ravel(), line.ravel(), h.ravel()
        lonlat, ok = np.empty((2, s_.size)), np.empty(s_.size, dtype=bool)
        iterations = []

        def block(sl):
            """Solve the points ``sl`` chunk by chunk into their columns of lonlat and ok (no per-block arrays:
            fresh ones faulted in 1,700 pages per 200k points here, 12 % of the CPU)."""
            for i in range(sl.start, max(sl.stop, 1), LOCALIZE_CHUNK):
                c = slice(i, min(i + LOCALIZE_CHUNK, sl.stop))
                iterations.append(_localize_chunk(kernel, s_[c], l_[c], h_[c], lonlat[:, c], ok[c], tol_px,
                                                  max_iter))

        map_blocks(block, s_.size)
        iters = max(iterations)
        lon, lat = lonlat
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


class _LocalizeKernel(NamedTuple):
    """:meth:`RPCModel._localize_kernel`: what :func:`_localize_chunk` solves with."""
    offsets: tuple               # subtracted from (sample, line, h): the raw offsets the monomials hold
    start: np.ndarray            # (2, 20) start cubic of the raw offsets
    lo: tuple                    # its frame (raw offsets of sample, line, h): inside it the cubic, outside the affine
    hi: tuple
    frame: tuple                 # (cx, sx, cy, sy) of :attr:`RPCModel._inverse_fit` and its affine (2, 4)
    affine: np.ndarray
    scales: tuple                # samp, line and height scales
    rows: np.ndarray             # (12, 20): numerators (px) and denominators, their d/dL, d/dP
    values: np.ndarray           # rows[0:4], contiguous
    ground: np.ndarray           # (2, 1) long and lat scales, and offsets
    ground_off: np.ndarray
    orientation: float           # sign of det d(s, l)/d(L, P) at the cube's centre


#: Rows of the work buffer of :func:`_localize_chunk` (:class:`_LocViews`); the [[1, -1], [-1, 1]] signs of a 2x2
#: adjugate.
_LOC_ROWS = 41
_LOC_SIGN = np.array([[1.0, -1.0], [-1.0, 1.0]])[:, :, None]


class _LocViews:
    """The arrays of :func:`_localize_chunk` as views of one (:data:`_LOC_ROWS`, k) buffer: its first 13 rows are
    a point's whole state (target, residual, inverse Jacobian, determinant, the monomials' 1, L, P, h), gathered
    in one call when converged points leave (:meth:`compacted`); the temporaries live in the polynomials' rows
    (dead once the Jacobian is inverted): a smaller buffer stays in cache."""
    __slots__ = ("buf", "state", "T", "q", "Inv", "det", "M", "V", "J", "d", "a", "fill")

    def __init__(self, buf: np.ndarray, k: int):
        b = buf[:, :k]
        self.buf, self.state = buf, b[0:13]
        self.T, self.q = b[0:2], b[2:4]                  # target (px offsets); values, then residual
        self.Inv, self.det = b[4:8].reshape(2, 2, k), b[8]
        self.M, self.V = b[9:29], b[29:41]               # monomials (rows 1-2: the unknowns L, P); polynomials
        self.J, self.d, self.a = b[33:37].reshape(2, 2, k), b[37:39], b[39:41]     # V[4:8], V[8:10], V[10:12]
        self.fill = monomial_views(self.M)               # the monomials are filled three times a chunk

    def compacted(self, cols: np.ndarray) -> "_LocViews":
        """The views on the points ``cols`` only, their state moved to the first columns."""
        self.buf[0:13, :cols.size] = self.state[:, cols]
        return _LocViews(self.buf, cols.size)


def _localize_chunk(K: _LocalizeKernel, s, l, h, out, ok, tol: float, max_iter: int) -> int:
    """:meth:`RPCModel.localize` of the flat points ``s, l, h`` into ``out`` (2, n: lon, lat; NaN where not
    converged) and ``ok``; returns the iterations. Chord Newton in one reused buffer of the thread
    (:func:`scratch`), every step on stacked (2, n) and (2, 2, n) arrays (each NumPy call holds the GIL, the cost a
    second thread pays for; ~50 calls per chunk where every point settles in two iterations, the common case).

    Started from the ground domain (:func:`_loc_start`). The Jacobian is evaluated at the start (within a
    fraction of a pixel of the solution inside the image of the ground cube) and refreshed every third step, every
    step after the third (points started outside the cube, cropped RPCs), so most steps cost a single projection.
    The start is always stepped once; from the second iteration a point whose residual is within ``tol`` px on
    both axes settles there (:func:`_loc_settle`). Steps are damped in ground space (:func:`_loc_damp`). A
    solution is accepted within ``_MAX_EXTRAPOLATION`` normalised units of the cube and, after more than two
    steps, with the cube's orientation (the sign of the Jacobian determinant at its centre): other roots are
    polynomial artefacts. Every point is solved on its own: the same bits in any chunk."""
    n = s.size
    if n == 0:
        return 1
    with scratch(_LOC_ROWS, n) as buf:
        w = _LocViews(buf, n)
        np.subtract(s, K.offsets[0], out=w.M[1])
        np.subtract(l, K.offsets[1], out=w.M[2])
        np.subtract(h, K.offsets[2], out=w.M[3])
        np.copyto(w.T, w.M[1:3])
        w.M[0] = 1.0
        _loc_start(K, w)
        _loc_jacobian(K.rows, w)
        idx = None                  # the chunk's points still solved (None: all, in place)
        for it in range(1, max_iter + 1):
            np.subtract(w.T, w.q, out=w.q)                       # the residual (px)
            if it > 1 or max_iter == 1:
                if idx is None and np.abs(w.q, out=w.a).max() <= tol:     # the common end: all settle at once
                    _loc_accept_all(K, w, out, ok, it)
                    return it
                w, idx = _loc_settle(K, w, idx, out, ok, tol, it)
                if w is None:
                    return it
            _loc_step(w)
            if it % 3 == 0 or it > 3:
                _loc_jacobian(K.rows, w)
            else:
                _loc_project(K.values, w)
        if idx is None:
            out[:] = np.nan
            ok[:] = False
        return max_iter


def _loc_start(K: _LocalizeKernel, w: _LocViews) -> None:
    """Newton start (L, P) into the monomials' rows 1-2 from the raw offsets there: the cubic inverse inside the
    image of the ground cube (within a small fraction of a pixel), the ground-cube affine outside it (cropped
    RPCs, points off the image; tested chunk-wise first: two reductions when every point is inside)."""
    D = w.M[1:4]
    lo, hi = D.min(axis=1).tolist(), D.max(axis=1).tolist()
    fill_monomials(w.M, w.fill)
    S = poly_product(K.start, w.M, out=w.V[0:2])
    if not (lo[0] >= K.lo[0] and lo[1] >= K.lo[1] and lo[2] >= K.lo[2] and hi[0] <= K.hi[0] and hi[1] <= K.hi[1]
            and hi[2] <= K.hi[2]):                        # NaN: never inside
        inside = ((D[0] >= K.lo[0]) & (D[0] <= K.hi[0]) & (D[1] >= K.lo[1]) & (D[1] <= K.hi[1])
                  & (D[2] >= K.lo[2]) & (D[2] <= K.hi[2]))
        out = np.flatnonzero(~inside)
        (cx, sx, cy, sy), A = K.frame, K.affine
        uo, vo = (D[0, out] / K.scales[0] - cx) / sx, (D[1, out] / K.scales[1] - cy) / sy
        ho = D[2, out] / K.scales[2]
        S[:, out] = A[:, 0:1] + A[:, 1:2] * uo + A[:, 2:3] * vo + A[:, 3:4] * ho
    np.copyto(w.M[1:3], S)


def _loc_jacobian(rows: np.ndarray, w: _LocViews) -> None:
    """Values (px) and the inverse Jacobian d(L, P)/d(s, l) with its determinant at the monomials' (L, P): one
    product, nine stacked calls (J[k, i] = d(s, l)_i / d(L, P)_k; its inverse from the adjugate)."""
    fill_monomials(w.M, w.fill)
    V = poly_product(rows, w.M, out=w.V)
    k = V.shape[1]
    q = np.divide(V[0:2], V[2:4], out=w.q)
    dens = np.multiply(V[8:12].reshape(2, 2, k), q, out=V[8:12].reshape(2, 2, k))
    J = np.subtract(w.J, dens, out=w.J)                          # the numerators' derivatives, in place
    np.divide(J, V[2:4], out=J)
    p = np.multiply(J[0], J[1, ::-1], out=w.d)                  # s_L l_P, l_L s_P
    np.subtract(p[0], p[1], out=w.det)
    np.divide(_LOC_SIGN, w.det, out=w.Inv)
    np.multiply(w.Inv, J[::-1, ::-1], out=w.Inv)


def _loc_project(values: np.ndarray, w: _LocViews) -> None:
    """The values (px) at the monomials' (L, P): one product, one division."""
    fill_monomials(w.M, w.fill)
    V = poly_product(values, w.M, out=w.V[0:4])
    np.divide(V[0:2], V[2:4], out=w.q)


def _loc_step(w: _LocViews) -> None:
    """One Newton step of (L, P) from the residual (in ``w.q``) with the inverse Jacobian, damped when any
    component exceeds half a normalised unit (:func:`_loc_damp`)."""
    t = np.multiply(w.Inv, w.q[None], out=w.J)
    d = np.add(t[:, 0], t[:, 1], out=w.d)
    if d.max() > 0.5 or d.min() < -0.5:
        _loc_damp(w.M[1:3], d)
    np.add(w.M[1:3], d, out=w.M[1:3])


def _loc_damp(LP: np.ndarray, d: np.ndarray) -> None:
    """Steps damped in ground space, in place: at most half a normalised unit, or half the distance from the
    cube's centre when the point lies farther out (rare: only these points pay for it)."""
    step = np.maximum(np.abs(d[0]), np.abs(d[1]))
    big = np.flatnonzero(step > 0.5)
    limit = 0.5 * np.maximum(1.0, np.maximum(np.abs(LP[0, big]), np.abs(LP[1, big])))
    d[:, big] *= np.minimum(1.0, limit / step[big])


def _loc_settle(K, w: _LocViews, idx, out, ok, tol: float, it: int):
    """Settle the points whose residual (``w.q``) is within ``tol`` on both axes (:func:`_loc_accept`), drop the
    non-finite ones, keep solving the rest: returns their views (None: none left) and their columns in the
    chunk. The first time a point leaves, the chunk's outputs are set to NaN, False."""
    amax = np.maximum(np.abs(w.q[0]), np.abs(w.q[1]))
    done = amax <= tol
    keep = ~done & np.isfinite(amax)
    if keep.all():
        return w, idx
    if idx is None:
        out[:] = np.nan
        ok[:] = False
        idx = np.arange(amax.size)
    cols = np.flatnonzero(done)
    if cols.size:
        _loc_accept(K, w, cols, idx[cols], out, ok, it)
    kept = np.flatnonzero(keep)
    if kept.size == 0:
        return None, idx
    return w.compacted(kept), idx[kept]


def _loc_accept(K, w: _LocViews, cols, where, out, ok, it: int) -> None:
    """The settled points ``cols`` of the views into ``out`` and ``ok`` at ``where``: accepted within
    ``_MAX_EXTRAPOLATION`` of the cube and, after more than two steps, with its orientation; else NaN."""
    LP = w.M[1:3, cols]
    good = np.maximum(np.abs(LP[0]), np.abs(LP[1])) <= _MAX_EXTRAPOLATION
    if it > 2:
        good &= np.sign(w.det[cols]) == K.orientation
    out[:, where] = np.where(good, LP * K.ground + K.ground_off, np.nan)
    ok[where] = good


def _loc_accept_all(K, w: _LocViews, out, ok, it: int) -> None:
    """Every point of the chunk settled at once: lon, lat in two calls, and accepted in two reductions unless a
    point lies farther than ``_MAX_EXTRAPOLATION`` or took more than two steps (:func:`_loc_accept`)."""
    LP = w.M[1:3]
    np.add(np.multiply(LP, K.ground, out=out), K.ground_off, out=out)
    if it <= 2 and LP.max() <= _MAX_EXTRAPOLATION and LP.min() >= -_MAX_EXTRAPOLATION:
        ok[:] = True
    else:
        cols = np.arange(LP.shape[1])
        _loc_accept(K, w, cols, cols, out, ok, it)


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
