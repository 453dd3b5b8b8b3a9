"""Digital elevation models (METHODS §2).

:class:`DEM` samples any GDAL raster, in any CRS, bilinearly at (lon, lat) and returns ellipsoidal heights.
Reads are windowed: points are grouped by tile and only the tiles they touch are read (an LRU cache keeps the
recently used ones), so sampling 10,000 points of a 30 GB mosaic reads a few MB.

Heights above a geoid (EGM96/EGM2008) are converted to ellipsoidal heights with PROJ's ``vgridshift`` through
pyproj when ``geoid`` is given, or when the DEM's own CRS declares that vertical datum (a compound CRS such as
EPSG:4326+5773, as GDAL's RPC transformer does by default); ``geoid=False`` uses the stored heights as they are.
"""
from __future__ import annotations

import copy
import functools
import logging
import math
import os
import threading
from collections import OrderedDict
from typing import Optional, Tuple, Union

import numpy as np
import pyproj
from osgeo import gdal, osr
from scipy.ndimage import map_coordinates, maximum_filter

from ._gdal import with_gdal_exceptions
from .errors import DEMError
from .estimation import normal_solve
from .geodesy import crs_transformer
from .geoid import declared_geoid, grid_path, proj_search_dirs

log = logging.getLogger(__name__)

#: Named geoid grids (legacy names; :data:`gdal_gf4cal.geoid.GEOID_GRID_NAMES` has PROJ's current ones too).
GEOID_GRIDS = {"egm96": "egm96_15.gtx", "egm2008": "egm08_25.gtx"}

#: Largest difference (m) between :meth:`DEM.newton_sampler`'s heights and :meth:`DEM.sample`'s (checked when its
#: geoid lattice is built; rounding only where the gradient is analytic).
NEWTON_SAMPLER_TOL_M = 1e-6

NodataPolicy = Union[str, float]


