"""Rendering of simulated raw images through the TRUE rigorous model (METHODS §10).

Every pixel is localised on the DEM through the true model and takes the value of a reference image (any GDAL
raster, any CRS) or of a built-in seeded texture at that ground point. Tiled (512 px), parallel (threads; NumPy
releases the GIL) and memory-bounded: at most ``2 * workers`` tiles are in flight, the output is written block by
block to a temporary GeoTIFF that replaces the target only when complete (a cancelled render leaves nothing).

Per tile, the line of sight of each pixel is interpolated between its ground points at the bottom and top of the
height range (exactly localised on a 32 px node grid: the geometry is smooth at that scale), then the DEM
intersection is solved along it by a few secant steps on an in-memory copy of the DEM.
"""
from __future__ import annotations

import functools
import os
import tempfile
import threading
from contextlib import closing
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from typing import Optional

import numpy as np
from osgeo import gdal, osr
from scipy.ndimage import map_coordinates

from .._gdal import with_gdal_exceptions
from ..atomic import atomic_output, fix_mode
from ..dem import DEM
from ..errors import DEMError, Gf4calError
from ..geodesy import crs_transformer
from ..outputs import gtiff_options
from ..progress import report

_M_PER_DEG = 111320.0


# ------------------------------------------------------------------------------------------------ texture
def _hash01(ix, iy, salt: int):
    """Deterministic pseudo-random numbers in [0, 1) for integer lattice points (splitmix64 mixing)."""
    h = (ix.astype(np.int64).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)) ^ \
        (iy.astype(np.int64).astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)) ^ \
        np.full(ix.shape, (salt * 0x165667B19E3779F9) & 0xFFFFFFFFFFFFFFFF, dtype=np.uint64)
    h ^= h >> np.uint64(30)
    h *= np.uint64(0xBF58476D1CE4E5B9)
    h ^= h >> np.uint64(27)
    h *= np.uint64(0x94D049BB133111EB)
    h ^= h >> np.uint64(31)
    return (h >> np.uint64(11)).astype(np.float64) / float(1 << 53)


class _Lattice:
    """The lattice cells of points ``(x, y)`` at spacing ``wavelength``: integer corner ``(ix, iy)`` and the
    smoothstep weights, shared by every salt; :meth:`corners` gives the four lattice values of a salt.

    The values are hashed once per lattice node of the points' range (a small table: a 512 px tile spans a few
    thousand nodes) and gathered per point, instead of hashed four times per point: the same numbers (the hash
    is an integer function of the node), several times faster. Scattered points (a table larger than the
    points) or non-finite ones are hashed per point."""

    def __init__(self, x, y, wavelength: float):
        gx, gy = x / wavelength, y / wavelength
        self.ix, self.iy = np.floor(gx), np.floor(gy)
        self.tx, self.ty = gx - self.ix, gy - self.iy
        self.k = None
        if self.ix.size >= 64:
            x0, x1, y0, y1 = self.ix.min(), self.ix.max(), self.iy.min(), self.iy.max()
            if np.isfinite(x0 + x1 + y0 + y1) and (x1 - x0 + 2) * (y1 - y0 + 2) <= self.ix.size:
                self.nx = int(x1 - x0) + 2
                self.gx, self.gy = np.meshgrid(x0 + np.arange(self.nx), y0 + np.arange(int(y1 - y0) + 2))
                self.k = ((self.iy - y0) * self.nx + (self.ix - x0)).astype(np.intp)

    def corners(self, salt: int):
        """``(v00, v10, v01, v11)``: the hash values at the cell's corners (x, y), (x + 1, y), (x, y + 1),
        (x + 1, y + 1)."""
        if self.k is None:
            ix, iy = self.ix, self.iy
            return (_hash01(ix, iy, salt), _hash01(ix + 1, iy, salt), _hash01(ix, iy + 1, salt),
                    _hash01(ix + 1, iy + 1, salt))
        t = _hash01(self.gx, self.gy, salt).ravel()
        k, nx = self.k, self.nx
        return t.take(k), t.take(k + 1), t.take(k + nx), t.take(k + nx + 1)


def value_noise(x, y, wavelength: float, salt: int):
    """Smooth value noise in [0, 1) with the given lattice spacing (same units as x, y)."""
    return value_noise_salts(x, y, wavelength, (salt,))[0]


