"""Resample a reference (an orthophoto, or another raw image with its sensor model) into the raw image's geometry
through RPC + DEM (automatic GCP collection, raw-to-raw matching).

For a stack of regular grids of raw-image positions (one grid per matching window) every grid node is localised
on the DEM through the RPC (``localize_dem``) and mapped to reference pixel coordinates by the reference's
``ground_to_pixel``: for an ortho (:class:`ReferenceImage`) the reference's CRS (pyproj) and inverse geotransform,
for a raw reference (:class:`RawReference`) its sensor model's ``project``; the reference is sampled there with a
cubic spline. The result shows, at
raw position ``u``, the ground that the RPC says is imaged at ``u``: comparing it with the raw image measures the
RPC's error (see :mod:`gdal_gf4cal.matching.collect`).

- Geometry is exact on a sub-grid of nodes (every ``geometry_step`` samples) and interpolated bilinearly in
  between: the mapping is smooth at the scale of a few pixels, and localisation is the expensive part.
- Reads are windowed: one ``ReadAsArray`` of the bounding box the grids need, never the whole reference.
- A reference much finer than the grid spacing is first read decimated by GDAL (``average`` resampling, which
  uses its overviews when present) and then low-passed with a Gaussian, so the resampled window has about the
  raw image's bandwidth instead of aliasing (the raw pixel itself integrates the ground).
"""
from __future__ import annotations

import math
import os
from typing import Tuple

import numpy as np
from osgeo import gdal
from scipy import ndimage

from .._gdal import with_gdal_exceptions
from ..errors import Gf4calError
from ..geodesy import crs_transformer

__all__ = ["ReferenceImage", "RawReference", "cut_boxes", "grid_nodes", "read_block", "read_boxes", "reference_on_grids",
           "whole_pixel_shift"]

#: Standard deviation (in grid spacings) of the anti-alias low-pass applied to a finer reference: about the
#: Gaussian equivalent of a pixel's box integration (1/sqrt(12) ~= 0.29) plus optics.
ANTIALIAS_SIGMA = 0.45

#: Largest deviation (px) of the reference positions from one whole-pixel translation of the grid below which the
#: reference is read as it is instead of being resampled (a reference on the raw image's own pixel grid, as two
#: orthos of one tiling: interpolating at whole pixels returns the pixels, to this fraction of their gradient).
IDENTITY_TOL = 1e-4

#: The whole-pixel test (:data:`IDENTITY_TOL`) first localises every this-many-th exact node only (and the last):
#: a mapping that is not one whole-pixel translation shows it there already, and one that is is then read at
#: once without localising the rest (about ``1 / PROBE_EVERY**2`` of the nodes).
PROBE_EVERY = 4

#: Extra cells read around each block of the batched path so that the spline prefilter's (mirror) boundary stays
#: away from the samples: its influence decays as 0.27^k.
_PAD = 4