class DEM:
    """A height model: a GDAL raster (:meth:`from_file`) or a constant height (:meth:`constant`).

    Build one from whatever the user gave with :meth:`from_user_input` (a DEM, a path, a number or None). Sample
    it with :meth:`sample` (scalars or arrays, the no-data policy per call) and, in Newton iterations, with
    :meth:`sample_with_gradient` (heights and slopes, vectorised, windowed tile reads) (METHODS §2).

    Parameters (of :meth:`from_file`)
    ----------
    path : any raster GDAL opens (GeoTIFF, .hgt, VRT mosaic, ...), any CRS.
    geoid : ``"egm96"``, ``"egm2008"`` or the path of a geoid grid: heights above that geoid are converted to
        ellipsoidal heights. ``None`` (default): ellipsoidal, unless the DEM's CRS declares a geoid vertical datum
        (EGM96/EGM2008), which is then applied (``geoid_applied`` says which). ``False`` (or ``"none"``,
        ``"ellipsoid"`` at the CLI): never convert.
    nodata : what to do where the DEM has no data or a point is outside it: ``"error"`` (raise
        :class:`DEMError`), ``"nan"`` (return NaN) or a number (use that ellipsoidal height).
    """

    @with_gdal_exceptions
    def __init__(self, *, path: Optional[str] = None, constant: Optional[float] = None, geoid=None,
                 nodata: NodataPolicy = "error", band: int = 1, tile_size: int = 1024, cache_tiles: int = 64):
        self.path = path
        self.constant_height = constant
        self.nodata_policy = nodata
        if isinstance(geoid, str) and geoid.strip().lower() in ("none", "ellipsoid", "ellipsoidal", "false"):
            geoid = False          # the CLI's way of saying geoid=False
        elif isinstance(geoid, str) and geoid.strip().lower() == "auto":
            geoid = None           # what the DEM's CRS declares
        self._geoid_name = geoid
        self._geoid = geoid_transformer(geoid) if geoid not in (None, False) else None
        self._geoid_source = None if geoid in (None, False) else geoid   # the grid's name or path (lattice)
        self._geoid_nodes = {}       # the geoid lattice of :meth:`newton_sampler` (shared by with_nodata copies)
        self._tile = int(tile_size)
        self._cache: "OrderedDict[Tuple[int, int], np.ndarray]" = OrderedDict()
        self._cache_tiles = int(cache_tiles)
        # The caches and the whole-raster reads hold this lock; windowed tile reads go through one dataset handle
        # per thread (self._handles: a GDAL dataset must not be used by two threads at once; the point kernels
        # sample one DEM from the thread pool, gdal_gf4cal.threads). Shared by the copies of with_nodata, which
        # share the dataset and the caches.
        self._lock = threading.RLock()
        self._handles = threading.local()
        if isinstance(nodata, str) and nodata not in ("error", "nan"):
            raise ValueError("nodata must be 'error', 'nan' or a height in metres")
        if path is None:
            return
        try:
            self._ds = gdal.Open(str(path))
        except RuntimeError as exc:
            raise DEMError(f"cannot open DEM {path}: {exc}") from None
        if self._ds is None:
            raise DEMError(f"cannot open DEM {path}")
        if band < 1 or band > self._ds.RasterCount:
            raise DEMError(f"DEM {path} has no band {band}")
        self._band = self._ds.GetRasterBand(band)
        self._band_index = band
        self._handles.ds, self._handles.band = self._ds, self._band
        self.width, self.height_px = self._ds.RasterXSize, self._ds.RasterYSize
        gt = self._ds.GetGeoTransform(can_return_null=True)
        if gt is None:
            raise DEMError(f"DEM {path} has no geotransform; georeference it (e.g. gdal_translate -a_ullr -a_srs)")
        if gt[2] != 0 or gt[4] != 0:
            raise DEMError(f"DEM {path} is rotated; warp it to a north-up grid first (gdalwarp)")
        self._gt = gt
        self._nodata_value = self._band.GetNoDataValue()
        # Band scale/offset (METHODS §2): stored value x scale + offset = height in metres (a decimetre DEM has 0.1).
        self._scale = float(self._band.GetScale() or 1.0)
        self._offset = float(self._band.GetOffset() or 0.0)
        if not (np.isfinite(self._scale) and np.isfinite(self._offset)) or self._scale == 0.0:
            raise DEMError(f"DEM {path} has an unusable band scale/offset ({self._scale!r}, {self._offset!r}); "
                           "fix them with gdal_edit.py -scale/-offset")
        wkt = self._ds.GetProjection()
        if not wkt:
            raise DEMError(f"DEM {path} has no CRS; assign one (gdal_edit.py -a_srs EPSG:4326)")
        srs = osr.SpatialReference(wkt=wkt)
        self.crs_wkt = wkt
        if geoid is None:
            declared = declared_geoid(str(path))
            if declared is not None:
                log.info("DEM %s: its CRS declares %s heights; converting them to ellipsoidal heights", path,
                         declared.upper())
                self._geoid_name = self._geoid_source = declared
                self._geoid = geoid_transformer(declared, source=str(path))
        self._to_dem = None
        geographic_wgs84 = srs.IsGeographic() and srs.GetAuthorityCode("GEOGCS") == "4326"
        if not geographic_wgs84:
            self._to_dem = crs_transformer("EPSG:4326", wkt)
        # Geographic DEMs: longitudes are compared modulo 360 (see :meth:`_wrap_lon`), so a DEM in the 0..360
        # convention or one crossing the antimeridian serves points given in -180..180, and the reverse.
        self._lon_wrap = srs.IsGeographic() == 1
        self._west = min(gt[0], gt[0] + gt[1] * self.width)
        # A DEM of up to 16 Mpx (128 MB as float64) is read once and sampled without tiling.
        self._whole = None
        self._max_step = self._affine = self._pixel_size = self._xy_poly = None     # kept once computed
        self._local_max = {}
        self._height_range = None
        self._bounds_lonlat = None
        self._whole_limit = 16 * 1024 * 1024

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_file(cls, path, geoid=None, nodata: NodataPolicy = "error", band: int = 1) -> "DEM":
        """Open a DEM raster. See the class docstring for ``geoid`` and ``nodata``."""
        if not os.path.exists(str(path)) and not str(path).startswith("/vsi"):
            raise DEMError(f"DEM file not found: {path}")
        return cls(path=str(path), geoid=geoid, nodata=nodata, band=band)

    @classmethod
    def constant(cls, height_m: float) -> "DEM":
        """A flat DEM at ``height_m`` metres above the ellipsoid."""
        return cls(constant=float(height_m))

    @classmethod
    def from_user_input(cls, dem, geoid=None, *, nodata: Optional[NodataPolicy] = None,
                        band: int = 1) -> Optional["DEM"]:
        """The one way from what a user gives to a :class:`DEM` (METHODS §2).

        Parameters
        ----------
        dem : a :class:`DEM` (returned as it is), the path of a raster (opened with ``geoid``, ``nodata`` and
            ``band``), a number or a string that is one and names no file (a constant ellipsoidal height in
            metres) or ``None`` (no DEM: returns ``None``).
        geoid : see the class docstring; only used when ``dem`` is a path (a DEM object keeps its own, and a
            constant height is ellipsoidal).
        nodata : the no-data policy of a DEM opened from a path (default ``"error"``); for a given DEM object,
            a copy with that policy (:meth:`with_nodata`).
        """
        if dem is None:
            return None
        if isinstance(dem, DEM):
            return dem if nodata is None else dem.with_nodata(nodata)
        if isinstance(dem, (bool, np.bool_)):
            raise DEMError(f"DEM {dem!r} is neither a raster path nor a height; pass a DEM file or a height in metres")
        if isinstance(dem, (int, float, np.floating, np.integer)):
            if not np.isfinite(float(dem)):
                raise DEMError(f"constant DEM height {dem!r} is not a finite number; pass a height in metres")
            return cls.constant(float(dem))
        if isinstance(dem, str) and not os.path.exists(dem):
            try:
                return cls.from_user_input(float(dem))      # a height typed at the CLI ("--dem 250")
            except ValueError:
                pass
        if isinstance(dem, (str, os.PathLike)):
            return cls.from_file(os.fspath(dem), geoid=geoid, nodata="error" if nodata is None else nodata, band=band)
        raise DEMError(f"cannot use {type(dem).__name__} as a DEM; pass a DEM, a raster path or a height in metres")

    @classmethod
    def coerce(cls, dem) -> "DEM":
        """A :class:`DEM` from a DEM, a number (constant height) or a path (:meth:`from_user_input`, not None)."""
        if dem is None:
            raise DEMError("no DEM given; pass a DEM, a raster path or a height in metres")
        return cls.from_user_input(dem)

    def with_nodata(self, nodata: NodataPolicy) -> "DEM":
        """A copy with another no-data policy, sharing the opened raster and its caches."""
        if isinstance(nodata, str) and nodata not in ("error", "nan"):
            raise ValueError("nodata must be 'error', 'nan' or a height in metres")
        if nodata == self.nodata_policy and type(nodata) is type(self.nodata_policy):
            return self
        other = copy.copy(self)
        other.nodata_policy = nodata
        return other

    # ------------------------------------------------------------------ properties
    @property
    def is_constant(self) -> bool:
        return self.constant_height is not None

    @property
    def in_memory(self) -> bool:
        """True for a raster small enough to be held in memory (read whole once): then :meth:`local_max` and
        :meth:`local_max_slope` answer (None otherwise)."""
        return not self.is_constant and self.width * self.height_px <= self._whole_limit

    @property
    def is_geographic(self) -> bool:
        """True for a raster in a geographic CRS (longitudes compared modulo 360)."""
        return not self.is_constant and bool(self._lon_wrap)

    def bounds_lonlat(self) -> Tuple[float, float, float, float]:
        """(min_lon, min_lat, max_lon, max_lat) of the raster, in WGS84 degrees."""
        if self.is_constant:
            return (-180.0, -90.0, 180.0, 90.0)
        if self._bounds_lonlat is None:
            self._bounds_lonlat = self._compute_bounds_lonlat()
        return self._bounds_lonlat

    def _compute_bounds_lonlat(self) -> Tuple[float, float, float, float]:
        gt = self._gt
        xs = gt[0] + gt[1] * np.array([0, self.width, 0, self.width, self.width / 2])
        ys = gt[3] + gt[5] * np.array([0, 0, self.height_px, self.height_px, self.height_px / 2])
        if self._to_dem is not None:
            xs, ys = self._to_dem.transform(xs, ys, direction="INVERSE")
        return (float(np.min(xs)), float(np.min(ys)), float(np.max(xs)), float(np.max(ys)))

    def height_range(self) -> Tuple[float, float]:
        """(min, max) of the stored heights (geoid not applied): exact for a raster held in memory (see
        :attr:`height_range_is_exact`), GDAL's approximate statistics for a larger one.

        Raises :class:`DEMError` if the raster holds no valid height at all (every pixel no-data).
        """
        if self.is_constant:
            return (self.constant_height, self.constant_height)
        if self.height_range_is_exact:
            if self._height_range is None:
                if self._whole is None:
                    self._load_whole()
                if np.all(np.isnan(self._whole)):
                    raise DEMError(f"DEM {self.path} has no valid height (every pixel is no-data); use a DEM with "
                                   "data over the scene")
                self._height_range = (float(np.nanmin(self._whole)), float(np.nanmax(self._whole)))
            return self._height_range
        with self._lock:
            if self._height_range is None:
                self._height_range = self._approximate_height_range()
        return self._height_range

    def _approximate_height_range(self) -> Tuple[float, float]:
        """GDAL's (approximate, else exact) min and max of a large raster, band scale/offset applied."""
        for approx in (True, False):       # approximate statistics may sample only voids: then scan it all
            try:
                lo_hi = self._thread_band().ComputeRasterMinMax(approx)
            except RuntimeError:
                lo_hi = None
            if lo_hi is not None and all(np.isfinite(lo_hi)):
                lo, hi = sorted(float(v) * self._scale + self._offset for v in lo_hi)
                return (lo, hi)
        raise DEMError(f"DEM {self.path} has no valid height (every pixel is no-data); use a DEM with data over "
                       "the scene")

    @property
    def height_range_is_exact(self) -> bool:
        """True when :meth:`height_range` is the exact range (a raster small enough to hold in memory)."""
        return self.is_constant or self.width * self.height_px <= self._whole_limit

    # ------------------------------------------------------------------ sampling
    def sample(self, lon, lat, *, nodata: Optional[NodataPolicy] = None):
        """Ellipsoidal height (m) at (lon, lat) degrees WGS84, bilinear; scalars or arrays (METHODS §2).

        Bilinear between pixel centres (GDAL convention: the centre of the first pixel is at (0.5, 0.5) pixel
        coordinates); between the outermost centres and the raster edge the edge value holds. Outside the raster
        or next to no-data the no-data policy applies: ``nodata`` (``"error"``, ``"nan"`` or a height in metres)
        or, when None, the DEM's own. A scalar point gives a Python float; arrays keep their (broadcast) shape.
        """
        policy = self.nodata_policy if nodata is None else nodata
        if isinstance(policy, str) and policy not in ("error", "nan"):
            raise ValueError("nodata must be 'error', 'nan' or a height in metres")
        return self._height(lon, lat, policy)

    def height(self, lon, lat):
        """Alias of :meth:`sample` with the DEM's own no-data policy."""
        return self._height(lon, lat, self.nodata_policy)

    @property
    def gradient_is_analytic(self) -> bool:
        """True when :meth:`sample_with_gradient` is the exact derivative of :meth:`sample` (a WGS84 geographic
        raster without geoid conversion, or a constant); otherwise it is a central difference over half a pixel."""
        return self.is_constant or (self._to_dem is None and self._geoid is None)

    def sample_with_gradient(self, lon, lat):
        """Heights and their slopes at (lon, lat): ``(h, dh/dlon, dh/dlat)`` in m, m/deg, m/deg (METHODS §2).

        The sampler of the DEM intersection's Newton steps: flat float arrays in and out, vectorised, NaN outside
        the raster or next to no-data whatever the no-data policy (a numeric policy gives its height and zero
        slope there). Small rasters are held in memory; large ones are read by windowed tiles (LRU cached). The
        gradient is that of the bilinear surface (in the half-pixel border where the edge value holds, that of
        the edge cell); see :attr:`gradient_is_analytic` for reprojected or geoid-corrected DEMs.
        """
        lon = np.asarray(lon, dtype=float).ravel()
        lat = np.asarray(lat, dtype=float).ravel()
        if self.is_constant:
            z = np.where(np.isfinite(lon) & np.isfinite(lat), self.constant_height, np.nan)
            return z, np.zeros(lon.size), np.zeros(lon.size)
        policy = self.nodata_policy
        numeric = not isinstance(policy, str)
        if not self.gradient_is_analytic:
            gt = self._gt
            step = 0.5 * min(abs(gt[1]), abs(gt[5]))
            if self._to_dem is not None:          # projected DEM: half a pixel in metres, in degrees
                step /= 111320.0
            z = self._height(lon, lat, "nan")
            gx = (self._height(lon + step, lat, "nan") - self._height(lon - step, lat, "nan")) / (2 * step)
            gy = (self._height(lon, lat + step, "nan") - self._height(lon, lat - step, "nan")) / (2 * step)
        else:
            return self._newton_sample(lon, lat)
        if numeric:
            g = np.array([gx, gy])
            _fallback_with_zero_slope(z, g, policy)
            gx, gy = g
        return z, gx, gy

    def _surfaces(self, xy, lattice, gradient: bool):
        """Stored heights and, with a geoid ``lattice``, undulations at pixel coordinates ``xy`` (R, 2, n) of the
        raster (row 0) and of the lattice (row 1) (overwritten: scratch): ``(z, g)``, z (R, n), g (R, 2, n) the
        slopes in m/px (None without ``gradient``); NaN off the raster or next to no-data. A raster held in memory
        and the lattice go through one bilinear pass (:func:`_bilinear_stack`, half the NumPy calls)."""
        R, n = xy.shape[0], xy.shape[2]
        z = np.empty((R, n))
        g = np.empty((R, 2, n)) if gradient else None
        stack = (lattice[:3],) if lattice is not None else ()
        if self.width * self.height_px <= self._whole_limit and self.width > 1 and self.height_px > 1:
            if self._whole is None:
                self._load_whole()
            stack = ((self._whole.ravel(), self.width, self.height_px),) + stack
        else:                                # windowed tile reads (or a degenerate raster) for the stored heights
            z0, gx, gy = (self._sample_tiles_gradient if self.width * self.height_px > self._whole_limit
                          else functools.partial(self._sample_whole, gradient=True))(xy[0, 0], xy[0, 1])
            z[0] = z0
            if gradient:
                g[0, 0], g[0, 1] = gx, gy
        # A small call: all rasters in one pass; a larger one: one raster at a time (the temporaries of one stay in
        # cache). The same operations on each point either way.
        r0 = R - len(stack)
        for a, b in ((r0, R),) if n <= _STACK_POINTS and stack else ((r, r + 1) for r in range(r0, R)):
            for i in range(0, n, _SAMPLE_CHUNK):
                sl = slice(i, i + _SAMPLE_CHUNK)
                _bilinear_stack(stack[a - r0:b - r0], xy[a:b, :, sl], z[a:b, sl], None if g is None else g[a:b, :, sl])
        return z, g

    def _pixel_affine(self):
        """``(scale, shift)``, (2, 1) arrays: pixel coordinates (centres at integers) = (lon, lat) x scale + shift."""
        affine = self._affine
        if affine is None:
            gt = self._gt
            affine = self._affine = (np.array([[1.0 / gt[1]], [1.0 / gt[5]]]),
                                     np.array([[-gt[0] / gt[1] - 0.5], [-gt[3] / gt[5] - 0.5]]))
        return affine

    def newton_sampler(self, gradient: bool = True):
        """``(lon, lat) -> (h, dh/dlon, dh/dlat)`` for Newton iterations whose result is checked with
        :meth:`sample` (the DEM intersection, METHODS §2), or None when there is none (a projected DEM whose
        gradient is not analytic: use secant steps on :meth:`sample`). NaN off the raster or next to no-data
        whatever the policy (a numeric policy: its height, zero slope), as :meth:`sample_with_gradient`.

        Where :attr:`gradient_is_analytic`, :meth:`sample_with_gradient`'s values. A geographic WGS84 DEM with a
        geoid: the stored bilinear surface plus the geoid's undulation interpolated bilinearly between PROJ's own
        values at the geoid grid's nodes over the DEM (:meth:`_geoid_lattice`: what ``vgridshift`` does, within
        :data:`NEWTON_SAMPLER_TOL_M` of :meth:`sample`, checked when built), with the exact slopes of both: no
        PROJ call at all (PROJ's transform holds the GIL: ~40 % of a DEM intersection's CPU, the part threads
        cannot share). With ``gradient=False``, ``(lon, lat) -> h`` alone: the same heights, bit for bit, without the
        slopes' NumPy calls (the checks of a Newton solution)."""
        if self.is_constant:
            return self.sample_with_gradient if gradient else (lambda lon, lat: self.sample_with_gradient(lon, lat)[0])
        if self._to_dem is not None or (self._geoid is not None and self._geoid_lattice() is None):
            return None
        return self._newton_sample if gradient else self._newton_heights

    def _newton_sample(self, lon, lat, gradient: bool = True):
        """:meth:`newton_sampler` of a geographic WGS84 DEM, with its geoid's lattice when one applies (flat arrays,
        see there): ``(h, dh/dlon, dh/dlat)``, or ``(h, None, None)`` without ``gradient``."""
        lon = np.asarray(lon, dtype=float).ravel()
        lat = np.asarray(lat, dtype=float).ravel()
        lattice = self._geoid_lattice() if self._geoid is not None else None
        # (lon, lat) as the rows of one array, twice with a geoid: the raster's and the lattice's coordinates.
        xy = np.empty((1 if lattice is None else 2, 2, lon.size))
        xy[:, 0] = self._wrap_lon(lon) if self._lon_wrap else lon
        xy[:, 1] = lat
        scale, shift = self._pixel_affine()
        xy[0] *= scale                       # px = lon (1 / gt[1]) + (-gt[0] / gt[1] - 0.5), py alike
        xy[0] += shift
        if lattice is not None:
            xy[1] -= lattice[3]              # (lon - lon0) (1 / dlon), (lat - lat0) (1 / dlat)
            xy[1] *= lattice[4]
        z, g = self._surfaces(xy, lattice, gradient)
        if gradient:
            g *= scale if lattice is None else self._slope_scales()      # m/px -> m/deg
            g = g[0] if lattice is None else np.add(g[0], g[1], out=g[0])
        z = z[0] if lattice is None else np.add(z[0], z[1], out=z[0])
        if not isinstance(self.nodata_policy, str):
            _fallback_with_zero_slope(z, g, self.nodata_policy)
        return (z, None, None) if g is None else (z, g[0], g[1])

    def _slope_scales(self):
        """(2, 2, 1): the raster's and the geoid lattice's pixels per degree (lon, lat), kept."""
        nodes = self._geoid_nodes
        if "scales" not in nodes:
            nodes["scales"] = np.array([self._pixel_affine()[0], self._geoid_lattice()[4]])
        return nodes["scales"]

    def _newton_heights(self, lon, lat):
        """:meth:`newton_sampler` without gradient."""
        return self._newton_sample(lon, lat, gradient=False)[0]

    def _geoid_lattice(self):
        """``(flat N, W, H, origin, inv)``: PROJ's undulation at the geoid grid's nodes over the DEM and one node
        around it (node (i, j) at lon0 + i dlon, lat0 + j dlat: origin [[lon0], [lat0]], inv [[1 / dlon],
        [1 / dlat]]), built once; None when the grid
        cannot be read by GDAL, spans more than 2000 x 2000 nodes here, or the lattice misses PROJ by more than
        :data:`NEWTON_SAMPLER_TOL_M` at 400 points over the DEM."""
        nodes = self._geoid_nodes
        if "lattice" not in nodes:             # built once (the lock only then: sampling threads never wait)
            with self._lock:
                if "lattice" not in nodes:
                    nodes["lattice"] = self._build_geoid_lattice()
        return nodes["lattice"]

    def _build_geoid_lattice(self):
        """:meth:`_geoid_lattice`, with the lock held."""
        try:
            ggt = gdal.Open(grid_path(self._geoid_source)).GetGeoTransform()
        except (RuntimeError, DEMError, AttributeError, TypeError):
            return None
        dx, dy = ggt[1], ggt[5]
        gt = self._gt
        xs = sorted((gt[0], gt[0] + gt[1] * self.width))
        ys = sorted((gt[3], gt[3] + gt[5] * self.height_px))
        x0n, y0n = ggt[0] + 0.5 * dx, ggt[3] + 0.5 * dy              # the grid's first node
        i, j = (np.arange(np.floor(min(f)) - 1, np.ceil(max(f)) + 2)
                for f in (((xs[0] - x0n) / dx, (xs[1] - x0n) / dx), ((ys[0] - y0n) / dy, (ys[1] - y0n) / dy)))
        if i.size > 2000 or j.size > 2000:
            return None
        lon_n, lat_n = x0n + i * dx, y0n + j * dy
        lon_n = lon_n[None, :].repeat(lat_n.size, axis=0)
        lat_n = np.clip(lat_n, -90.0, 90.0)[:, None].repeat(i.size, axis=1)
        nodes = self.geoid_undulation(lon_n.ravel(), lat_n.ravel())
        lattice = (nodes, i.size, j.size, np.array([[x0n + i[0] * dx], [y0n + j[0] * dy]]),
                   np.array([[1.0 / dx], [1.0 / dy]]))
        # Check it against PROJ over the DEM (an odd grid, a convention PROJ reads otherwise: not used).
        u = (np.arange(400) * 0.6180339887) % 1.0
        v = (np.arange(400) * 0.7548776662 + 0.1) % 1.0
        lon_t, lat_t = xs[0] + u * (xs[1] - xs[0]), ys[0] + v * (ys[1] - ys[0])
        n_t = np.empty(400)
        uv = (np.array([lon_t, lat_t]) - lattice[3]) * lattice[4]       # as in _newton_sample
        _bilinear_stack(((nodes, i.size, j.size),), uv[None], n_t[None])
        err = np.abs(n_t - self.geoid_undulation(lon_t, lat_t))
        return lattice if np.all(np.isfinite(nodes)) and np.all(err <= NEWTON_SAMPLER_TOL_M) else None

    # ------------------------------------------------------------------ raster-space access (line-of-sight marches)
    def to_pixel(self, lon, lat):
        """Pixel coordinates ``(px, py)`` of (lon, lat) WGS84 degrees in this raster, pixel centres at integers
        (flat float arrays; the coordinates :meth:`sample_pixel` takes). Not for a constant DEM."""
        x = np.asarray(lon, dtype=float).ravel()
        y = np.asarray(lat, dtype=float).ravel()
        if self._to_dem is not None:
            x, y = self._dem_xy(x, y)
        elif self._lon_wrap:
            x = self._wrap_lon(x)
        gt = self._gt
        return (x - gt[0]) / gt[1] - 0.5, (y - gt[3]) / gt[5] - 0.5

    def sample_pixel(self, px, py):
        """Stored heights (band scale/offset applied, geoid not) at pixel coordinates, bilinear: NaN outside the
        raster or next to no-data (METHODS §2). Windowed tile reads for large rasters, as :meth:`sample`."""
        px = np.asarray(px, dtype=float).ravel()
        py = np.asarray(py, dtype=float).ravel()
        if self.width * self.height_px <= self._whole_limit:
            return self._sample_whole(px, py)
        return self._sample_tiles_gradient(px, py)[0]

    def geoid_undulation(self, lon, lat, *, exact: bool = True):
        """Ellipsoidal minus stored height at (lon, lat): the geoid undulation N when a geoid applies, else 0.

        PROJ's values; with ``exact=False`` those of the lattice of :meth:`newton_sampler` where it has one and
        covers the point (a geographic DEM and one geoid node around it: within :data:`NEWTON_SAMPLER_TOL_M` of
        PROJ, no PROJ call: the line-of-sight march's one value per ray), PROJ's elsewhere."""
        lon = np.asarray(lon, dtype=float).ravel()
        lat = np.asarray(lat, dtype=float).ravel()
        if self._geoid is None:
            return np.zeros(lon.size)
        lattice = None if exact or self._to_dem is not None else self._geoid_lattice()
        if lattice is None:
            _, _, n = self._geoid.transform(lon, lat, np.zeros(lon.size))
            return np.asarray(n, dtype=float)
        uv = np.empty((1, 2, lon.size))
        uv[0, 0] = self._wrap_lon(lon) if self._lon_wrap else lon
        uv[0, 1] = lat
        uv[0] -= lattice[3]                  # as in _newton_sample
        uv[0] *= lattice[4]
        n = _bilinear_stack((lattice[:3],), uv, np.empty((1, lon.size)))[0]
        off = np.flatnonzero(np.isnan(n))    # beyond the lattice (or NaN): PROJ's
        if off.size:
            n[off] = self.geoid_undulation(lon[off], lat[off])
        return n

    def local_max(self, px, py, radius_px):
        """Largest stored height (m) within ``radius_px`` pixels (a square) of the pixels nearest to (px, py),
        clipped into the raster; -inf where that window holds no data. ``radius_px`` may be a tuple of radii
        (then a list, one array per radius). None for a raster too large to hold in memory. The windowed maxima
        are computed once per radius (rounded up to a power of two) and kept."""
        if not self.in_memory:
            return None
        radii = radius_px if isinstance(radius_px, tuple) else (radius_px,)
        tables = [self._local_max_table(r) for r in radii]
        W, H = self.width, self.height_px
        i = np.fmin(np.fmax(np.asarray(py, dtype=float) + 0.5, 0.0), H - 1.0).astype(np.intp)   # NaN -> 0
        j = np.fmin(np.fmax(np.asarray(px, dtype=float) + 0.5, 0.0), W - 1.0).astype(np.intp)
        k = i * W
        k += j
        out = [t.take(k) for t in tables]
        return out if isinstance(radius_px, tuple) else out[0]

    def local_max_slope(self, px, py, radius_px: int):
        """Steepest slope (m/m) of the bilinear surface within ``radius_px`` pixels of (px, py) (as
        :meth:`local_max`; no-data ignored). None for a raster too large to hold in memory."""
        if not self.in_memory:
            return None
        W, H = self.width, self.height_px
        i = np.fmin(np.fmax(np.asarray(py, dtype=float) + 0.5, 0.0), H - 1.0).astype(np.intp)
        j = np.fmin(np.fmax(np.asarray(px, dtype=float) + 0.5, 0.0), W - 1.0).astype(np.intp)
        return self._local_max_table(radius_px, slope=True).take(i * W + j)

    def _local_max_table(self, radius_px: int, slope: bool = False) -> np.ndarray:
        """Windowed maxima (flat) of the heights, or of the cell slopes, radius rounded up to a power of two."""
        r = 1 << (max(math.ceil(radius_px), 1) - 1).bit_length()      # 2 ** ceil(log2(radius)), 1 at least
        key = (r, slope)
        table = self._local_max.get(key)
        if table is not None:
            return table
        with self._lock:                   # computed once, also when several threads ask at once
            return self._local_max_table_locked(r, key, slope)

    def _local_max_table_locked(self, r: int, key, slope: bool) -> np.ndarray:
        """:meth:`_local_max_table` with the lock held."""
        if self._local_max.get(key) is None:
            if self._whole is None:
                self._load_whole()
            z = self._whole
            if slope:
                mx, my = self.pixel_size_m()
                g = np.zeros(z.shape)
                with np.errstate(invalid="ignore"):
                    if z.shape[1] > 1:
                        dx = np.nan_to_num(np.abs(np.diff(z, axis=1)) / mx)
                        g[:, :-1] = np.maximum(g[:, :-1], dx)
                        g[:, 1:] = np.maximum(g[:, 1:], dx)
                    if z.shape[0] > 1:
                        dy = np.nan_to_num(np.abs(np.diff(z, axis=0)) / my)
                        g[:-1] = np.maximum(g[:-1], dy)
                        g[1:] = np.maximum(g[1:], dy)
                table = maximum_filter(g, size=2 * r + 3, mode="nearest")    # + the cells' own extent
            else:
                table = maximum_filter(np.where(np.isnan(z), -np.inf, z), size=2 * r + 1, mode="nearest")
            self._local_max[key] = table.ravel()
        return self._local_max[key]

    def pixel_size_m(self) -> Tuple[float, float]:
        """Approximate pixel size in metres (x, y) at the raster's centre (projected CRS: its units, metres)."""
        if self.is_constant:
            return (np.inf, np.inf)
        if self._pixel_size is None:         # kept (a small call's fixed cost)
            gt = self._gt
            if self._lon_wrap:
                lat = gt[3] + gt[5] * self.height_px / 2
                self._pixel_size = (abs(gt[1]) * 111320.0 * max(np.cos(np.radians(lat)), 1e-6),
                                    abs(gt[5]) * 110574.0)
            else:
                self._pixel_size = (abs(gt[1]), abs(gt[5]))
        return self._pixel_size

    def max_step_px(self) -> Tuple[float, float]:
        """Largest height difference (m) between neighbouring pixels along x and along y: bounds of the bilinear
        surface's slopes in metres per pixel (no-data ignored). ``(inf, inf)`` for a raster too large to hold in
        memory (no bound known without reading it all)."""
        if self.is_constant:
            return (0.0, 0.0)
        if self.width * self.height_px > self._whole_limit:
            return (np.inf, np.inf)
        if self._max_step is None:
            if self._whole is None:
                self._load_whole()
            z = self._whole
            with np.errstate(invalid="ignore"):
                dx = np.abs(np.diff(z, axis=1)) if z.shape[1] > 1 else np.zeros(1)
                dy = np.abs(np.diff(z, axis=0)) if z.shape[0] > 1 else np.zeros(1)
            self._max_step = (float(np.nanmax(dx, initial=0.0)), float(np.nanmax(dy, initial=0.0)))
        return self._max_step

    def _sample_tiles_gradient(self, px, py):
        """Bilinear value and gradient (per pixel) of a large raster, by windowed tile reads (one per tile)."""
        W, H = self.width, self.height_px
        n = px.size
        z = np.full(n, np.nan)
        gx = np.full(n, np.nan)
        gy = np.full(n, np.nan)
        with np.errstate(invalid="ignore"):
            inside = np.isfinite(px) & np.isfinite(py) & (px >= -0.5) & (py >= -0.5) & (px <= W - 0.5) & \
                (py <= H - 0.5)
        idx = np.flatnonzero(inside)
        if idx.size == 0:
            return z, gx, gy
        pxi = np.clip(px[idx], 0.0, W - 1.0)
        pyi = np.clip(py[idx], 0.0, H - 1.0)
        T = self._tile
        tx = np.minimum(np.floor(pxi).astype(np.int64), max(W - 2, 0)) // T
        ty = np.minimum(np.floor(pyi).astype(np.int64), max(H - 2, 0)) // T
        key = ty * (W // T + 2) + tx
        order = np.argsort(key, kind="stable")
        keys_sorted = key[order]
        starts = np.flatnonzero(np.r_[True, keys_sorted[1:] != keys_sorted[:-1]])
        ends = np.r_[starts[1:], keys_sorted.size]
        for a, b in zip(starts, ends):           # one iteration per tile touched, not per point
            sel = order[a:b]
            tile_y, tile_x = int(ty[sel[0]]), int(tx[sel[0]])
            block = self._read_tile(tile_x, tile_y)
            bh, bw = block.shape
            lx = pxi[sel] - tile_x * T
            ly = pyi[sel] - tile_y * T
            zz, gg = np.empty((1, sel.size)), np.empty((1, 2, sel.size))
            _bilinear_stack(((block.ravel(), bw, bh),), np.array([[lx, ly]]), zz, gg)
            j = idx[sel]
            z[j], gx[j], gy[j] = zz[0], gg[0, 0], gg[0, 1]
        return z, gx, gy

    def _height(self, lon, lat, policy: NodataPolicy) -> np.ndarray:
        """:meth:`height` with an explicit no-data policy (iterations ask for NaN without touching the DEM)."""
        lon = np.asarray(lon, dtype=float)
        lat = np.asarray(lat, dtype=float)
        if lon.shape != lat.shape:
            lon, lat = np.broadcast_arrays(lon, lat)
        shape = lon.shape
        if self.is_constant:
            h = np.full(lon.size, self.constant_height)
            h[~(np.isfinite(lon.ravel()) & np.isfinite(lat.ravel()))] = np.nan
            return h.reshape(shape) if shape else float(h[0])
        x, y = lon.ravel(), lat.ravel()
        if self._to_dem is not None:
            x, y = self._dem_xy(x, y)
        if self._lon_wrap:
            x = self._wrap_lon(x)
        h = self._sample_bilinear(x, y)
        if self._geoid is not None:
            ok = np.isfinite(h)
            if np.any(ok):
                _, _, h_ell = self._geoid.transform(lon.ravel()[ok], lat.ravel()[ok], h[ok])
                h[ok] = h_ell
        h = self._apply_nodata(h, lon.ravel(), lat.ravel(), policy)
        return h.reshape(shape) if shape else float(h[0])

    def _dem_xy(self, lon, lat):
        """(lon, lat) -> DEM CRS coordinates: a cubic polynomial fitted over the DEM's footprint where it
        reproduces PROJ to 1e-6 pixel (checked when fitted), PROJ itself elsewhere or when it does not."""
        if self._xy_poly is None:
            self._xy_poly = self._fit_xy_poly()
        fit = self._xy_poly
        if fit is False:
            x, y = self._to_dem.transform(lon, lat)
            return np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        (lo0, la0, lo_s, la_s), coef = fit
        u = (lon - lo0) / lo_s
        v = (lat - la0) / la_s
        with np.errstate(invalid="ignore"):
            inside = (np.abs(u) <= 1.0) & (np.abs(v) <= 1.0)
        x, y = _cubic_eval(coef[0], u, v), _cubic_eval(coef[1], u, v)
        if not np.all(inside):
            out = np.flatnonzero(~inside & np.isfinite(u) & np.isfinite(v))
            if out.size:
                xo, yo = self._to_dem.transform(lon[out], lat[out])
                x[out], y[out] = xo, yo
        return x, y

    def _fit_xy_poly(self):
        """((lon0, lat0, lon_scale, lat_scale), (2, 10) coefficients) or False (see :meth:`_dem_xy`)."""
        w, s_, e, n = self.bounds_lonlat()
        if not (np.isfinite([w, s_, e, n]).all() and e > w and n > s_) or e - w > 2.0 or n - s_ > 2.0:
            return False
        lo0, la0 = 0.5 * (w + e), 0.5 * (s_ + n)
        # The footprint and around it (lines of sight are fitted over their whole height range, which can
        # reach far beyond a small DSM): half its size, 0.02 deg at least, each side.
        lo_s, la_s = max(e - w, 0.02), max(n - s_, 0.02)
        g = np.cos(np.pi * np.arange(12) / 11)
        u, v = (a.ravel() for a in np.meshgrid(g, g))
        x, y = self._to_dem.transform(lo0 + lo_s * u, la0 + la_s * v)
        x0, y0 = self._to_dem.transform(lo0, la0)
        design, ones = _cubic_terms(u, v).T, np.ones(u.size)
        coef = np.array([normal_solve(design, x - x0, ones, hint="DEM CRS polynomial")[0],
                         normal_solve(design, y - y0, ones, hint="DEM CRS polynomial")[0]])
        coef[:, 0] += (x0, y0)
        c = np.linspace(-0.97, 0.97, 15)
        u, v = (a.ravel() for a in np.meshgrid(c, c))
        x, y = self._to_dem.transform(lo0 + lo_s * u, la0 + la_s * v)
        px = coef @ _cubic_terms(u, v)
        err = max(np.max(np.abs(px[0] - x)) / abs(self._gt[1]), np.max(np.abs(px[1] - y)) / abs(self._gt[5]))
        return ((lo0, la0, lo_s, la_s), coef) if err <= 1e-6 else False

    def _wrap_lon(self, x):
        """Longitudes (DEM CRS degrees) outside ``[west, west + 360)`` moved into it by whole turns."""
        if x.size and self._west <= x.min() and x.max() < self._west + 360.0:
            return x                          # all inside (two reductions; NaN fails them): the common case
        with np.errstate(invalid="ignore"):
            off = (x < self._west) | (x >= self._west + 360.0)
        if not np.any(off):
            return x
        return np.where(off, self._west + np.mod(x - self._west, 360.0), x)

    def _apply_nodata(self, h, lon, lat, policy):
        bad = ~np.isfinite(h)
        if not np.any(bad):
            return h
        if isinstance(policy, str):
            if policy == "nan":
                return h
            i = int(np.flatnonzero(bad)[0])
            raise DEMError(f"DEM {self.path}: {int(bad.sum())} point(s) fall outside the DEM or on no-data "
                           f"(first at lon {lon[i]:.6f}, lat {lat[i]:.6f}); use a DEM that covers the scene (a "
                           "larger tile or a mosaic, e.g. gdalbuildvrt)")
        h = h.copy()
        h[bad] = float(policy)
        return h

    def _sample_bilinear(self, x, y):
        """Bilinear interpolation at DEM CRS coordinates; NaN outside the raster or next to no-data."""
        gt = self._gt
        # Pixel coordinates with pixel centres at integers.
        px = (x - gt[0]) / gt[1] - 0.5
        py = (y - gt[3]) / gt[5] - 0.5
        W, H = self.width, self.height_px
        if W * H <= self._whole_limit:
            return self._sample_whole(px, py)
        out = np.full(px.size, np.nan)
        inside = np.isfinite(px) & np.isfinite(py) & (px >= -0.5) & (py >= -0.5) & (px <= W - 0.5) & (py <= H - 0.5)
        if not np.any(inside):
            return out
        idx = np.flatnonzero(inside)
        # Between the outermost pixel centre and the raster edge, hold the edge value.
        pxi = np.clip(px[idx], 0.0, W - 1.0)
        pyi = np.clip(py[idx], 0.0, H - 1.0)
        x0 = np.minimum(np.floor(pxi).astype(np.int64), max(W - 2, 0))
        y0 = np.minimum(np.floor(pyi).astype(np.int64), max(H - 2, 0))
        fx = pxi - x0
        fy = pyi - y0
        T = self._tile
        tx, ty = x0 // T, y0 // T
        key = ty * (W // T + 2) + tx
        if key.size and np.all(key == key[0]):        # common case: every point in one tile, no sort needed
            block = self._read_tile(int(tx[0]), int(ty[0]))
            out[idx] = _bilinear(block, x0 - int(tx[0]) * T, y0 - int(ty[0]) * T, fx, fy)
            return out
        order = np.argsort(key, kind="stable")
        keys_sorted = key[order]
        starts = np.flatnonzero(np.r_[True, keys_sorted[1:] != keys_sorted[:-1]])
        ends = np.r_[starts[1:], keys_sorted.size]
        values = np.empty(idx.size)
        for a, b in zip(starts, ends):           # one iteration per tile touched, not per point
            sel = order[a:b]
            tile_y, tile_x = int(ty[sel[0]]), int(tx[sel[0]])
            block = self._read_tile(tile_x, tile_y)
            values[sel] = _bilinear(block, x0[sel] - tile_x * T, y0[sel] - tile_y * T, fx[sel], fy[sel])
        out[idx] = values
        return out

    @with_gdal_exceptions
    def _load_whole(self) -> None:
        """Read the whole raster once (no-data as NaN, band scale/offset applied) for :meth:`_sample_whole`."""
        with self._lock:
            if self._whole is not None:        # read by another thread meanwhile
                return
            block = self._thread_band().ReadAsArray().astype(float)
            if self._nodata_value is not None:
                block[block == self._nodata_value] = np.nan
            if self._scale != 1.0 or self._offset != 0.0:
                block = block * self._scale + self._offset
            self._whole = block

    def _sample_whole(self, px, py, gradient: bool = False):
        """Bilinear sampling of a small DEM held in memory, at pixel coordinates (pixel centres at integers).

        NaN outside the raster or where a neighbour is no-data. With ``gradient=True`` also returns the
        derivatives of the bilinear surface, ``(z, dz/dpx, dz/dpy)`` in metres per pixel (used by Newton steps of
        the DEM intersection; in the half-pixel border where the edge value is held they are those of the edge
        cell). Points are processed in cache-sized chunks with four flat gathers each (faster than scipy's
        generic ``map_coordinates``).
        """
        if self._whole is None:
            self._load_whole()
        W, H = self.width, self.height_px
        px = np.asarray(px, dtype=float).ravel()
        py = np.asarray(py, dtype=float).ravel()
        n = px.size
        if W < 2 or H < 2:        # degenerate one-row/column raster: scipy handles the edge modes
            coords = np.vstack([np.nan_to_num(py, nan=-1e9), np.nan_to_num(px, nan=-1e9)])
            out = map_coordinates(self._whole, coords, order=1, mode="nearest", prefilter=False)
            with np.errstate(invalid="ignore"):
                out[~((px >= -0.5) & (py >= -0.5) & (px <= W - 0.5) & (py <= H - 0.5))] = np.nan
            return (out, np.zeros(n), np.zeros(n)) if gradient else out
        xy = np.empty((2, n))
        xy[0] = px
        xy[1] = py
        z, g = self._sample_whole_xy(xy, gradient)
        return (z, g[0], g[1]) if gradient else z

    def _sample_whole_xy(self, xy, gradient: bool = False):
        """:meth:`_sample_whole` at pixel coordinates ``xy`` (2, n) (overwritten: scratch): ``(z, g)``, g the
        (2, n) derivatives in m/px (None without ``gradient``)."""
        if self._whole is None:
            self._load_whole()
        W, H = self.width, self.height_px
        n = xy.shape[1]
        if W < 2 or H < 2:
            z, gx, gy = self._sample_whole(xy[0], xy[1], gradient=True)
            return z, (np.array([gx, gy]) if gradient else None)
        stack = ((self._whole.ravel(), W, H),)
        z = np.empty(n)
        g = np.empty((2, n)) if gradient else None
        for i in range(0, n, _SAMPLE_CHUNK):
            sl = slice(i, i + _SAMPLE_CHUNK)
            _bilinear_stack(stack, xy[None, :, sl], z[None, sl], None if g is None else g[None, :, sl])
        return z, g

    @property
    def geoid_applied(self):
        """The geoid whose undulation is added to the stored heights (None: stored heights used as they are)."""
        return self._geoid_name if self._geoid is not None else None

    @with_gdal_exceptions
    def _read_tile(self, tile_x: int, tile_y: int) -> np.ndarray:
        """Read tile (tile_x, tile_y) with a one-pixel overlap to the right and below (LRU cached).

        The lock guards only the cache: the read itself goes through this thread's own dataset handle
        (:meth:`_thread_band`), so threads sampling one DEM read their tiles in parallel. Two threads missing the
        same tile both read it (the same values); the first one stored is kept."""
        key = (tile_x, tile_y)
        with self._lock:
            block = self._cache.get(key)
            if block is not None:
                self._cache.move_to_end(key)
                return block
        T = self._tile
        xoff, yoff = tile_x * T, tile_y * T
        xsize = min(T + 1, self.width - xoff)
        ysize = min(T + 1, self.height_px - yoff)
        block = self._thread_band().ReadAsArray(xoff, yoff, xsize, ysize).astype(float)
        if self._nodata_value is not None:
            block[block == self._nodata_value] = np.nan
        if self._scale != 1.0 or self._offset != 0.0:
            block = block * self._scale + self._offset
        with self._lock:
            block = self._cache.setdefault(key, block)
            self._cache.move_to_end(key)
            if len(self._cache) > self._cache_tiles:
                self._cache.popitem(last=False)
        return block

    def _thread_band(self):
        """The raster band through a dataset handle of the calling thread's own (a GDAL dataset must not be used
        by two threads at once): the DEM's own handle in the thread that opened it, a new one in any other."""
        band = getattr(self._handles, "band", None)
        if band is None:
            ds = gdal.Open(str(self.path))
            band = ds.GetRasterBand(self._band_index)
            self._handles.ds, self._handles.band = ds, band
        return band

    def __repr__(self) -> str:
        if self.is_constant:
            return f"DEM.constant({self.constant_height})"
        return f"DEM.from_file({self.path!r}, geoid={self._geoid_name!r})"


def _cubic_eval(c, u, v) -> np.ndarray:
    """``c @ _cubic_terms(u, v)`` for one row of coefficients, nested (no (10, n) temporary)."""
    a = c[6] * u
    a += c[7] * v
    a += c[4]
    a *= u
    a += c[3] * v
    a += c[1]
    a *= u
    b = c[9] * v
    b += c[8] * u
    b += c[5]
    b *= v
    b += c[2]
    b *= v
    a += b
    a += c[0]
    return a


def _cubic_terms(u, v) -> np.ndarray:
    """The ten monomials of a bivariate cubic (rows)."""
    return np.array([np.ones_like(u), u, v, u * v, u * u, v * v, u ** 3, u * u * v, u * v * v, v ** 3])


def _bilinear(block: np.ndarray, lx, ly, fx, fy) -> np.ndarray:
    """Bilinear interpolation in ``block`` at integer corners (lx, ly) plus fractions (fx, fy).

    SciPy's compiled ``map_coordinates`` (order 1) does the gather and weighting in one pass; a NaN neighbour
    (no-data) with a non-zero weight gives NaN, as it should.
    """
    coords = np.empty((2, lx.size))
    np.add(ly, fy, out=coords[0])
    np.add(lx, fx, out=coords[1])
    return map_coordinates(block, coords, order=1, mode="nearest", prefilter=False)


#: Points per chunk in :meth:`DEM._sample_whole`: one chunk per call of the DEM intersection's fast path (its chunks
#: of 32768 points). Each point is interpolated on its own (the same bits for any chunk). Value and gradient at
#: 32768 random points of SRTM, least CPU of 15 runs (loaded 2-core machine): 41, 36, 32, 30 ns per point for
#: chunks of 4096, 8192, 16384, 32768 (the four gathers' cache misses dominate; fewer calls win).
_SAMPLE_CHUNK = 32768

#: Points up to which :meth:`DEM._surfaces` samples the raster and the geoid's lattice in one pass (fewer NumPy calls);
#: above, one at a time (a stacked pass of 32768 points was 4x slower: its temporaries leave the cache).
_STACK_POINTS = 1024


def _fallback_with_zero_slope(z, g, policy) -> None:
    """A numeric no-data policy in a sampler's output: its height and zero slopes (the rows of g, or None) where z
    is NaN. In place."""
    bad = ~np.isfinite(z)
    if np.any(bad):
        z[bad] = float(policy)
        if g is not None:
            g[:, bad] = 0.0


def _outside(xy, bounds, top):
    """Mask (R, n) of the points (columns of ``xy`` (R, 2, n): rows x, y in raster r) outside ``[-0.5, x1] x
    [-0.5, y1]`` of their raster (``bounds``: (x1, y1) per raster; ``top``: the same as an (R, 2, 1) array) or NaN,
    None when there is none (two reductions tell, without the mask's NumPy calls: a small call's fixed cost)."""
    if xy.shape[2]:
        lo, hi = xy.min(axis=2).tolist(), xy.max(axis=2).tolist()
        if all(-0.5 <= x_lo and -0.5 <= y_lo and x_hi <= x1 and y_hi <= y1
               for (x_lo, y_lo), (x_hi, y_hi), (x1, y1) in zip(lo, hi, bounds)):
            return None
    with np.errstate(invalid="ignore"):
        inside = (xy >= -0.5) & (xy <= top)
    return ~(inside[:, 0] & inside[:, 1])


@functools.lru_cache(maxsize=64)
def _raster_constants(shapes):
    """The constants of :func:`_bilinear_stack` on rasters of ``shapes`` ((W, H), ...), kept (a small call's fixed
    cost): (R, ...) arrays of the last pixel centres [[W - 1], [H - 1]], the last cells' corners as integers, the
    flat offsets of the four corners, the widths; the bounds (W - 0.5, H - 0.5) as floats and as an array."""
    hi = np.array([[[W - 1.0], [H - 1.0]] for W, H in shapes])
    bounds = tuple((W - 0.5, H - 0.5) for W, H in shapes)
    return (hi, hi.astype(np.intp) - 1, np.array([[[0], [1], [W], [W + 1]] for W, _ in shapes]),
            np.array([[W] for W, _ in shapes]), bounds, np.array(bounds)[:, :, None])


def _bilinear_stack(rasters, xy, z, g=None):
    """Bilinear values (and gradients) of R rasters ``rasters`` ((flat, W, H), ...: (H, W) rasters raveled) at
    pixel coordinates ``xy`` (R, 2, n) (rows x, y per raster; overwritten: scratch), into ``z`` (R, n) (and ``g``
    (R, 2, n): d/dx, d/dy per pixel).

    Outside ``[-0.5, W - 0.5] x [-0.5, H - 0.5]`` (or NaN input) the result is NaN; between the outermost pixel
    centre and the raster edge the edge value holds (coordinates clipped), like ``map_coordinates(mode="nearest")``.
    A no-data (NaN) corner makes the result NaN. x and y, and the rasters, go through the same steps as the rows of
    one array, the four corners through one gather per raster (the same operations on each point as one by one, a
    fraction of the NumPy calls: what a small call costs).
    """
    hi, last_cell, corners, width, bounds, top = _raster_constants(tuple((W, H) for _, W, H in rasters))
    outside = _outside(xy, bounds, top)
    np.minimum(xy, hi, out=xy)                # np.clip with scalars is several times slower
    np.maximum(xy, 0.0, out=xy)
    if outside is not None:
        np.copyto(xy, 0.0, where=outside[:, None, :])
    c0 = np.minimum(xy.astype(np.intp), last_cell)                   # the cells' corners (x0, y0)
    xy -= c0                                  # fractions in [0, 1]
    x, y = xy[:, 0], xy[:, 1]
    k = c0[:, 1] * width
    k += c0[:, 0]
    k = k[:, None, :] + corners
    if len(rasters) == 1:
        zc = rasters[0][0].take(k)            # z00, z01, z10, z11
    else:
        zc = np.empty(k.shape)
        for r, (flat, _, _) in enumerate(rasters):
            flat.take(k[r], out=zc[r], mode="clip")      # the indices are inside (clip: an unbuffered out)
    zc[:, 1::2] -= zc[:, 0::2]                # d/dx along the top and the bottom edge
    tb = x[:, None] * zc[:, 1::2]
    tb += zc[:, 0::2]                         # top, bottom
    top, bottom = tb[:, 0], tb[:, 1]
    bottom -= top                             # d/dy
    np.multiply(y, bottom, out=z)
    z += top
    if outside is not None:
        z[outside] = np.nan
    if g is not None:
        gx = g[:, 0]
        np.subtract(zc[:, 3], zc[:, 1], out=gx)
        gx *= y
        gx += zc[:, 1]
        g[:, 1] = bottom
    return z


def geoid_transformer(geoid, source=None):
    """A pyproj transformer adding the geoid undulation N: h_ellipsoidal = H_geoid + N (lon, lat in degrees).

    The grid is found by :func:`gdal_gf4cal.geoid.grid_path` (PROJ's current and legacy grid names).
    """
    grid = grid_path(geoid, source=source)
    try:
        # vgridshift computes Z + multiplier * N in the forward direction; PROJ wants radians for the grid lookup.
        return pyproj.Transformer.from_pipeline(
            f"+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
            f"+step +proj=vgridshift +grids={grid} +multiplier=1 +step +proj=unitconvert +xy_in=rad +xy_out=deg")
    except pyproj.exceptions.ProjError as exc:
        raise DEMError(f"cannot use geoid grid {grid}: {exc}") from None


def _find_proj_grid(name: str) -> Optional[str]:
    """Path of a PROJ grid file by name in PROJ's data directories (see :mod:`gdal_gf4cal.geoid`), or None."""
    for d in proj_search_dirs():
        candidate = os.path.join(d, name)
        if os.path.exists(candidate):
            return candidate
    return None