def value_noise_salts(x, y, wavelength: float, salts):
    """:func:`value_noise` for several salts at the same points (the lattice geometry computed once)."""
    lat = _Lattice(x, y, wavelength)
    fx, fy = lat.tx * lat.tx * (3 - 2 * lat.tx), lat.ty * lat.ty * (3 - 2 * lat.ty)
    gx, gy = 1 - fx, 1 - fy
    out = []
    for salt in salts:
        v00, v10, v01, v11 = lat.corners(salt)
        out.append((v00 * gx + v10 * fx) * gy + (v01 * gx + v11 * fx) * fy)
    return out


def _value_noise_grad(x, y, wavelength: float, salt: int):
    """:func:`value_noise` and the norm of its gradient (per unit of x, y), from the same four lattice values."""
    lat = _Lattice(x, y, wavelength)
    tx, ty = lat.tx, lat.ty
    fx, fy = tx * tx * (3 - 2 * tx), ty * ty * (3 - 2 * ty)
    dfx, dfy = 6 * tx * (1 - tx), 6 * ty * (1 - ty)
    v00, v10, v01, v11 = lat.corners(salt)
    v = (v00 * (1 - fx) + v10 * fx) * (1 - fy) + (v01 * (1 - fx) + v11 * fx) * fy
    dvx = dfx * ((v10 - v00) * (1 - fy) + (v11 - v01) * fy) / wavelength
    dvy = dfy * ((v01 - v00) * (1 - fx) + (v11 - v10) * fx) / wavelength
    return v, np.hypot(dvx, dvy)


def _box_step(d, width):
    """A unit step at signed distance ``d = 0`` averaged over a box of ``width`` (a detector's footprint)."""
    if width <= 0:
        return (d >= 0).astype(float)
    return np.clip(0.5 + d / width, 0.0, 1.0)


def texture_value(lon, lat, seed: int = 0, scale_m: float = 150.0, edge_m: Optional[float] = None):
    """Built-in ground texture at (lon, lat), values in [0, 1] (deterministic in seed and scale).

    Multi-scale noise (finest wavelength ``scale_m``, in spherical-Mercator metres, i.e. ground metres divided by
    cos(lat)) + patchy "fields" with sharp edges + thin dark "roads",
    so that phase correlation / matching works at every scale from ``scale_m`` to ~100 ``scale_m``. Use the same
    ``seed`` and ``scale_m`` in :func:`write_reference_ortho` to get a reference DOM of the same ground.

    The sharp edges of fields and roads are averaged over a box of ``edge_m`` (default ``scale_m / 3``, the pixel
    size of the images rendered from it): the value at a point is what a detector of that size centred there
    integrates (analytically, from the local gradient of the noise that places the edge). Point-sampling the
    hard edges instead aliased them: an edge moved by up to half a pixel between two samplings of the same ground
    (the raw image and the reference), i.e. local shifts of ~0.5-1 px where edges dominate a window's texture.
    ``edge_m=0`` gives the hard edges.
    """
    x, y = mercator_xy(lon, lat)
    return texture_of_mercator(x, y, seed, scale_m, edge_m)


def mercator_xy(lon, lat):
    """Spherical-Mercator metres of (lon, lat): conformal (no shear, isotropic features anywhere); lengths are
    ground metres / cos(lat). The coordinates of :func:`texture_value`'s texture."""
    lon = np.asarray(lon, dtype=float)
    lat = np.asarray(lat, dtype=float)
    return np.radians(lon) * 6378137.0, np.log(np.tan(np.pi / 4 + np.radians(np.clip(lat, -85, 85)) / 2)) * 6378137.0