class ReferenceImage:
    """Windowed reader of one band of a reference orthophoto (any GDAL raster with a geotransform and CRS).

    ``lonlat_to_pixel(lon, lat)`` gives continuous pixel coordinates (GDAL convention: the centre of the first
    pixel at 0.5, 0.5); ``read(x0, y0, nx, ny, decimation)`` returns float32 with NaN on no-data.
    Objects are cheap; the dataset is opened lazily and not pickled (a worker reopens it from ``path``).
    """

    def __init__(self, path, band: int = 1):
        self.path = os.fspath(path)
        self.band = int(band)
        self._ds = None
        ds = self._open()
        self.width, self.height = ds.RasterXSize, ds.RasterYSize
        gt = ds.GetGeoTransform(can_return_null=True)
        if gt is None:
            raise Gf4calError(f"reference {self.path} has no geotransform; give an orthorectified, "
                              "georeferenced image (e.g. a GeoTIFF)")
        self.geotransform = tuple(gt)
        self._inv = gdal.InvGeoTransform(gt)
        if self._inv is None:
            raise Gf4calError(f"reference {self.path} has a degenerate geotransform (zero pixel size); fix it "
                              "with gdal_edit.py -a_ullr or use a properly georeferenced orthophoto")
        wkt = ds.GetProjection()
        if not wkt:
            raise Gf4calError(f"reference {self.path} has no CRS; assign one (gdal_edit.py -a_srs EPSG:...)")
        self.crs_wkt = wkt
        b = ds.GetRasterBand(self.band)
        self.nodata = b.GetNoDataValue()
        self._transformer = None

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_ds"] = None
        state["_transformer"] = None
        return state

    @with_gdal_exceptions
    def _open(self):
        if self._ds is None:
            try:
                self._ds = gdal.Open(self.path)
            except RuntimeError as exc:
                raise Gf4calError(f"cannot open reference {self.path}: {str(exc).splitlines()[0]}") from None
            if self.band < 1 or self.band > self._ds.RasterCount:
                raise Gf4calError(f"reference {self.path} has no band {self.band}; choose a band from 1 to "
                                  f"{self._ds.RasterCount}")
        return self._ds

    @property
    def transformer(self):
        if self._transformer is None:
            self._transformer = crs_transformer("EPSG:4326", self.crs_wkt)
        return self._transformer

    def lonlat_to_pixel(self, lon, lat) -> Tuple[np.ndarray, np.ndarray]:
        """Continuous reference pixel coordinates (GDAL convention) of WGS84 (lon, lat); NaN stays NaN."""
        lon = np.asarray(lon, dtype=float)
        lat = np.asarray(lat, dtype=float)
        X, Y = self.transformer.transform(lon, lat)
        X = np.asarray(X, dtype=float)
        Y = np.asarray(Y, dtype=float)
        g = self._inv
        return g[0] + g[1] * X + g[2] * Y, g[3] + g[4] * X + g[5] * Y

    def ground_to_pixel(self, lon, lat, h=None) -> Tuple[np.ndarray, np.ndarray]:
        """Reference pixel (GDAL convention) showing the ground point; an ortho ignores the height."""
        return self.lonlat_to_pixel(lon, lat)

    def read(self, x0: int, y0: int, nx: int, ny: int, decimation: int = 1) -> np.ndarray:
        """Block ``[x0, x0 + nx) x [y0, y0 + ny)`` (full-resolution pixels), averaged by ``decimation``.

        Parts outside the raster and no-data are NaN. The output has ``ceil(n / decimation)`` pixels per axis;
        decimated pixel ``i`` covers full-resolution pixels ``[x0 + i*d, x0 + (i+1)*d)``.
        """
        band = self._open().GetRasterBand(self.band)
        return read_block(band, self.width, self.height, self.nodata, x0, y0, nx, ny, decimation)

    def inside(self, sample, line, margin: float = 0.0) -> np.ndarray:
        """Pixel positions at least ``margin`` px inside the raster (NaN is outside)."""
        s, l = np.asarray(sample, dtype=float), np.asarray(line, dtype=float)
        with np.errstate(invalid="ignore"):
            return (s >= margin) & (s <= self.width - margin) & (l >= margin) & (l <= self.height - margin)


class RawReference(ReferenceImage):
    """A raw (not orthorectified) image as the matching reference: ground -> pixel through its sensor model.

    ``model`` is an :class:`~gdal_gf4cal.RPCModel` or any model on the sensor contract
    (:class:`gdal_gf4cal.sensor.SensorModel`); ``ground_to_pixel(lon, lat, h) = model.project(lon, lat, h)`` (GDAL
    convention), so :func:`reference_on_grids` resamples the reference raw image into another raw image's
    geometry through both models and the DEM (raw-to-raw matching, METHODS §8 tie points, §9 pan-MS). A finer
    reference (pan for an MS image) is decimated and low-passed exactly as a finer ortho. Same reader and
    pickling as :class:`ReferenceImage` (no geotransform or CRS needed).
    """

    def __init__(self, path, model, band: int = 1):
        self.path = os.fspath(path)
        self.band = int(band)
        self.model = model
        self._ds = None
        self._transformer = None
        ds = self._open()
        self.width, self.height = ds.RasterXSize, ds.RasterYSize
        self.nodata = ds.GetRasterBand(self.band).GetNoDataValue()

    def with_model(self, model) -> "RawReference":
        """The same opened reader with another sensor model (cheap: shares the dataset)."""
        other = object.__new__(RawReference)
        other.__dict__.update(self.__dict__)
        other.model = model
        return other

    def lonlat_to_pixel(self, lon, lat):  # pragma: no cover - a raw image needs the height
        raise TypeError("a raw reference maps (lon, lat, h): use ground_to_pixel")

    def ground_to_pixel(self, lon, lat, h=None) -> Tuple[np.ndarray, np.ndarray]:
        """Pixel (GDAL convention) of the reference raw image imaging the ground point (``model.project``)."""
        s, l = self.model.project(lon, lat, h)
        return np.asarray(s, dtype=float), np.asarray(l, dtype=float)