def texture_of_mercator(x, y, seed: int = 0, scale_m: float = 150.0, edge_m: Optional[float] = None):
    """:func:`texture_value` at spherical-Mercator points (:func:`mercator_xy`)."""
    s = int(seed) * 1000
    width = scale_m / 3.0 if edge_m is None else float(edge_m)
    fbm, amp, total = 0.0, 1.0, 0.0
    for k in range(6):
        fbm = fbm + amp * value_noise(x, y, scale_m * 2.0 ** k, s + k)
        total += amp
        amp *= 0.75
    fbm = fbm / total
    tiny = 1e-12
    # Fields: levels floor(7 n) / 6; near the closest level boundary b (n = b / 7) the step from (b - 1) / 6 to
    # b / 6 is box-averaged across the signed distance to the boundary.
    n, gn = _value_noise_grad(x, y, 25 * scale_m, s + 50)
    n7 = n * 7
    b = np.round(n7)
    d = (n7 - b) / np.maximum(7 * gn, tiny)
    fields = np.clip((b - 1 + _box_step(d, width)) / 6.0, 0.0, 1.0)
    # Roads: the band |r - 0.5| < 0.006 (half-width 0.006 / |grad r| across the centre line), box-averaged.
    r, gr = _value_noise_grad(x, y, 60 * scale_m, s + 60)
    gr = np.maximum(gr, tiny)
    dc = (r - 0.5) / gr
    hw = 0.006 / gr
    road = _box_step(dc + hw, width) - _box_step(dc - hw, width)
    v = 0.5 * fields + 0.6 * (fbm - 0.5) + 0.25
    v = v * (1 - road) + 0.1 * road
    return np.clip(v, 0.0, 1.0)


def create_ortho_tif(path, nx: int, ny: int, top_left, resolution_deg: float):
    """A new tiled DEFLATE Byte GeoTIFF in EPSG:4326 (``top_left = (lon, lat)`` of the outer corner), open for
    writing block by block (call ``FlushCache()`` after each block to keep memory at a block)."""
    ds = gdal.GetDriverByName("GTiff").Create(os.fspath(path), nx, ny, 1, gdal.GDT_Byte,
                                              gtiff_options())
    ds.SetGeoTransform((top_left[0], resolution_deg, 0.0, top_left[1], 0.0, -resolution_deg))
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(4326)
    ds.SetProjection(srs.ExportToWkt())
    return ds


@with_gdal_exceptions
def write_reference_ortho(path, bounds, resolution_deg: float, seed: int = 0, scale_m: float = 150.0,
                          block: int = 512, workers: int = 2) -> str:
    """Write the built-in texture as an EPSG:4326 Byte GeoTIFF over ``bounds = (min_lon, min_lat, max_lon,
    max_lat)`` at ``resolution_deg``: a reference DOM for matching tests (values at pixel centres).

    Blocks are computed by ``workers`` threads (NumPy releases the GIL), at most ``2 * workers`` in flight."""
    x0, y0, x1, y1 = bounds
    nx = int(np.ceil((x1 - x0) / resolution_deg))
    ny = int(np.ceil((y1 - y0) / resolution_deg))
    if nx * ny > 40000 ** 2 or nx < 1 or ny < 1:
        raise Gf4calError(f"reference ortho of {nx} x {ny} px is unreasonable; choose a coarser resolution")
    path = os.fspath(path)
    with atomic_output(path) as tmp:
        ds = create_ortho_tif(tmp, nx, ny, (x0, y1), resolution_deg)
        band = ds.GetRasterBand(1)

        def do_block(i, j):
            w, h = min(block, nx - i), min(block, ny - j)
            lat = y1 - (j + np.arange(h) + 0.5) * resolution_deg
            lon = x0 + (i + np.arange(w) + 0.5) * resolution_deg
            LON, LAT = np.meshgrid(lon, lat)
            return i, j, _to_byte(texture_value(LON, LAT, seed, scale_m))

        blocks = [(i, j) for j in range(0, ny, block) for i in range(0, nx, block)]
        for i, j, arr in _bounded_map(do_block, blocks, workers):
            band.WriteArray(arr, i, j)
            # Write the finished blocks out and drop them from GDAL's block cache (which may grow to 5 % of the
            # RAM): memory stays at a few blocks whatever the raster size (issue 14).
            ds.FlushCache()
        ds = None
    return path


def _bounded_map(fn, jobs, workers: int):
    """Yield ``fn(*job)`` for every job, in completion order, from ``workers`` threads (NumPy releases the GIL).

    At most ``2 * workers`` jobs are in flight, so memory stays at a few tiles whatever the raster size. If the
    consumer raises (e.g. CancelledError from a progress callback), jobs not yet started are cancelled.
    """
    nw = max(1, int(workers))
    it = iter(jobs)
    with ThreadPoolExecutor(max_workers=nw) as pool:
        pending = set()
        try:
            while True:
                while len(pending) < 2 * nw:
                    nxt = next(it, None)
                    if nxt is None:
                        break
                    pending.add(pool.submit(fn, *nxt))
                if not pending:
                    return
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in finished:
                    yield fut.result()
        except BaseException:
            for fut in pending:
                fut.cancel()
            raise


def _to_byte(v):
    return np.clip(np.round(20.0 + 220.0 * v), 1, 255).astype(np.uint8)


# ------------------------------------------------------------------------------------------------ DEM grid
class _DemGrid:
    """In-memory EPSG:4326 copy of the DEM over the footprint, with vectorised bilinear sampling (read-only, so
    safe to share between threads)."""

    def __init__(self, dem, bounds, max_cells: int = 3000):
        if dem.is_constant:
            self.constant = dem.constant_height
            return
        self.constant = None
        x0, y0, x1, y1 = bounds
        cell = max((x1 - x0), (y1 - y0)) / max_cells
        native = _native_cell_deg(dem)
        if native is not None and native >= cell:
            # Nodes on the raster's own pixel centres: bilinear sampling is then identical to the DEM's.
            gt = dem._gt
            cell = abs(gt[1])
            x0 = gt[0] + (np.floor((x0 - gt[0]) / cell - 0.5) + 0.5) * cell
            y1 = gt[3] - (np.floor((gt[3] - y1) / cell - 0.5) + 0.5) * cell
        nx, ny = int(np.ceil((x1 - x0) / cell)) + 2, int(np.ceil((y1 - y0) / cell)) + 2
        lon = x0 + np.arange(nx) * cell
        lat = y1 - np.arange(ny) * cell
        LON, LAT = np.meshgrid(lon, lat)
        h = np.asarray(dem.height(LON, LAT), dtype=float)
        if not np.all(np.isfinite(h)):
            raise DEMError("the DEM does not cover the image footprint; use a DEM covering the scene")
        self.h, self.x0, self.y1, self.cell = h, x0, y1, cell

    def height(self, lon, lat):
        if self.constant is not None:
            return np.full(np.shape(lon), self.constant)
        c = (lon - self.x0) / self.cell
        r = (self.y1 - lat) / self.cell
        ny, nx = self.h.shape
        c = np.clip(c, 0, nx - 1.000001)
        r = np.clip(r, 0, ny - 1.000001)
        ic, ir = np.floor(c).astype(np.intp), np.floor(r).astype(np.intp)
        fc, fr = c - ic, r - ir
        h, k = self.h.ravel(), ir * nx + ic          # flat gathers: the same values, faster than 2-D indexing
        gc = 1 - fc
        return ((h.take(k) * gc + h.take(k + 1) * fc) * (1 - fr) +
                (h.take(k + nx) * gc + h.take(k + nx + 1) * fc) * fr)


def _native_cell_deg(dem) -> Optional[float]:
    gt = getattr(dem, "_gt", None)
    if gt is None or getattr(dem, "_to_dem", None) is not None:
        return None
    return min(abs(gt[1]), abs(gt[5]))