def read_block(band, width: int, height: int, nodata, x0: int, y0: int, nx: int, ny: int,
               decimation: int = 1) -> np.ndarray:
    """One windowed read of a GDAL band: block ``[x0, x0 + nx) x [y0, y0 + ny)``, averaged by ``decimation``.

    float32, NaN outside the raster (``width x height``) and on ``nodata``. With ``decimation > 1`` GDAL does
    the averaging while reading (``buf_xsize/buf_ysize`` with ``average`` resampling; it ignores no-data pixels
    inside a cell and uses overviews when present), so a coarse level never holds full-resolution pixels.
    The output has ``ceil(n / decimation)`` pixels per axis; decimated pixel ``i`` covers full-resolution pixels
    ``[x0 + i*d, x0 + (i+1)*d)``; only whole cells inside the raster are read.
    """
    d = max(int(decimation), 1)
    ox, oy = -(-nx // d), -(-ny // d)
    # Snap the readable part to whole decimated cells so every output cell averages complete pixels.
    cx0 = -(x0 // d) if x0 < 0 else 0
    cy0 = -(y0 // d) if y0 < 0 else 0
    cx1 = min(ox, (width - x0) // d)
    cy1 = min(oy, (height - y0) // d)
    inside = (cx0, cy0, cx1, cy1) == (0, 0, ox, oy)
    out = np.empty((oy, ox), dtype=np.float32) if inside else np.full((oy, ox), np.nan, dtype=np.float32)
    if cx1 <= cx0 or cy1 <= cy0:
        return out
    part = out[cy0:cy1, cx0:cx1]
    win = (int(x0 + cx0 * d), int(y0 + cy0 * d), int((cx1 - cx0) * d), int((cy1 - cy0) * d))
    if d == 1:  # GDAL converts into the output itself (the values of astype, without two copies)
        band.ReadAsArray(*win, buf_obj=part)
    else:       # averaged in the band's own type, then converted
        part[...] = band.ReadAsArray(*win, buf_xsize=int(cx1 - cx0), buf_ysize=int(cy1 - cy0),
                                     resample_alg=gdal.GRIORA_Average)
    if nodata is not None and np.isfinite(nodata):
        part[part == np.float32(nodata)] = np.nan
    return out


def read_boxes(band, width: int, height: int, nodata, x0, y0, size: int, decimation: int = 1) -> np.ndarray:
    """Stack of ``size x size`` blocks of a GDAL band with top-left corners ``(x0, y0)`` (ints), averaged by
    ``decimation`` while reading: float32 ``(N, size/d, size/d)``, NaN outside the raster and on ``nodata``
    (:func:`read_block` of each box).

    Dense boxes (their union no larger than the pixels they hold: overlapping matching windows; decimated, their
    corners on one lattice of the decimation) are read in one :func:`read_block` of their union and cut out of it
    (the same values: a box of the union is the box read alone); others one read per box. A tile of pan-MS windows every 4 px is one GDAL call
    instead of hundreds, each holding the GIL for its Python wrapper longer than for the read itself.
    """
    x0 = np.asarray(x0, dtype=np.int64).ravel()
    y0 = np.asarray(y0, dtype=np.int64).ravel()
    d = max(int(decimation), 1)
    m = -(-size // d)
    n = x0.size
    if n > 1:
        ux0, uy0 = int(x0.min()), int(y0.min())
        uw, uh = int(x0.max()) - ux0 + size, int(y0.max()) - uy0 + size
        if uw * uh <= n * size * size and not (np.any((x0 - ux0) % d) or np.any((y0 - uy0) % d)):
            return cut_boxes(read_block(band, width, height, nodata, ux0, uy0, uw, uh, d), 0, 0, (x0 - ux0) // d,
                             (y0 - uy0) // d, m)
    out = np.empty((n, m, m), dtype=np.float32)
    for i in range(n):  # one windowed read per box far apart: I/O, not arithmetic
        out[i] = read_block(band, width, height, nodata, int(x0[i]), int(y0[i]), size, size, d)
    return out


def cut_boxes(block: np.ndarray, bx: int, by: int, x0, y0, size: int) -> np.ndarray:
    """The ``size x size`` boxes with top-left corners ``(x0, y0)`` (ints, inside the block) cut out of ``block``
    (2-D, its top-left corner at ``(bx, by)``) in one fancy index: a new ``(N, size, size)`` array."""
    x0 = np.asarray(x0, dtype=np.int64).ravel()
    y0 = np.asarray(y0, dtype=np.int64).ravel()
    return np.lib.stride_tricks.sliding_window_view(block, (size, size))[y0 - by, x0 - bx]


def grid_nodes(n: int, step: int) -> np.ndarray:
    """Indices ``0, step, 2 step, ..., n - 1`` of the exact-geometry nodes along an axis of ``n`` samples."""
    nodes = np.arange(0, n, max(int(step), 1))
    if nodes[-1] != n - 1:
        nodes = np.append(nodes, n - 1)
    return nodes


def _interp_matrix(n: int, nodes: np.ndarray) -> np.ndarray:
    """(n, len(nodes)) linear interpolation weights from node values to every index 0..n-1."""
    m = np.zeros((n, nodes.size))
    i = np.arange(n)
    k = np.minimum(np.maximum(np.searchsorted(nodes, i, side="right") - 1, 0), nodes.size - 2) if nodes.size > 1 else 0
    if nodes.size == 1:
        m[:, 0] = 1.0
        return m
    t = (i - nodes[k]) / (nodes[k + 1] - nodes[k])
    m[i, k] = 1 - t
    m[i, k + 1] = t
    return m


def _lowpass(ratio: float, oversample: float):
    """``(decimation, gaussian sigma, read margin)`` for a reference with ``ratio`` pixels per grid spacing."""
    ratio = max(ratio, 1e-6)
    dec = max(1, int(math.floor(ratio / max(float(oversample), 1.0))))
    sigma = math.sqrt(max((ANTIALIAS_SIGMA * ratio / dec) ** 2 - (1.0 / 12.0 if dec > 1 else 0.0), 0.0))
    sigma = sigma if ratio > 1.25 else 0.0  # a reference at about the raw resolution is used as it is
    margin = int(math.ceil(3 * sigma + 3)) * dec + dec
    return dec, sigma, margin


def whole_pixel_shift(dx: np.ndarray, dy: np.ndarray):
    """``(tx, ty)`` when every offset ``dx, dy`` (reference position minus grid position at the exact nodes) is
    one whole-pixel translation to within :data:`IDENTITY_TOL`; else None."""
    if dx.size == 0 or not (np.all(np.isfinite(dx)) and np.all(np.isfinite(dy))):
        return None
    tx, ty = np.rint(dx.flat[0]), np.rint(dy.flat[0])
    if max(float(np.abs(dx - tx).max()), float(np.abs(dy - ty).max())) > IDENTITY_TOL:
        return None
    return int(tx), int(ty)


def _probe_nodes(nodes: np.ndarray) -> np.ndarray:
    """Every :data:`PROBE_EVERY`-th of the exact-geometry ``nodes`` along an axis, and the last."""
    sub = nodes[::PROBE_EVERY]
    return sub if sub[-1] == nodes[-1] else np.append(sub, nodes[-1])


def _reference_pixels(rpc, dem, reference, S: np.ndarray, L: np.ndarray):
    """Reference pixel coordinates ``(rx, ry)`` (shape of ``S``) of the raw positions ``S, L`` localised on the
    DEM."""
    lon, lat, h = rpc.localize_dem(S, L, dem)
    return tuple(np.asarray(v, dtype=float).reshape(S.shape) for v in reference.ground_to_pixel(lon, lat, h))


def _probe_shift(rpc, dem, reference, S: np.ndarray, L: np.ndarray):
    """:func:`whole_pixel_shift` at the raw positions ``S, L`` (a subset of the exact nodes)."""
    rx, ry = _reference_pixels(rpc, dem, reference, S, L)
    return whole_pixel_shift(rx - S, ry - L)


def _on_union_grid(rpc, dem, reference, x0, y0, size: int, step: int, order: int, oversample: float, dtype,
                   spacing: int = 1, probe: bool = True):
    """:func:`reference_on_grids` of dense, overlapping windows (whole-pixel corners on one lattice of the grid
    ``spacing``) as one grid over their union, resampled once and cut into the windows; None when the windows
    are not dense. A whole-pixel translation is looked for at pixel spacing only."""
    ix0, iy0 = np.round(x0).astype(int), np.round(y0).astype(int)
    if not (np.array_equal(ix0, x0) and np.array_equal(iy0, y0)):
        return None
    ux0, uy0 = int(ix0.min()), int(iy0.min())
    if np.any((ix0 - ux0) % spacing) or np.any((iy0 - uy0) % spacing):
        return None
    Wu, Hu = (int(ix0.max()) - ux0) // spacing + size, (int(iy0.max()) - uy0) // spacing + size
    if Wu * Hu > 0.8 * x0.size * size * size:
        return None
    nx, ny = grid_nodes(Wu, step), grid_nodes(Hu, step)
    t = None
    if spacing == 1 and probe:
        px, py = _probe_nodes(nx), _probe_nodes(ny)
        t = _probe_shift(rpc, dem, reference, *np.meshgrid(ux0 + px + 0.5, uy0 + py + 0.5))
    if t is None:  # not one whole-pixel translation: every node (the dense test kept as it was)
        S = np.broadcast_to(ux0 + spacing * (nx[None, :] + 0.5), (ny.size, nx.size))
        L = np.broadcast_to(uy0 + spacing * (ny[:, None] + 0.5), (ny.size, nx.size))
        rx, ry = _reference_pixels(rpc, dem, reference, S, L)
        t = whole_pixel_shift(rx - S, ry - L) if spacing == 1 else None
    if t is not None:
        return cut_boxes(reference.read(ux0 + t[0], uy0 + t[1], Wu, Hu), ux0, uy0, ix0, iy0, size).astype(
            dtype, copy=False)
    fin = np.isfinite(rx) & np.isfinite(ry)
    if not fin.any():
        return np.full((x0.size, size, size), np.nan, dtype=dtype)
    Mx, My = _interp_matrix(Wu, nx), _interp_matrix(Hu, ny)
    fx = My @ np.where(fin, rx, 0.0) @ Mx.T
    fy = My @ np.where(fin, ry, 0.0) @ Mx.T
    # Pixels near a node without a ground point (none in the usual tile: its whole-grid passes saved)
    bad = None if fin.all() else (My @ (~fin).astype(float) @ Mx.T) > 0
    step_len = np.hypot(np.diff(rx, axis=1), np.diff(ry, axis=1)) / np.diff(nx)[None, :]
    ok = np.isfinite(step_len)
    dec, sigma, margin = _lowpass(float(np.median(step_len[ok])) if ok.any() else 1.0, oversample)
    if bad is not None and bad.any():
        fx[bad], fy[bad] = float(np.mean(fx[~bad])), float(np.mean(fy[~bad]))
    vals = _sample_reference(reference, fx, fy, dec, sigma, margin, order)
    if bad is not None:
        vals[bad] = np.nan
    return cut_boxes(vals.astype(dtype, copy=False), 0, 0, (ix0 - ux0) // spacing, (iy0 - uy0) // spacing, size)


def reference_on_grids(rpc, dem, reference: ReferenceImage, x0, y0, size: int, spacing: float = 1.0, *,
                       geometry_step: int = 4, order: int = 3, lonlat=None, oversample: float = 2.0,
                       shared: bool = False, dtype=np.float64, probe: bool = True) -> np.ndarray:
    """The reference resampled on ``N`` square grids of the raw image (METHODS §1 localisation, §2 DEM).

    Grid ``i`` has ``size x size`` nodes at raw positions ``(x0[i] + spacing * (j + 0.5), y0[i] + spacing *
    (k + 0.5))`` (GDAL convention; ``x0, y0`` are the grids' top-left corners), i.e. the centres of
    ``spacing x spacing`` blocks of raw pixels. Returns ``(N, size, size)`` of ``dtype`` (float64, or float32:
    the float64 values rounded, without a float64 copy), NaN where the DEM, the localisation or the reference has
    no value.

    ``reference`` is an orthophoto (:class:`ReferenceImage`) or another raw image with its sensor model
    (:class:`RawReference`): either maps the localised ground points to its pixels (``ground_to_pixel``).
    ``geometry_step`` : nodes between exact localisations (bilinear in between); ``order`` spline order (3 =
    cubic). ``lonlat`` : optional precomputed ``(lon, lat, h)`` at the exact nodes (shape ``(N, m, m)``).
    ``oversample`` : a reference finer than the grid is read decimated down to about this many of its pixels per
    grid spacing (then low-passed). 2 (default) keeps the interpolation accurate to a small fraction of a pixel;
    1 reads 4 times fewer pixels and suits a coarse level, whose raw side is a plain block average anyway.
    ``shared``: dense overlapping windows at a whole spacing, their corners on one lattice of it (raw-to-raw pan-MS
    cells, a coarse matching level) are resampled once on the grid of their union and cut out of it (up to 4 times less localisation and interpolation; geometry nodes every
    ``geometry_step`` pixels of the union instead of each window). ``probe=False``: the caller knows the mapping is
    no whole-pixel translation (e.g. from the windows' corners); every node is localised at once, without the
    probe on a subset of them first (a translation is still recognised on all the nodes).
    """
    x0 = np.atleast_1d(np.asarray(x0, dtype=float))
    y0 = np.atleast_1d(np.asarray(y0, dtype=float))
    n = x0.size
    if shared and lonlat is None and n > 1 and spacing == int(spacing):
        vals = _on_union_grid(rpc, dem, reference, x0, y0, size, geometry_step, order, oversample, dtype,
                              int(spacing), probe)
        if vals is not None:
            return vals
    nodes = grid_nodes(size, geometry_step)
    whole = spacing == 1.0 and np.all(x0 == np.round(x0)) and np.all(y0 == np.round(y0))
    # A whole-pixel translation is first looked for on a subset of the nodes (see PROBE_EVERY).
    t = _probe_shift(rpc, dem, reference, *_node_grid(x0, y0, _probe_nodes(nodes) + 0.5)) \
        if whole and lonlat is None and probe else None
    if t is None:
        S, L = _node_grid(x0, y0, spacing * (nodes + 0.5))
        lon, lat, h = rpc.localize_dem(S, L, dem) if lonlat is None else lonlat
        rx, ry = reference.ground_to_pixel(lon, lat, h)
        rx = np.asarray(rx, dtype=float).reshape(n, nodes.size, nodes.size)
        ry = np.asarray(ry, dtype=float).reshape(n, nodes.size, nodes.size)
        t = whole_pixel_shift(rx - S, ry - L) if whole else None
    if t is not None:
        band = reference._open().GetRasterBand(reference.band)
        return read_boxes(band, reference.width, reference.height, reference.nodata, x0.astype(int) + t[0],
                          y0.astype(int) + t[1], size).astype(dtype, copy=False)
    ok_win = np.all(np.isfinite(rx) & np.isfinite(ry), axis=(1, 2))
    if not ok_win.any():
        return np.full((n, size, size), np.nan, dtype=dtype)
    M = _interp_matrix(size, nodes)
    # Full-resolution reference coordinates of every grid node: M @ nodes @ M.T per window.
    fx = M @ np.where(np.isfinite(rx), rx, 0.0) @ M.T
    fy = M @ np.where(np.isfinite(ry), ry, 0.0) @ M.T
    # Reference pixels per grid spacing (median over windows): decides decimation and low-pass.
    step_len = np.hypot(np.diff(rx, axis=2), np.diff(ry, axis=2)) / (np.diff(nodes)[None, None, :])
    ratio = float(np.nanmedian(step_len[ok_win])) if np.isfinite(step_len[ok_win]).any() else 1.0
    ok_idx = np.flatnonzero(ok_win)
    if ok_idx.size < n:
        fx, fy = fx[ok_idx], fy[ok_idx]
    vals = _sample_windows(reference, fx, fy, *_lowpass(ratio, oversample), order).astype(dtype, copy=False)
    if ok_idx.size == n:
        return vals
    out = np.full((n, size, size), np.nan, dtype=dtype)
    out[ok_idx] = vals
    return out


def _node_grid(x0: np.ndarray, y0: np.ndarray, pos: np.ndarray):
    """Raw positions ``(S, L)``, each ``(N, m, m)``, of the nodes ``pos`` (offsets along both axes) of the grids
    with top-left corners ``x0, y0``."""
    S = x0[:, None, None] + pos[None, None, :] + 0 * pos[None, :, None]
    L = y0[:, None, None] + pos[None, :, None] + 0 * pos[None, None, :]
    return S, L


def _sample_windows(reference, fx: np.ndarray, fy: np.ndarray, dec: int, sigma: float, margin: int, order: int):
    """The reference at ``fx, fy`` (``(N, size, size)``, one grid per window): dense windows share one read of
    their union; sparse ones are read (and filtered) one by one, so the work is proportional to the windows' area
    and not to the area they are spread over."""
    lo_x = np.floor(fx.min(axis=(1, 2))).astype(int) - margin
    hi_x = np.ceil(fx.max(axis=(1, 2))).astype(int) + margin
    lo_y = np.floor(fy.min(axis=(1, 2))).astype(int) - margin
    hi_y = np.ceil(fy.max(axis=(1, 2))).astype(int) + margin
    own = float(np.sum((hi_x - lo_x) * (hi_y - lo_y)))
    union = float((hi_x.max() - lo_x.min()) * (hi_y.max() - lo_y.min()))
    sample = _sample_reference if union <= 2.0 * own or fx.shape[0] == 1 else _sample_reference_each
    return sample(reference, fx, fy, dec, sigma, margin, order)


def _sample_reference(reference: ReferenceImage, fx: np.ndarray, fy: np.ndarray, dec: int, sigma: float,
                      margin: int, order: int) -> np.ndarray:
    """Sample the reference at continuous pixel coordinates ``fx, fy`` (one read of their bounding box)."""
    out = np.full(fx.shape, np.nan)
    bx0 = int(math.floor(fx.min())) - margin
    by0 = int(math.floor(fy.min())) - margin
    bx1 = int(math.ceil(fx.max())) + margin
    by1 = int(math.ceil(fy.max())) + margin
    # Align the box on the decimation lattice of the raster so overview reads are reused across tiles.
    bx0 -= bx0 % dec
    by0 -= by0 % dec
    block = reference.read(bx0, by0, bx1 - bx0, by1 - by0, dec).astype(np.float64)
    valid = np.isfinite(block)
    full = valid.all()          # the usual block: no gap to fill nor to look up (whole-block passes saved)
    if not full and not valid.any():
        return out
    filled = block if full else np.where(valid, block, float(np.mean(block[valid])))
    if sigma > 0:
        filled = ndimage.gaussian_filter(filled, sigma, mode="nearest")
    # Continuous pixel coordinate x (GDAL) -> index in the decimated block: cell i is centred at x0 + (i + 0.5) d.
    coords = np.stack([((fy - by0) / dec - 0.5).ravel(), ((fx - bx0) / dec - 0.5).ravel()])
    vals = ndimage.map_coordinates(filled, coords, order=order, mode="nearest", prefilter=True)
    inside = (coords[0] >= 0) & (coords[0] <= block.shape[0] - 1) & (coords[1] >= 0) & \
        (coords[1] <= block.shape[1] - 1)
    if not full:
        # A sample is invalid when any no-data cell (or the outside) is within the interpolation support.
        reach = (2 if order >= 2 else 1) + int(math.ceil(3 * sigma))
        bad = ndimage.binary_dilation(~valid, iterations=reach)
        ci = np.minimum(np.maximum(np.rint(coords[0]).astype(int), 0), block.shape[0] - 1)
        cj = np.minimum(np.maximum(np.rint(coords[1]).astype(int), 0), block.shape[1] - 1)
        inside &= ~bad[ci, cj]
    return np.where(inside, vals, np.nan).reshape(fx.shape)


def _sample_reference_each(reference: ReferenceImage, fx: np.ndarray, fy: np.ndarray, dec: int, sigma: float,
                           margin: int, order: int) -> np.ndarray:
    """:func:`_sample_reference` for windows far apart: one read per window, the arithmetic once for them all.

    Every window gets a block of one common size (its bounding box + ``margin``, widened to the largest box with
    real reference pixels, plus ``_PAD`` more for the spline prefilter's boundary) and the blocks are stacked:
    the prefilter runs along the two block axes of the stack and one ``map_coordinates`` call samples every
    window in the stack viewed as a tall 2-D array (a sample's 4 x 4 support never leaves its block: samples are
    ``margin`` inside). A sparse grid of small windows otherwise spends more time in per-call overhead than in
    interpolation. Samples within reach of no-data or outside the raster are NaN, as in the one-block path.
    """
    n = fx.shape[0]
    d = dec
    reach = (2 if order >= 2 else 1) + int(math.ceil(3 * sigma))
    pad = _PAD * d
    bx0 = np.floor(fx.min(axis=(1, 2))).astype(int) - margin - pad
    by0 = np.floor(fy.min(axis=(1, 2))).astype(int) - margin - pad
    bx1 = np.ceil(fx.max(axis=(1, 2))).astype(int) + margin + pad
    by1 = np.ceil(fy.max(axis=(1, 2))).astype(int) + margin + pad
    bx0 -= bx0 % d
    by0 -= by0 % d
    nx = int((bx1 - bx0).max())
    ny = int((by1 - by0).max())
    band = reference._open().GetRasterBand(reference.band)
    blocks = np.empty((n, -(-ny // d), -(-nx // d)), dtype=np.float64)
    for k in range(n):  # one windowed read per window: I/O, not arithmetic
        blocks[k] = read_block(band, reference.width, reference.height, reference.nodata, int(bx0[k]), int(by0[k]),
                               nx, ny, d)
    bh, bw = blocks.shape[1:]
    valid = np.isfinite(blocks)
    any_bad = not valid.all()
    usable = np.ones(n, dtype=bool)
    if any_bad:
        cnt = valid.sum(axis=(1, 2))
        usable = cnt > 0
        mean = np.where(valid, blocks, 0.0).sum(axis=(1, 2)) / np.maximum(cnt, 1)
        blocks = np.where(valid, blocks, mean[:, None, None])
    if sigma > 0:
        blocks = ndimage.gaussian_filter(blocks, (0, sigma, sigma), mode="nearest")
    if order > 1:
        for ax in (1, 2):
            blocks = ndimage.spline_filter1d(blocks, order, axis=ax, mode="mirror", output=np.float64)
    # Continuous pixel coordinate x (GDAL) -> index in the decimated block: cell i is centred at x0 + (i + 0.5) d.
    # Every sample is inside its own block by construction (the block is its window's bounding box + margin).
    coords = np.empty((2,) + fx.shape)
    np.subtract(fy, (by0 + 0.5 * d)[:, None, None], out=coords[0])
    np.subtract(fx, (bx0 + 0.5 * d)[:, None, None], out=coords[1])
    if d != 1:
        coords /= d
    cy, cx = coords[0], coords[1]
    if any_bad:
        bad = ndimage.binary_dilation(~valid, structure=_plane_cross(), iterations=reach)
        ci = np.minimum(np.maximum(np.rint(cy).astype(int), 0), bh - 1)
        cj = np.minimum(np.maximum(np.rint(cx).astype(int), 0), bw - 1)
        bad_sample = bad[np.arange(n)[:, None, None], ci, cj]
    cy += (np.arange(n) * bh)[:, None, None]  # row in the stack viewed as one tall 2-D array
    vals = ndimage.map_coordinates(blocks.reshape(n * bh, bw), coords.reshape(2, -1), order=order,
                                   mode="nearest", prefilter=False).reshape(fx.shape)
    if any_bad:
        vals[bad_sample] = np.nan
    vals[~usable] = np.nan
    return vals


def _plane_cross():
    """3-D structuring element of the 2-D cross (no growth along the stack axis)."""
    s = np.zeros((3, 3, 3), dtype=bool)
    s[1] = [[0, 1, 0], [1, 1, 1], [0, 1, 0]]
    return s