# ------------------------------------------------------------------------------------------------ reference
class _Reference:
    """Windowed bilinear sampling of any GDAL raster (any CRS) at (lon, lat); one dataset handle per thread."""

    @with_gdal_exceptions
    def __init__(self, path: str, image_gsd_m: float):
        self.path = os.fspath(path)
        try:
            ds = gdal.Open(self.path)
        except RuntimeError as exc:
            raise Gf4calError(f"cannot open the reference image {path}: {exc}") from None
        gt = ds.GetGeoTransform(can_return_null=True)
        if gt is None or gt[2] != 0 or gt[4] != 0:
            raise Gf4calError(f"reference {path} must be a north-up georeferenced raster (gdalwarp it first)")
        wkt = ds.GetProjection()
        if not wkt:
            raise Gf4calError(f"reference {path} has no CRS; assign one (gdal_edit.py -a_srs)")
        self.gt = gt
        self.size = (ds.RasterXSize, ds.RasterYSize)
        band = ds.GetRasterBand(1)
        self.byte = band.DataType == gdal.GDT_Byte
        lo, hi = band.ComputeRasterMinMax(True)
        self.lo, self.hi = float(lo), float(max(hi, lo + 1e-9))
        srs = osr.SpatialReference(wkt=wkt)
        self.geographic = bool(srs.IsGeographic())
        self.tr = crs_transformer("EPSG:4326", wkt)
        ref_m = abs(gt[1]) * (_M_PER_DEG if self.geographic else 1.0)
        # Average the reference down to about the image's resolution (anti-aliasing).
        self.factor = max(1.0, image_gsd_m / ref_m / 1.5)
        self._local = threading.local()

    def _ds(self):
        ds = getattr(self._local, "ds", None)
        if ds is None:
            ds = self._local.ds = gdal.Open(self.path)
        return ds

    def sample(self, lon, lat):
        x, y = self.tr.transform(lon, lat)
        col = (np.asarray(x) - self.gt[0]) / self.gt[1]
        row = (np.asarray(y) - self.gt[3]) / self.gt[5]
        W, H = self.size
        ok = np.isfinite(col) & np.isfinite(row)
        if not np.any(ok):
            return np.zeros(np.shape(lon))
        c0 = int(np.clip(np.floor(np.min(col[ok])) - 2, 0, W - 1))
        c1 = int(np.clip(np.ceil(np.max(col[ok])) + 2, c0 + 1, W))
        r0 = int(np.clip(np.floor(np.min(row[ok])) - 2, 0, H - 1))
        r1 = int(np.clip(np.ceil(np.max(row[ok])) + 2, r0 + 1, H))
        bw = max(2, int(round((c1 - c0) / self.factor)))
        bh = max(2, int(round((r1 - r0) / self.factor)))
        ds = self._ds()
        arr = ds.GetRasterBand(1).ReadAsArray(c0, r0, c1 - c0, r1 - r0, buf_xsize=bw, buf_ysize=bh,
                                              resample_alg=gdal.GRIORA_Average).astype(float)
        # Drop the blocks read from GDAL's block cache (up to 5 % of the RAM): else rendering a 24,576^2 scene
        # from a reference kept ~1.2 GB of it (issue 14); neighbouring tiles share only their borders' blocks.
        ds.FlushCache()
        fx, fy = bw / (c1 - c0), bh / (r1 - r0)
        cc = (col - c0) * fx - 0.5
        rr = (row - r0) * fy - 0.5
        inside = ok & (col >= 0) & (col <= W) & (row >= 0) & (row <= H)
        v = map_coordinates(arr, [np.where(inside, rr, 0), np.where(inside, cc, 0)], order=1, mode="nearest")
        v = v if self.byte else (v - self.lo) / (self.hi - self.lo) * 255.0
        return np.where(inside, v, 0.0)


# ------------------------------------------------------------------------------------------------ render
def model_bounds(model, margin: float = 0.02):
    """(min_lon, min_lat, max_lon, max_lat) of the image border at both ends of the height range, plus margin."""
    W, H = model.size
    e = np.linspace(0, 1, 17)
    bs = np.concatenate([e * W, np.full(17, W), e * W, np.zeros(17)])
    bl = np.concatenate([np.zeros(17), e * H, np.full(17, H), e * H])
    lons, lats = [], []
    for hh in model.height_range:
        lo_, la_ = model.localize(bs, bl, np.full(bs.shape, hh))
        lons.append(lo_)
        lats.append(la_)
    lons, lats = np.concatenate(lons), np.concatenate(lats)
    mx, my = margin * (lons.max() - lons.min()) + 1e-5, margin * (lats.max() - lats.min()) + 1e-5
    return (float(lons.min() - mx), float(lats.min() - my), float(lons.max() + mx), float(lats.max() + my))


def _bilinear_nodes(nodes, x, y, step):
    """Bilinear interpolation of node grids (each ``(ny, nx)``, spacing ``step`` px, first node at 0) at pixel
    offsets x, y (a grid of them: ``x`` along the rows, ``y`` down the columns); the weights computed once."""
    ny, nx = nodes[0].shape
    cx = np.clip(x / step, 0, nx - 1.000001)
    cy = np.clip(y / step, 0, ny - 1.000001)
    ix, iy = np.floor(cx).astype(np.intp), np.floor(cy).astype(np.intp)
    fx, fy = cx - ix, cy - iy
    gx, gy = 1 - fx, 1 - fy
    k = iy * nx + ix
    out = []
    for n in nodes:
        n = n.ravel()
        out.append((n.take(k) * gx + n.take(k + 1) * fx) * gy + (n.take(k + nx) * gx + n.take(k + nx + 1) * fx) * fy)
    return out


#: Rows of a tile computed at once by the per-pixel steps: arrays of ~32k values stay in the CPU cache (2-3x
#: faster than whole 512 px tiles); every step is per pixel, so the numbers do not depend on it.
BAND_ROWS = 64


def ground_of_pixels(model, demgrid, x0, y0, w, h, step: int = 32, iterations: int = 10):
    """(lon, lat, h) of the pixel centres of window (x0, y0, w, h) on the DEM, through ``model`` (see module doc)."""
    h_lo, h_hi = model.height_range
    if h_hi - h_lo < 1.0:
        h_lo, h_hi = h_lo - 100.0, h_hi + 100.0
    nxn, nyn = int(np.ceil(w / step)) + 1, int(np.ceil(h / step)) + 1
    S, L = np.meshgrid(x0 + np.arange(nxn) * step, y0 + np.arange(nyn) * step)
    lo_lon, lo_lat = model.localize(S.astype(float), L.astype(float), np.full(S.shape, h_lo))
    hi_lon, hi_lat = model.localize(S.astype(float), L.astype(float), np.full(S.shape, h_hi))
    out = np.empty((3, h, w))
    for r in range(0, h, BAND_ROWS):
        px, py = np.meshgrid(np.arange(w) + 0.5, np.arange(r, min(h, r + BAND_ROWS)) + 0.5)
        out[:, r:r + BAND_ROWS] = _ground_on_rays(_bilinear_nodes((lo_lon, lo_lat, hi_lon, hi_lat), px, py, step),
                                                  demgrid, h_lo, h_hi, iterations)
    return out[0], out[1], out[2]


def _ground_on_rays(ends, demgrid, h_lo, h_hi, iterations):
    """(lon, lat, h) where the rays from ``ends = (lon, lat at h_lo, lon, lat at h_hi)`` (linear in between)
    meet the DEM: secant steps, then a bracketing search where they did not settle."""
    a_lon, a_lat, b_lon, b_lat = ends
    d_lon, d_lat = b_lon - a_lon, b_lat - a_lat

    def terrain_minus(hh):
        f = (hh - h_lo) / (h_hi - h_lo)
        return demgrid.height(a_lon + f * d_lon, a_lat + f * d_lat) - hh

    def terrain_minus_at(hh, i):        # terrain_minus at the flat pixel indices i (the same numbers)
        f = (hh - h_lo) / (h_hi - h_lo)
        lon_ = a_lon.ravel().take(i) + f * d_lon.ravel().take(i)
        lat_ = a_lat.ravel().take(i) + f * d_lat.ravel().take(i)
        return demgrid.height(lon_, lat_) - hh

    # Secant iteration on DEM(P(h)) - h from two fixed-point starts, kept inside the height range.
    ha = np.full(a_lon.shape, 0.5 * (h_lo + h_hi))
    fa = terrain_minus(ha)
    hb = np.clip(ha + fa, h_lo, h_hi)
    fb = terrain_minus(hb)
    for _ in range(iterations):
        # A pixel with fb == 0 exactly is a fixed point (every further step gives hb again, and fb = 0): once
        # most pixels are there (~97 % after 5 steps), step only the others -- the same numbers, less work.
        i = np.flatnonzero(fb.ravel() != 0)
        if i.size > fb.size // 4:
            hn = _secant_step(ha, fa, hb, fb, h_lo, h_hi)
            ha, fa = hb, fb
            hb, fb = hn, terrain_minus(hn)
            continue
        if i.size == 0:
            break
        HA, FA, HB, FB = ha.ravel(), fa.ravel(), hb.ravel(), fb.ravel()     # views: updated in place
        hb_i, fb_i = HB.take(i), FB.take(i)
        hn = _secant_step(HA.take(i), FA.take(i), hb_i, fb_i, h_lo, h_hi)
        HA[i], FA[i] = hb_i, fb_i
        HB[i], FB[i] = hn, terrain_minus_at(hn, i)
    # Where the secant did not settle (steep slopes seen obliquely), bracket the first crossing from the top of
    # the height range and refine by regula falsi (Illinois).
    bad = ~(np.abs(fb) <= 1e-2)
    if np.any(bad):
        hb[bad] = _bracket(terrain_minus, bad, h_lo, h_hi)
    f = (hb - h_lo) / (h_hi - h_lo)
    return a_lon + f * d_lon, a_lat + f * d_lat, hb


def _secant_step(ha, fa, hb, fb, h_lo, h_hi):
    """The next secant iterate from (ha, fa), (hb, fb) (a fixed-point step where fb - fa vanishes), clipped to
    the height range."""
    denom = fb - fa
    safe = np.abs(denom) > 1e-9
    hn = np.where(safe, hb - fb * (hb - ha) / np.where(safe, denom, 1.0), hb + fb)
    return np.clip(hn, h_lo, h_hi)


def _bracket(terrain_minus_full, bad, h_lo, h_hi, n_scan: int = 24, n_refine: int = 30):
    idx = np.nonzero(bad)

    def g(hh):
        full = np.zeros(bad.shape)
        full[idx] = hh
        return terrain_minus_full(full)[idx]

    levels = np.linspace(h_hi, h_lo, n_scan + 1)
    hi = np.full(idx[0].size, h_hi)
    g_hi = g(hi)
    lo, g_lo = hi.copy(), g_hi.copy()
    found = g_hi >= 0
    for lev in levels[1:]:
        cur = np.full(hi.shape, lev)
        gc = g(cur)
        new = (~found) & (gc >= 0)
        lo[new], g_lo[new] = cur[new], gc[new]
        found |= new
        keep = ~found
        hi[keep], g_hi[keep] = cur[keep], gc[keep]
    # hi (above the surface, g < 0) and lo (below, g >= 0) bracket the first crossing.
    a, fa, b, fb = hi, g_hi, lo, g_lo
    side = np.zeros(a.shape)
    for _ in range(n_refine):
        c = np.where(fb != fa, b - fb * (b - a) / np.where(fb != fa, fb - fa, 1.0), 0.5 * (a + b))
        fc = g(c)
        left = np.sign(fc) == np.sign(fa)
        a = np.where(left, c, a)
        fa = np.where(left, fc, np.where(side == -1, fa / 2, fa))
        b = np.where(left, b, c)
        fb = np.where(left, np.where(side == 1, fb / 2, fb), fc)
        side = np.where(left, 1, -1)
    return np.where(found, np.where(np.abs(fa) < np.abs(fb), a, b), h_hi)


def _cloud_field(x, y, W, H, seed):
    return value_noise(x, y, max(W, H) / 5.0, 9000 + seed) * 0.7 + value_noise(x, y, max(W, H) / 17.0,
                                                                                9100 + seed) * 0.3


@with_gdal_exceptions
def render_image(model, dem, path, *, reference=None, seed: int = 0, gsd_m: Optional[float] = None,
                 paint_clouds: float = 0.0, cloud_mask_path: Optional[str] = None, tile: int = 512,
                 workers: int = 2, progress=None) -> str:
    """Render ``model``'s image (normally the TRUE model) into a Byte GeoTIFF at ``path``.

    Parameters
    ----------
    model : rigorous model with ``localize``, ``size`` and ``height_range``.
    dem : :class:`gdal_gf4cal.dem.DEM` (or a height).
    reference : path of any GDAL raster (any CRS) to render from; default: :func:`texture_value` (``seed``,
        wavelength ``3 * gsd_m``).
    paint_clouds : fraction of the image covered by bright clouds (image-space, seeded); ``cloud_mask_path``
        receives the mask (255 = cloud).
    tile, workers : tile size and number of threads; memory stays at a few tiles.
    """
    dem = DEM.coerce(dem)
    W, H = model.size
    if gsd_m is None:
        gsd_m = _centre_gsd_m(model)
    demgrid = _DemGrid(dem, model_bounds(model))
    ref = _Reference(reference, gsd_m) if reference is not None else None
    threshold = None
    if paint_clouds > 0:
        gx, gy = np.meshgrid(np.linspace(0, W, 200), np.linspace(0, H, 200))
        threshold = float(np.quantile(_cloud_field(gx, gy, W, H, seed), 1.0 - paint_clouds))
    do_tile = functools.partial(_render_tile, model, demgrid, ref, seed, gsd_m, threshold)
    path = os.fspath(path)
    tmps = []
    opts = gtiff_options(tile=tile)
    try:
        ds = _create_byte_tiff(path, ".render-", W, H, opts, tmps)
        band = ds.GetRasterBand(1)
        band.SetNoDataValue(0)
        mds = mband = None
        if cloud_mask_path and threshold is not None:
            mds = _create_byte_tiff(cloud_mask_path, ".mask-", W, H, opts, tmps)
            mband = mds.GetRasterBand(1)
        tiles = [(x, y, min(tile, W - x), min(tile, H - y)) for y in range(0, H, tile) for x in range(0, W, tile)]
        # closing(): a cancel raised by report() stops the pool at once, not when the generator is collected.
        with closing(_bounded_map(do_tile, tiles, workers)) as results:
            for done, (x0, y0, arr, mask) in enumerate(results, start=1):
                band.WriteArray(arr, x0, y0)
                ds.FlushCache()           # the tile's blocks to disk, out of the block cache (memory bound)
                if mband is not None and mask is not None:
                    mband.WriteArray(mask, x0, y0)
                    mds.FlushCache()
                report(progress, done / len(tiles), f"rendering tile {done}/{len(tiles)}")
        ds.SetMetadataItem("GF4CAL_RENDERED", "true model; " + (f"reference {reference}" if reference else
                                                                  f"built-in texture seed {seed}"))
        ds = None
        os.replace(tmps[0], path)
        fix_mode(path)
        if mds is not None:
            mds = None
            os.replace(tmps[1], cloud_mask_path)
            fix_mode(cloud_mask_path)
    finally:
        for t in tmps:
            if os.path.exists(t):
                os.unlink(t)
    return path


def _centre_gsd_m(model) -> float:
    """Ground size of one pixel at the image centre along the sample axis (m)."""
    W, H = model.size
    lon, lat = model.localize(np.array([W / 2, W / 2 + 1]), np.array([H / 2, H / 2]), float(np.mean(model.height_range)))
    return float(np.hypot((lon[1] - lon[0]) * _M_PER_DEG * np.cos(np.radians(lat[0])),
                          (lat[1] - lat[0]) * _M_PER_DEG))


def _render_tile(model, demgrid, ref, seed: int, gsd_m: float, threshold: Optional[float], x0: int, y0: int,
                 w: int, h: int):
    """One tile ``(x0, y0, Byte values, cloud mask or None)``: the reference (or the texture) at the pixels'
    ground, with clouds painted above ``threshold``."""
    W, H = model.size
    lon, lat, _ = ground_of_pixels(model, demgrid, x0, y0, w, h)
    if ref is not None:
        v = np.clip(ref.sample(lon, lat), 0, 255)
    else:
        v = 20.0 + 220.0 * texture_value(lon, lat, seed, 3.0 * gsd_m)
    mask = None
    if threshold is not None:
        px, py = np.meshgrid(x0 + np.arange(w) + 0.5, y0 + np.arange(h) + 0.5)
        a = np.clip((_cloud_field(px, py, W, H, seed) - threshold) / 0.04, 0.0, 1.0)
        v = v * (1 - a) + 250.0 * a
        mask = np.where(a > 0.5, 255, 0).astype(np.uint8)
    return x0, y0, np.clip(np.round(v), 1, 255).astype(np.uint8), mask


def _create_byte_tiff(path: str, prefix: str, W: int, H: int, opts, tmps: list):
    """A one-band Byte GeoTIFF on a fresh temporary beside ``path`` (appended to ``tmps``)."""
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=".tif", dir=os.path.dirname(os.path.abspath(path)))
    os.close(fd)
    tmps.append(tmp)
    return gdal.GetDriverByName("GTiff").Create(tmp, W, H, 1, gdal.GDT_Byte, opts)
