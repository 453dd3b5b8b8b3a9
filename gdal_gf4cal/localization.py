"""Line-of-sight / DEM intersection for any sensor model (METHODS §1, §2): the localisation layer.

Localisation lives apart from the models (as in Shareloc): a model only has to ``localize(sample, line, h)``;
this module intersects its lines of sight with a :class:`~gdal_gf4cal.dem.DEM` through the DEM's public sampling
API (:meth:`DEM.sample`, :meth:`DEM.sample_with_gradient`, and the raster-space :meth:`DEM.to_pixel`,
:meth:`DEM.sample_pixel`, :meth:`DEM.local_max`) and never reads a private DEM attribute.

The answer is the first crossing of f(h) = DEM(localize(s, l, h)) - h seen from above. Where a ray can cross the
DEM only once (|slope x tan(view angle)| < 1 everywhere near it: smooth terrain) any root is that one, and Newton
or height iterations find it in a few steps. Elsewhere (a DSM's walls, cliffs seen obliquely, holes) the ray is
marched from the top of the DEM's range down (:func:`_march`, as Shareloc and Rugged do over DTM cells): the ray as
a cubic in DEM pixel space, one pixel of ground track per step, longer jumps where windowed maxima of the DEM show
empty space below the ray; no-data samples are stepped over and a crossing inside a hole is bridged (f linear
along the ray between the hole's edges); a ray whose track leaves the raster gives up at once (NaN). The bracket
is refined by the Illinois variant of regula falsi, then polished with the exact model. Every stage is
vectorised over the points still unsolved.

RPC fast path (models with ``rational_polynomial = True``, i.e. :class:`~gdal_gf4cal.rpc.RPCModel`): a cubic
model of the line of sight, Newton steps for the height on it with DEM samples and slopes only (rays crossing
once) or the march on it (the others), then an exact polish (see :func:`_rpc_localize_dem_fast`); the points it
does not settle take the generic path.

More than :data:`gdal_gf4cal.threads.DEM_BLOCK` points are intersected in fixed blocks over the thread pool
(``GF4CAL_NUM_THREADS``), each block a whole intersection: results are bit-identical whatever the thread count.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from ._rpc_poly import _EXPONENTS, monomials, poly_product
from .dem import DEM, NEWTON_SAMPLER_TOL_M
from . import threads
from .threads import matmul, split_points

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LocalizationStats:
    """How a vectorised localisation went (``full_output=True`` of every ``localize`` and ``localize_dem``).

    Attributes
    ----------
    n_points : number of points asked for.
    n_failed : points without a solution (returned as NaN).
    max_iterations : iterations of the longest-running stage (Newton steps, or height iterations for a DEM).
    max_residual_px : largest re-projection error ``|project(localize(p)) - p|`` of the solutions, measured
        (NaN when no point has a solution).
    max_residual_m : for ``localize_dem``, largest ``|DEM(lon, lat) - h|`` of the solutions (NaN otherwise).
    """

    n_points: int
    n_failed: int
    max_iterations: int
    max_residual_px: float = math.nan
    max_residual_m: float = math.nan

    @property
    def n_converged(self) -> int:
        """Points with a solution."""
        return self.n_points - self.n_failed


def _pixel_shift(pixel_convention: str) -> float:
    """Raw RPC00B -> ``pixel_convention`` offset (as :func:`gdal_gf4cal.sensor.pixel_shift`, which imports this
    module)."""
    if pixel_convention == "gdal":
        return 0.5
    if pixel_convention == "rpc":
        return 0.0
    raise ValueError(f"pixel_convention must be 'gdal' or 'rpc', not {pixel_convention!r}")


def _shape_out(values, shape):
    return float(values.reshape(-1)[0]) if shape == () else values.reshape(shape)


def localize_dem(model, sample, line, dem, *, pixel_convention: str = "gdal", tol_m: float = 1e-4,
                 max_iter: int = 30, scan_steps: int = 64, full_output: bool = False, fast_path: bool = True):
    """Intersect the lines of sight of image points with a DEM (METHODS §2).

    Parameters
    ----------
    model : a :class:`~gdal_gf4cal.sensor.SensorModel` (anything with ``localize(sample, line, h,
        pixel_convention=...) -> (lon, lat)``, NaN on failure, and ``project``).
    sample, line : image coordinates (GDAL convention unless ``pixel_convention="rpc"``).
    dem : anything :meth:`DEM.from_user_input` accepts but None (a DEM, a raster path, a constant height in m).
    tol_m : convergence on |DEM(localize(h)) - h| in metres.
    fast_path : use the RPC fast path for RPC models (default); False forces the generic height iteration.

    Returns
    -------
    lon, lat, h : arrays (or Python floats for scalar input): the first crossing of each line of sight with the
    DEM seen from above (on a DSM: the roof or wall, never the ground hidden behind it); across no-data holes
    inside the raster the surface is bridged (interpolated linearly along the ray between the hole's edges).
    NaN where there is no intersection (off the DEM, no convergence), or the DEM's fallback height where its
    no-data policy is a number. With ``full_output=True`` a fourth item, :class:`LocalizationStats`.
    """
    dem = DEM.coerce(dem)
    sample, line = np.asarray(sample, dtype=float), np.asarray(line, dtype=float)
    if sample.shape != line.shape:           # (broadcast_arrays costs a small call ~10 us)
        sample, line = np.broadcast_arrays(sample, line)
    shape = sample.shape
    s, l = sample.ravel(), line.ravel()
    iterations = []

    def block(sb, lb):
        solve = _localize_dem_flat if fast_path else _localize_dem_generic
        lo, la, hb, it = solve(model, sb, lb, dem, pixel_convention, tol_m, max_iter, scan_steps)
        _fallback_height(model, sb, lb, dem, pixel_convention, lo, la, hb)
        iterations.append(it)
        return lo, la, hb

    # Blocks of points over the thread pool: each block is a whole intersection (its own start height, marches
    # and fallbacks), so the result depends on the blocks (fixed by the number of points), never on the threads.
    lon, lat, hgt = split_points(block, s, l, block=threads.DEM_BLOCK)
    iters = max(iterations)
    _warn_implausible_heights(model, dem, hgt)
    out = (_shape_out(lon, shape), _shape_out(lat, shape), _shape_out(hgt, shape))
    if not full_output:
        return out
    return out + (_dem_stats(model, s, l, dem, pixel_convention, lon, lat, hgt, iters),)


def _fallback_height(model, s, l, dem, pixel_convention, lon, lat, hgt) -> None:
    """A DEM with a numeric no-data policy (a fallback height): the points whose line of sight meets no DEM
    surface (off the raster, or into no-data it cannot bridge) are localised at that height. In place."""
    policy = dem.nodata_policy
    if isinstance(policy, str) or dem.is_constant:
        return
    todo = np.flatnonzero(~np.isfinite(hgt))
    if todo.size == 0:
        return
    kw = {"pixel_convention": pixel_convention} if pixel_convention != "gdal" else {}
    lo, la = model.localize(s[todo], l[todo], np.full(todo.size, float(policy)), **kw)
    lo, la = np.asarray(lo, dtype=float).reshape(-1), np.asarray(la, dtype=float).reshape(-1)
    ok = np.isfinite(lo) & np.isfinite(la)
    lon[todo[ok]], lat[todo[ok]], hgt[todo[ok]] = lo[ok], la[ok], float(policy)


def _warn_implausible_heights(model, dem, hgt) -> None:
    """Log a warning when DEM heights lie far outside the RPC's height range (METHODS §2: a DEM in feet or in
    decimetres without its band scale, the wrong DEM): beyond HEIGHT_OFF ± 2 x HEIGHT_SCALE, 500 m at least."""
    height_range = getattr(model, "height_range", None)
    if height_range is None or dem.is_constant or hgt.size == 0:
        return
    lo, hi = height_range
    margin = max(0.5 * (hi - lo), 500.0)
    h_min, h_max = float(np.fmin.reduce(hgt)), float(np.fmax.reduce(hgt))     # NaN ignored, NaN when all are
    if h_min < lo - margin or h_max > hi + margin:
        log.warning("DEM %s: heights %.0f..%.0f m lie far outside the RPC's height range %.0f..%.0f m; check the "
                    "DEM's units (band scale/offset), its vertical datum and that it covers the scene",
                    dem.path, h_min, h_max, lo, hi)


def _dem_stats(model, s, l, dem, pixel_convention, lon, lat, hgt, iters) -> LocalizationStats:
    """Measured residuals of a DEM intersection: re-projection (px) and |DEM - h| (m) of the solutions."""
    ok = np.isfinite(lon) & np.isfinite(lat) & np.isfinite(hgt)
    res_px = res_m = math.nan
    if np.any(ok):
        kw = {"pixel_convention": pixel_convention} if pixel_convention != "gdal" else {}
        ps, pl = model.project(lon[ok], lat[ok], hgt[ok], **kw)
        with np.errstate(invalid="ignore"):
            r = np.hypot(np.asarray(ps, float).ravel() - s[ok], np.asarray(pl, float).ravel() - l[ok])
            dz = np.abs(_dem_height_nan(dem, lon[ok], lat[ok]) - hgt[ok])
        res_px = float(np.nanmax(r)) if np.any(np.isfinite(r)) else math.nan
        res_m = float(np.nanmax(dz)) if np.any(np.isfinite(dz)) else math.nan
    return LocalizationStats(n_points=int(lon.size), n_failed=int(np.count_nonzero(~ok)), max_iterations=int(iters),
                             max_residual_px=res_px, max_residual_m=res_m)


def _localize_dem_flat(model, s, l, dem, pixel_convention, tol_m, max_iter, scan_steps):
    """:func:`localize_dem` on flat arrays: ``(lon, lat, h, iterations)``; the RPC fast path first if it applies."""
    if getattr(model, "rational_polynomial", False) is True and not dem.is_constant:
        lon, lat, h, iters, missed = _rpc_localize_dem_fast(model, s, l, dem, _pixel_shift(pixel_convention),
                                                            tol_m)
        todo = np.flatnonzero(~np.isfinite(h) & ~missed)
        if todo.size:
            lo, la, hh, it2 = _localize_dem_generic(model, s[todo], l[todo], dem, pixel_convention, tol_m, max_iter,
                                                    scan_steps)
            lon[todo], lat[todo], h[todo] = lo, la, hh
            iters = max(iters, it2)
        return lon, lat, h, iters
    return _localize_dem_generic(model, s, l, dem, pixel_convention, tol_m, max_iter, scan_steps)


def _localize_dem_generic(model, s, l, dem, pixel_convention, tol_m, max_iter, scan_steps):
    """The generic height iteration (any model), flat arrays: ``(lon, lat, h, iterations)``."""
    n = s.size
    kw = {"pixel_convention": pixel_convention} if pixel_convention != "gdal" else {}
    heights, tol_m = _terrain_heights(dem, tol_m)

    def loc(idx, h):
        lo, la = model.localize(s[idx], l[idx], h, **kw)
        return np.asarray(lo, dtype=float).reshape(-1), np.asarray(la, dtype=float).reshape(-1)

    def terrain(lo, la):
        ok = np.isfinite(lo) & np.isfinite(la)
        out = np.full(lo.shape, np.nan)
        if np.any(ok):
            out[ok] = heights(lo[ok], la[ok])
        return out

    lon = np.full(n, np.nan)
    lat = np.full(n, np.nan)
    hgt = np.full(n, np.nan)

    if dem.is_constant:
        lo, la = loc(np.arange(n), np.full(n, dem.constant_height))
        lon[:], lat[:], hgt[:] = lo, la, np.where(np.isfinite(lo), dem.constant_height, np.nan)
        return lon, lat, hgt, 1

    h_lo_dem, h_hi_dem = _dem_height_bounds(dem)
    if not _one_crossing(dem, _view_tangent(loc, n, h_lo_dem, h_hi_dem)):
        # A DSM (walls) or steep terrain: several crossings per ray are possible, take the first from the top.
        todo = np.arange(n)
        iterations = _bracket_and_refine(loc, terrain, todo, h_lo_dem, h_hi_dem, tol_m, max_iter, scan_steps, lon,
                                         lat, hgt, dem)
        _log_failed(hgt)
        return lon, lat, hgt, iterations
    # Stage 1: height iteration from the middle of the DEM's range: a fixed-point step, then secant steps on
    # f(h) = DEM(localize(h)) - h (superlinear; the plain fixed point is only linear and fails where |f'+1| >= 1).
    idx = np.arange(n)
    iterations = 0
    h = np.full(n, 0.5 * (h_lo_dem + h_hi_dem))
    h_prev = np.full(n, np.nan)
    f_prev = np.full(n, np.nan)
    for iterations in range(1, max_iter + 1):
        if idx.size == 0:
            break
        hi = h[idx]
        lo, la = loc(idx, hi)
        z = terrain(lo, la)
        f = z - hi
        done = np.abs(f) <= tol_m
        # Return the height the point was localised at (|DEM - h| <= tol_m): re-projection is then exact.
        lon[idx[done]], lat[idx[done]], hgt[idx[done]] = lo[done], la[done], hi[done]
        fp, hp = f_prev[idx], h_prev[idx]
        with np.errstate(divide="ignore", invalid="ignore"):
            secant = hi - f * (hi - hp) / (f - fp)
        use_secant = np.isfinite(secant) & (np.abs(f) < np.abs(fp))
        h_new = np.where(use_secant, secant, z)
        # Points that stop improving (oscillation on steep slopes) or leave the DEM go to stage 2.
        good = ~done & np.isfinite(f) & (np.isnan(fp) | (np.abs(f) < 0.9 * np.abs(fp) + tol_m))
        f_prev[idx], h_prev[idx] = f, hi
        h[idx[good]] = h_new[good]
        idx = idx[good]
    todo = np.flatnonzero(~np.isfinite(hgt))
    if todo.size:
        iterations += _bracket_and_refine(loc, terrain, todo, h_lo_dem, h_hi_dem, tol_m, max_iter, scan_steps, lon,
                                          lat, hgt, dem)
    _log_failed(hgt)
    return lon, lat, hgt, iterations


def _log_failed(hgt) -> None:
    n_failed = int(np.count_nonzero(~np.isfinite(hgt)))
    if n_failed:
        log.info("DEM intersection: %d of %d points found no intersection (NaN)", n_failed, hgt.size)


def _max_slope(dem: DEM) -> float:
    """Steepest slope of the DEM's bilinear surface (m/m; inf when unknown)."""
    sx, sy = dem.max_step_px()
    px, py = dem.pixel_size_m()
    return max(sx / px, sy / py)


#: sqrt(2) (the same double as np.sqrt(2.0), without a NumPy scalar call).
_SQRT2 = math.sqrt(2.0)


def _one_crossing(dem: DEM, tan_view) -> np.ndarray:
    """Whether a line of sight with this tangent of its view angle crosses the DEM once only (slope x tan(view)
    < 1 everywhere, with a margin for the two axes): then any root found is the first from the top."""
    return _max_slope(dem) * _SQRT2 * np.asarray(tan_view) < 0.9


def _one_crossing_near(dem: DEM, G, h0) -> np.ndarray:
    """:func:`_one_crossing` per ray of the cubic rays ``G`` (lon, lat in u = h - h0), with the steepest slope
    of the DEM near each ray's track (within the track's length of its point at h0) where the DEM is held in
    memory, the DEM's steepest slope otherwise."""
    tan_view = 1.1 * np.hypot(G[1] * 111320.0 * np.cos(np.radians(G[4])), G[5] * 110574.0)
    if G.shape[1] == 0:
        return np.zeros(0, dtype=bool)
    if _one_crossing(dem, tan_view).all():
        return np.ones(G.shape[1], dtype=bool)
    h_lo, h_hi = _dem_height_bounds(dem)
    radius = float(tan_view.max()) * max(h_hi - h0, h0 - h_lo) / min(dem.pixel_size_m()) + 2.0
    if not math.isfinite(radius) or radius > 512 or not dem.in_memory:
        return _one_crossing(dem, tan_view)
    # Rays that never fly over the DEM: to the march, which drops them at once.
    near = _near_footprint(dem, _track_ends(G, h_lo - h0, h_hi - h0))
    if near.all():                           # the usual case: no compaction
        px, py = dem.to_pixel(G[0], G[4])
        return dem.local_max_slope(px, py, math.ceil(radius)) * _SQRT2 * tan_view < 0.9
    near = np.flatnonzero(near)
    px, py = dem.to_pixel(G[0, near], G[4, near])
    once = np.zeros(G.shape[1], dtype=bool)
    once[near] = dem.local_max_slope(px, py, math.ceil(radius)) * _SQRT2 * tan_view[near] < 0.9
    return once


def _track_ends(G, u0: float, u1: float) -> np.ndarray:
    """(4, n) lon, lat at ``u0``, then at ``u1`` of the cubic rays ``G`` (lon, lat in u = h - h0): one (4, 8) x
    (8, n) product instead of four Horner evaluations (24 NumPy calls)."""
    p0, p1 = ((1.0, u, u * u, u * u * u) for u in (u0, u1))
    z = (0.0,) * 4
    return poly_product(np.array([p0 + z, z + p0, p1 + z, z + p1]), G)


def _view_tangent(loc, n, h_lo, h_hi) -> float:
    """Largest tan(view angle) (ground metres per metre of height) over a subsample of the points (NaN -> inf)."""
    sub = np.arange(0, n, max(1, n // 64))
    lo1, la1 = loc(sub, np.full(sub.size, h_hi))
    lo0, la0 = loc(sub, np.full(sub.size, h_lo))
    with np.errstate(invalid="ignore"):
        d = np.hypot((lo1 - lo0) * 111320.0 * np.cos(np.radians(la0)), (la1 - la0) * 110574.0) / (h_hi - h_lo)
    return float(np.max(d)) if np.all(np.isfinite(d)) else np.inf


def _dem_height_nan(dem: DEM, lon, lat):
    """DEM heights inside iterations: NaN off the DEM / in voids for the 'error' and 'nan' policies (a point
    without intersection is NaN, never an exception), the fallback height for a numeric policy."""
    policy = dem.nodata_policy
    return dem.sample(lon, lat, nodata="nan" if isinstance(policy, str) else policy)


def _terrain_heights(dem: DEM, tol_m: float):
    """``(heights(lon, lat), tol)`` of the generic path's checks |DEM - h| <= tol (and the fast path's start height):
    on a DEM with a geoid, the Newton sampler's heights where it has one (:func:`_newton_sampler`: the geoid's lattice,
    within NEWTON_SAMPLER_TOL_M of :meth:`DEM.sample`, tol is tol_m less that, as in the fast path's polish: no PROJ
    call per height iteration, PROJ holds the GIL); :meth:`DEM.sample` (NaN off the DEM) otherwise, the same bits
    as ever."""
    if dem.geoid_applied is not None:
        return _newton_sampler(dem, tol_m)[1:]
    return (lambda lon, lat: _dem_height_nan(dem, lon, lat)), tol_m


def _dem_height_bounds(dem: DEM):
    lo, hi = dem.height_range()
    # Geoid undulation is within about +-110 m worldwide; widen the bracket by it and a margin.
    return lo - 120.0, hi + 120.0


def _bracket_and_refine(loc, terrain, todo, h_lo, h_hi, tol_m, max_iter, scan_steps, lon, lat, hgt, dem=None):
    """The first crossing of f(h) = DEM(h) - h from the top down, then Illinois regula falsi with exact
    localisations; holes bridged (:func:`_march`). Returns the number of height evaluations made.

    The line of sight of each point is modelled as a cubic in h through four exact localisations (for the
    march only); the bracket the march finds is then refined with ``loc`` itself. (``scan_steps``, the fixed
    scan of earlier versions, is no longer used: the march steps one DEM pixel of ground track.)"""
    if dem is None or dem.is_constant:
        return 0
    ray = _LineOfSight.from_localizer(loc, todo, dem, h_lo, h_hi)
    br = _march(ray, dem)
    steps = br.steps
    # Bridged points: the exact localisation at the height interpolated across the hole.
    j = np.flatnonzero(br.bridged)
    if j.size:
        lo_, la_ = loc(todo[j], br.h[j])
        ok = np.isfinite(lo_) & np.isfinite(la_)
        lon[todo[j[ok]]], lat[todo[j[ok]]], hgt[todo[j[ok]]] = lo_[ok], la_[ok], br.h[j[ok]]
    k = np.flatnonzero(br.found & ~br.bridged)
    return steps + _illinois(loc, terrain, todo[k], br.a[k], br.b[k], br.fa[k], br.fb[k], tol_m, max_iter, lon,
                             lat, hgt)


def _illinois(loc, terrain, todo, a, b, fa, fb, tol_m, max_iter, lon, lat, hgt):
    """Illinois regula falsi on brackets [a, b] of f = DEM(loc(h)) - h (fa < 0 <= fb), exact localisations;
    writes the solutions into lon, lat, hgt at ``todo``. Returns the number of steps."""
    k = np.arange(todo.size)
    side = np.zeros(k.size)  # Illinois bookkeeping: which end was kept last time
    steps = 0
    for _ in range(4 * max_iter):
        if k.size == 0:
            return steps
        steps += 1
        ak, bk, fak, fbk = a[k], b[k], fa[k], fb[k]
        c = np.where(fbk != fak, bk - fbk * (bk - ak) / (fbk - fak), 0.5 * (ak + bk))
        lo_, la_ = loc(todo[k], c)
        z = terrain(lo_, la_)
        fc = z - c
        done = np.isfinite(fc) & (np.abs(fc) <= tol_m)
        tk = todo[k[done]]
        lon[tk], lat[tk], hgt[tk] = lo_[done], la_[done], c[done]
        bad = ~np.isfinite(fc)
        left = np.sign(fc) == np.sign(fak)   # root between c and b
        # Replace the end with the same sign as fc; halve the other end's value when it is kept twice (Illinois).
        new_a = np.where(left, c, ak)
        new_fa = np.where(left, fc, np.where(side < 0, fak / 2, fak))
        new_b = np.where(left, bk, c)
        new_fb = np.where(left, np.where(side > 0, fbk / 2, fbk), fc)
        side = np.where(left, 1.0, -1.0)
        a[k], fa[k], b[k], fb[k] = new_a, new_fa, new_b, new_fb
        keep = ~done & ~bad
        k, side = k[keep], side[keep]
    return steps


# ------------------------------------------------------------------------------- first crossing from the top
#: Chebyshev nodes on [-1, 1] where each line of sight is localised exactly to fit its cubic, and the inverse
#: Vandermonde matrix giving the cubic's coefficients (t^0..t^3) from the four positions.
_NODES = np.cos(np.pi * (2 * np.arange(4) + 1) / 8)
_VINV = np.linalg.inv(np.vander(_NODES, 4, increasing=True))

#: March step along a line of sight: this many DEM pixels of ground track per step.
_STEP_PX = 1.0

#: Window radii (pixels) of the windowed DEM maxima that let the march jump over empty space, shortest first.
_JUMP_PX = (4, 8)

#: Rays marched together (their state, 18 floats each, stays in cache).
_MARCH_CHUNK = 16384

#: Bisection steps that locate a hole's edges along a line of sight (1/32 of a step).
_EDGE_STEPS = 5


@dataclass
class _LineOfSight:
    """Lines of sight as cubics in DEM pixel space: ``px(t), py(t)`` with ``h = h_mid + h_half * t``, t in [-1, 1]
    (top at t = 1), and each ray's geoid undulation (DEM stored height + N = ellipsoidal height)."""

    C: np.ndarray          # (8, m): coefficients t^0..t^3 of px, then py
    h_mid: np.ndarray      # (m,)
    h_half: np.ndarray     # (m,)
    n_geoid: np.ndarray    # (m,)

    @classmethod
    def from_lonlat(cls, lonlat_at, dem, h_lo, h_hi):
        """From ``lonlat_at(h) -> (lon, lat)`` (arrays over the rays, h an array too) between heights h_lo..h_hi."""
        h_mid = 0.5 * (h_lo + h_hi)
        h_half = 0.5 * (h_hi - h_lo)
        P = np.empty((2, 4, np.size(h_mid)))
        lon_c = lat_c = None
        for k, node in enumerate(_NODES):
            lon, lat = lonlat_at(h_mid + h_half * node)
            P[0, k], P[1, k] = dem.to_pixel(lon, lat)
            if k == 1:
                lon_c, lat_c = lon, lat
        C = np.concatenate([matmul(_VINV, P[0]), matmul(_VINV, P[1])])
        ok = np.isfinite(lon_c) & np.isfinite(lat_c)
        n_geoid = np.zeros(np.size(h_mid))
        if np.any(ok):
            n_geoid[ok] = dem.geoid_undulation(lon_c[ok], lat_c[ok], exact=False)      # the lattice's: no PROJ
        return cls(C, np.broadcast_to(h_mid, n_geoid.shape).copy(), np.broadcast_to(h_half, n_geoid.shape).copy(),
                   n_geoid)

    @classmethod
    def from_localizer(cls, loc, todo, dem, h_lo, h_hi):
        """From exact localisations ``loc(idx, h)`` of the points ``todo``."""
        return cls.from_lonlat(lambda h: loc(todo, np.broadcast_to(h, todo.shape).astype(float)), dem,
                               np.full(todo.size, float(h_lo)), np.full(todo.size, float(h_hi)))

    def pixel(self, i, t):
        """(px, py) of rays ``i`` at ``t``."""
        C = self.C[:, i]
        return _horner_pair(C, t)

    def f(self, dem, i, t):
        """DEM minus ray height (m) of rays ``i`` at ``t``: < 0 above the surface; NaN off the DEM / in holes."""
        px, py = self.pixel(i, t)
        return dem.sample_pixel(px, py) + self.n_geoid[i] - (self.h_mid[i] + self.h_half[i] * t)


@dataclass
class _Brackets:
    """What :func:`_march` found per ray: ``found``; the bracket [a, b] in height (a above, fa < 0 <= fb);
    ``bridged`` rays crossed the surface inside a hole, ``h`` is then the height interpolated across it."""

    found: np.ndarray
    bridged: np.ndarray
    a: np.ndarray
    b: np.ndarray
    fa: np.ndarray
    fb: np.ndarray
    h: np.ndarray
    steps: int


def _clip_to_raster(ray, dem):
    """Part [t_lo, t_hi] of each ray's straight ground track (top to bottom) inside the raster plus one pixel
    (Liang-Barsky); empty (t_lo > t_hi) for a ray that never flies over the DEM."""
    m = ray.C.shape[1]
    i = np.arange(m)
    x1, y1 = ray.pixel(i, np.ones(m))
    x0, y0 = ray.pixel(i, -np.ones(m))
    lo, hi = np.full(m, -1.0), np.full(m, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        for p0, p1, edge_lo, edge_hi in ((x0, x1, -1.5, dem.width + 0.5), (y0, y1, -1.5, dem.height_px + 0.5)):
            d = p1 - p0                                  # t from -1 (p0) to 1 (p1): p = p0 + d (t + 1) / 2
            ta = -1.0 + 2.0 * (edge_lo - p0) / d
            tb = -1.0 + 2.0 * (edge_hi - p0) / d
            t_in, t_out = np.minimum(ta, tb), np.maximum(ta, tb)
            flat = d == 0
            inside = (p0 >= edge_lo) & (p0 <= edge_hi)
            t_in = np.where(flat, np.where(inside, -1.0, np.inf), t_in)
            t_out = np.where(flat, np.where(inside, 1.0, -np.inf), t_out)
            lo, hi = np.fmax(lo, t_in), np.fmin(hi, t_out)
    bad = ~np.isfinite(ray.C).all(axis=0)
    lo[bad], hi[bad] = 1.0, -1.0
    return lo, hi


def _march(ray, dem):
    """First crossing of each line of sight with the DEM from the top down (METHODS §2), vectorised.

    Steps of about one DEM pixel of ground track from where the ray enters the raster; a ray leaving the raster
    (or never over it) ends with no crossing at once. The crossing is the first sample at or below the surface
    after a sample above it; no-data samples are stepped over: a crossing after a hole is bridged, i.e. f is
    interpolated linearly across the hole between its edges (located by bisection) along the ray.
    """
    m = ray.C.shape[1]
    out = _Brackets(np.zeros(m, bool), np.zeros(m, bool), *(np.full(m, np.nan) for _ in range(5)), 0)
    t_lo, t_hi = _clip_to_raster(ray, dem)
    z_lo, z_hi = dem.height_range()
    if not dem.height_range_is_exact:          # approximate statistics: leave room above and below
        z_lo, z_hi = z_lo - 0.05 * (z_hi - z_lo) - 1.0, z_hi + 0.05 * (z_hi - z_lo) + 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hi = np.fmin(t_hi, (z_hi + ray.n_geoid + 0.5 - ray.h_mid) / ray.h_half)
        t_lo = np.fmax(t_lo, (z_lo + ray.n_geoid - 0.5 - ray.h_mid) / ray.h_half)
    c = ray.C
    rate = np.abs(c[1]) + 2 * np.abs(c[2]) + 3 * np.abs(c[3])          # |dpx/dt| bound on [-1, 1]
    rate = np.maximum(rate, np.abs(c[5]) + 2 * np.abs(c[6]) + 3 * np.abs(c[7]))
    with np.errstate(divide="ignore"):
        dt = np.minimum(_STEP_PX / rate, 2.0)
    t_top = t_hi.copy()
    _start_below_local_max(ray, dem, rate, t_lo, t_hi)
    f_start = np.full(t_hi.size, np.nan)
    with np.errstate(invalid="ignore"):
        live = np.flatnonzero((t_lo <= t_hi) & (t_hi < t_top))
        f_start[live] = ray.f(dem, live, t_hi[live])
        f_start[f_start >= 0] = np.nan
        hole = live[np.isnan(f_start[live])]
        # A ray starting in a hole: a crossing in the hole is bridged from the last data above it, wherever that
        # is (as a march from the top does): look for it upwards, step by step (all above the surface there).
        t_up, f_up, t_nan = _data_above(ray, dem, hole, t_hi[hole], t_top[hole], dt[hole])
    idx = np.flatnonzero(t_lo <= t_hi)
    # State of the live rays, one row per ray (compacted with one contiguous gather per step): the ray's cubic
    # (8), h_mid - geoid, h_half, then t, t_end, dt, the last sample above the surface (tp, fp), the first no-data
    # sample after it (tn: the hole's entry, NaN if none yet), the previous sample's t, the ray's index.
    S = np.empty((idx.size, 18))
    S[:, 0:8] = ray.C[:, idx].T
    S[:, 8], S[:, 9] = ray.h_mid[idx] - ray.n_geoid[idx], ray.h_half[idx]
    S[:, 10], S[:, 11], S[:, 12] = t_hi[idx], t_lo[idx], dt[idx]
    S[:, 13:16] = np.nan
    S[:, 16], S[:, 17] = t_hi[idx], idx
    # Rays whose start sample is known above the surface (below a local maximum) take their first step at once;
    # those starting in a hole carry the data above it (tp, fp) and the hole's entry (tn).
    known = np.isfinite(f_start[idx])
    S[known, 13], S[known, 14] = t_hi[idx[known]], f_start[idx[known]]
    row = np.full(m, -1)
    row[idx] = np.arange(idx.size)
    k = row[hole]
    S[k, 13], S[k, 14], S[k, 15] = t_up, f_up, t_nan
    known[k] = True
    S[known, 10] = np.maximum(S[known, 10] - S[known, 12], S[known, 11])
    hits = []
    steps = 0
    jump = dem.in_memory
    with np.errstate(invalid="ignore"):
        for i in range(0, S.shape[0], _MARCH_CHUNK):      # chunks: the state of a chunk stays in cache
            steps = max(steps, _march_chunk(S[i:i + _MARCH_CHUNK], dem, jump, hits))
        if hits:
            _settle(ray, dem, out, *(np.concatenate(v) for v in zip(*hits)))
    out.steps = steps
    return out


def _data_above(ray, dem, i, t0, t_top, dt):
    """Walk rays ``i`` up from t0 (a no-data sample) by ``dt`` to t_top at most: ``(t, f, t_nan)``, the first
    sample with data (NaN where none), f there, and the no-data sample just below it (the hole's entry)."""
    t_found = np.full(i.size, np.nan)
    f_found = np.full(i.size, np.nan)
    t_nan = t0.copy()
    k = np.arange(i.size)
    t = t0.copy()
    while k.size:
        t_next = np.minimum(t + dt[k], t_top[k])
        f = ray.f(dem, i[k], t_next)
        data = np.isfinite(f)
        t_found[k[data]], f_found[k[data]] = t_next[data], f[data]
        go = ~data & (t_next < t_top[k])
        t_nan[k[~data]] = t_next[~data]
        k, t = k[go], t_next[go]
    f_found[f_found >= 0] = np.nan          # cannot happen below the local maximum; never a false bracket
    t_found[np.isnan(f_found)] = np.nan
    t_nan[np.isnan(f_found)] = np.nan
    return t_found, f_found, t_nan


def _march_chunk(S, dem, jump, hits) -> int:
    """The march loop of :func:`_march` on the state rows ``S`` of some rays; appends the crossings found to
    ``hits``; returns the number of steps."""
    steps = 0
    while S.shape[0]:
        steps += 1
        T = S.T
        t = T[10]
        px, py = _horner_pair(T[0:8], t)
        z = dem.sample_pixel(px, py)
        f = z - (T[8] + T[9] * t)
        fin = np.isfinite(f)
        above = fin & (f < 0)
        hit = fin & ~above
        has_above = np.isfinite(T[14])
        j = np.flatnonzero(hit & has_above)
        if j.size:
            hits.append((T[17, j].astype(np.intp), T[13, j], T[14, j], t[j], f[j], T[15, j], T[16, j]))
        T[15] = np.where(above, np.nan, np.where(has_above & ~fin & np.isnan(T[15]), t, T[15]))
        T[13] = np.where(above, t, T[13])
        T[14] = np.where(above, f, T[14])
        keep = ~hit & (t > T[11])
        if not keep.all():
            S = S[keep]
            T = S.T
        T[16] = T[10]
        # Jump r - 2 pixels at once where the ray stays above the highest DEM point within r pixels (a windowed
        # maximum, r in _JUMP_PX): no crossing can lie in between (-2: rounding, bilinear neighbours).
        step = T[12]
        if jump:
            pxk, pyk = (px, py) if keep.all() else (px[keep], py[keep])
            for r, zmax in zip(_JUMP_PX, dem.local_max(pxk, pyk, _JUMP_PX)):   # the longest jump allowed wins
                far = (r - 2) * T[12]
                step = np.where(T[8] + T[9] * (T[10] - far) > zmax + 0.01, far, step)
        T[10] = np.maximum(T[10] - step, T[11])
    return steps


def _start_below_local_max(ray, dem, rate, t_lo, t_hi) -> None:
    """Lower each ray's start ``t_hi`` to the highest DEM point near its track (a windowed maximum of the DEM
    around the middle of the track, as wide as the track is long): nothing above can be hit. A ray with no data
    near its track gets an empty range. In place; nothing for DEMs too large to hold in memory."""
    last = np.inf
    for _ in range(4):               # the track shortens with each pass: repeat with a narrower window
        live = np.flatnonzero(t_lo <= t_hi)
        if live.size == 0:
            return
        half = 0.5 * rate[live] * (t_hi[live] - t_lo[live])
        radius = float(np.max(half)) + 2.0               # + rounding to a pixel and the bilinear neighbours
        if not np.isfinite(radius) or radius > 512 or radius > 0.7 * last:
            return
        last = radius
        t_mid = 0.5 * (t_hi[live] + t_lo[live])
        px, py = ray.pixel(live, t_mid)
        z = dem.local_max(px, py, int(np.ceil(radius)))
        if z is None:
            return
        with np.errstate(invalid="ignore"):
            top = (z + ray.n_geoid[live] + 0.5 - ray.h_mid[live]) / ray.h_half[live]
        t_hi[live] = np.where(np.isneginf(z), -np.inf, np.fmin(t_hi[live], top))


def _settle(ray, dem, out, i, ta, fa, tb, fb, tn, t_exit):
    """Record the brackets of rays ``i`` crossing between ta (above) and tb (at/below); where a hole lies between
    (tn: its first no-data sample, t_exit the last no-data sample before tb), bisect both hole edges and
    interpolate across it, unless a sample there finds the crossing before or after the hole."""
    gap = np.isfinite(tn)
    g = np.flatnonzero(gap)
    if g.size:
        a, f_a, e_in = ta[g], fa[g], tn[g]
        b, f_b, e_out = tb[g], fb[g], t_exit[g]
        plain = np.zeros(g.size, bool)
        for _ in range(_EDGE_STEPS):
            # Hole entry edge, between a (data, above) and e_in (no data).
            mid = 0.5 * (a + e_in)
            fm = ray.f(dem, i[g], mid)
            dat = np.isfinite(fm) & ~plain
            below = dat & (fm >= 0)                # crossing before the hole: a plain bracket [a, mid]
            b, f_b = np.where(below, mid, b), np.where(below, fm, f_b)
            plain |= below
            up = dat & (fm < 0)
            a, f_a = np.where(up, mid, a), np.where(up, fm, f_a)
            e_in = np.where(~np.isfinite(fm), mid, e_in)
            # Hole exit edge, between e_out (no data) and b (data, at/below).
            mid = 0.5 * (e_out + b)
            fm = ray.f(dem, i[g], mid)
            dat = np.isfinite(fm) & ~plain
            up = dat & (fm < 0)                    # crossing after the hole: a plain bracket [mid, b]
            a, f_a = np.where(up, mid, a), np.where(up, fm, f_a)
            plain |= up
            below = dat & (fm >= 0)
            b, f_b = np.where(below, mid, b), np.where(below, fm, f_b)
            e_out = np.where(~np.isfinite(fm) & ~plain, mid, e_out)
        ta, fa, tb, fb = ta.copy(), fa.copy(), tb.copy(), fb.copy()
        ta[g], fa[g], tb[g], fb[g] = a, f_a, b, f_b
        gap[g] = ~plain
    hm, hh = ray.h_mid[i], ray.h_half[i]
    out.found[i] = True
    out.bridged[i] = gap
    out.a[i], out.b[i], out.fa[i], out.fb[i] = hm + hh * ta, hm + hh * tb, fa, fb
    tc = ta - fa * (tb - ta) / (fb - fa)
    out.h[i] = np.where(gap, hm + hh * tc, np.nan)


# ---------------------------------------------------------------------------------------------- RPC fast path
def _rpc_localize_dem_fast(rpc, s, l, dem, shift, tol_m, ray_iter: int = 12, polish_iter: int = 4):
    """RPC x DEM fast path of :func:`localize_dem` (METHODS §1-§2): ``(lon, lat, h, iterations)``, NaN where it
    did not settle (the caller retries those on the generic path).

    Per chunk of points (all temporaries stay in cache):

    1. *Ray.* The approximate inverse (cubic in x, y, H) gives, for fixed image point, (L, P) as a cubic in H
       around a scene start height h0; one Newton step with the exact Jacobian (incl. d/dH) at h0 corrects
       its value and slope, so the cubic ray is exact at h0 and within ~1e-3 px over 1.5 normalised heights.
    2. *Height on the ray* with DEM samples only: Newton on f(h) = DEM(ray(h)) - h with the slopes of
       :meth:`DEM.newton_sampler` (geoid-corrected DEMs: the geoid's own lattice, no PROJ call; secant steps on
       :meth:`DEM.sample` where there is none: reprojected DEMs).
    3. *Polish:* exact localisation at h by chord Newton (1e-8 px), DEM check |DEM - h| <= tol_m (on the
       Newton sampler's heights, with its NEWTON_SAMPLER_TOL_M off tol_m: no PROJ call); points that
       miss it take a Newton step in h on the ray re-anchored at the exact point, and are polished again.
    """
    n = s.size
    x = (s - shift - rpc.samp_off) / rpc.samp_scale
    y = (l - shift - rpc.line_off) / rpc.line_scale
    sampler, heights, tol_p = _newton_sampler(dem, tol_m)
    with np.errstate(all="ignore"):
        h0 = _dem_start_height(rpc, x, y, dem)
        basis = _ray_basis(rpc._approximate_inverse, (h0 - rpc.height_off) / rpc.height_scale)
        if n <= _DEM_CHUNK:                  # one chunk (a small call): its arrays as they are, no copies
            R, J, G, u, slope, ready = _dem_chunk_ray(rpc, x, y, dem, sampler, h0, basis, tol_m, ray_iter)
        else:
            R, J, G = np.empty((8, n)), np.empty((4, n)), np.empty((8, n))
            u, slope = np.empty(n), np.empty(n)
            ready = np.empty(n, dtype=bool)
            for i in range(0, n, _DEM_CHUNK):
                sl = slice(i, i + _DEM_CHUNK)
                R[:, sl], J[:, sl], G[:, sl], u[sl], slope[sl], ready[sl] = _dem_chunk_ray(
                    rpc, x[sl], y[sl], dem, sampler, h0, basis, tol_m, ray_iter)
        # 2b. The others (several crossings possible, holes, Newton failures): the first crossing from the top,
        # all at once (a march is a few cheap steps over many rays).
        bridged = np.zeros(n, dtype=bool)
        missed = np.zeros(n, dtype=bool)
        todo = np.flatnonzero(~ready)
        if todo.size:
            _march_rpc_ray(G[:, todo], h0, dem, todo, u, slope, ready, bridged, missed)
        if n <= _DEM_CHUNK:
            out = _dem_chunk_polish(rpc, x, y, R, J, u, slope, ready, bridged, h0, heights, tol_p, polish_iter)
        else:
            out = np.empty((3, n))
            for i in range(0, n, _DEM_CHUNK):
                sl = slice(i, i + _DEM_CHUNK)
                out[:, sl] = _dem_chunk_polish(rpc, x[sl], y[sl], R[:, sl], J[:, sl], u[sl], slope[sl], ready[sl],
                                               bridged[sl], h0, heights, tol_p, polish_iter)
    return out[0], out[1], out[2], ray_iter + polish_iter, missed


def _newton_sampler(dem: DEM, tol_m: float):
    """``(sampler, heights, tol)`` of the fast path: ``sampler(lon, lat) -> (h, dh/dlon, dh/dlat)`` of its height
    steps (:meth:`DEM.newton_sampler`; slopes None where the DEM has none: secant steps), ``heights(lon, lat)`` of
    the polish's check |DEM - h| <= tol: the sampler's own heights (within NEWTON_SAMPLER_TOL_M of
    :meth:`DEM.sample`: tol is tol_m less that), else :meth:`DEM.sample`. NaN off the DEM for the 'error' and 'nan'
    policies."""
    if isinstance(dem.nodata_policy, str) and dem.nodata_policy != "nan":
        dem = dem.with_nodata("nan")
    sampler = dem.newton_sampler()
    if sampler is not None:
        return sampler, dem.newton_sampler(gradient=False), max(tol_m - NEWTON_SAMPLER_TOL_M, 0.5 * tol_m)

    def exact(lon, lat):
        return _dem_height_nan(dem, lon, lat)
    return lambda lon, lat: (exact(lon, lat), None, None), exact, tol_m


#: Points per chunk of the DEM-intersection fast path (half a block of :data:`gdal_gf4cal.threads.DEM_BLOCK`): the
#: fewest NumPy calls whose temporaries (256 KB each) still stay in this machine's L2 (512 KB a core). Measured on
#: SRTM + EGM96, 500k points, one run, loaded 2-core machine: CPU per point 8192: 1.00, 16384: 0.96-1.07,
#: 32768: 0.81-0.90, 65536: 1.01 (its temporaries no longer fit); 2-thread switches fall with the chunk count.
_DEM_CHUNK = 32768

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
    B = [[0.0] * 10 for _ in range(8)]         # Python floats: the same IEEE operations, no NumPy scalar calls
    a0, a1 = A.tolist()
    for j, q, k, c, p in _RAY_BASIS_TERMS:
        w = c * Hm ** p
        B[k][q] += a0[j] * w
        B[4 + k][q] += a1[j] * w
    return np.array(B)


#: ``(j, q, k, comb(eh, k), eh - k)`` of :func:`_ray_basis`: term j of the RPC00B order (x, y, H exponents ex, ey,
#: eh) adds to row k (power of t) of column q (its H-free term) its coefficient times comb(eh, k) Hm^(eh - k).
_RAY_BASIS_TERMS = tuple((j, [(ex_, ey_) for _, ex_, ey_ in _XY_TERMS].index((ex, ey)), k, math.comb(eh, k), eh - k)
                         for j, (ex, ey, eh) in enumerate(_EXPONENTS) for k in range(eh + 1))


def _horner_pair(C, u):
    """Two cubics in u at once, rows 0..3 and 4..7 of C (8, N) (coefficients of u^0..u^3): (2, N), each row
    c[0] + c[1] u + c[2] u² + c[3] u³ (the same operations as one at a time, half the NumPy calls)."""
    c = C.reshape(2, 4, -1).transpose(1, 0, 2)              # c[k]: the u^k coefficients of both (views)
    r = c[3] * u
    r += c[2]
    r *= u
    r += c[1]
    r *= u
    r += c[0]
    return r


def _dem_start_height(rpc, x, y, dem) -> float:
    """One start height for the scene: middle of the DEM heights under a subsample of the points (approximate; on
    a geoid DEM the Newton sampler's heights, :func:`_terrain_heights`: no PROJ call, a small call's fixed cost)."""
    lo, hi = dem.height_range()
    mid = 0.5 * (lo + hi)
    step = max(1, x.size // 512)
    xs, ys = x[::step], y[::step]
    A = rpc._approximate_inverse
    L, P = poly_product(A, monomials(xs, ys, np.full(xs.size, (mid - rpc.height_off) / rpc.height_scale)))
    heights = _terrain_heights(dem, 0.0)[0]
    z = heights(L * rpc.long_scale + rpc.long_off, P * rpc.lat_scale + rpc.lat_off)
    if z.size == 0:
        return mid
    z_lo, z_hi = float(np.fmin.reduce(z)), float(np.fmax.reduce(z))     # NaN ignored (off the DEM), NaN when all are
    return 0.5 * (z_lo + z_hi) if z_lo == z_lo else mid


def _dem_chunk_ray(rpc, x, y, dem, sample, h0, basis, tol_m, ray_iter):
    """Stages 1 and 2 of :func:`_rpc_localize_dem_fast` on one chunk: ``(R, J, G, u, slope, ready)``, the rays
    (normalised, their inverse Jacobians, in degrees per metre) and the heights u = h - h0 found by Newton
    steps where ``ready``."""
    m = x.size
    hs = rpc.height_scale
    Hm = (h0 - rpc.height_off) / hs
    # 1. Ray: cubic in t = H - Hm from the approximate inverse, value and slope corrected by one exact Newton step.
    R = poly_product(basis, _xy_monomials(x, y))                # rows L0..L3, P0..P3
    L0, P0 = R[0], R[4]
    V = poly_product(rpc._coeffs_with_derivatives, monomials(L0, P0, np.full(m, Hm)))
    xe, ye = V[0] / V[1], V[2] / V[3]
    # d(x, y)/d(L, P, H): rows xL, xP, xH from V[4, 8, 12] and V[5, 9, 13], yL, yP, yH from V[6, 10, 14] and
    # V[7, 11, 15] (strided views: three rows per NumPy call, each row the same operations as one by one).
    xL, xP, xH = (V[4::4] - xe * V[5::4]) / V[1]
    yL, yP, yH = (V[6::4] - ye * V[7::4]) / V[3]
    det = xL * yP - xP * yL
    # Inverse Jacobian d(L, P)/d(x, y), reused for every chord-Newton step of the polish.
    J = np.empty((4, m))
    np.divide(yP, det, out=J[0])
    np.divide(-xP, det, out=J[1])
    np.divide(-yL, det, out=J[2])
    np.divide(xL, det, out=J[3])
    rx, ry = x - xe, y - ye
    R[0::4] += J[0::2] * rx + J[1::2] * ry                  # L0, P0 (rows 0, 4)
    R[1::4] = -(J[0::2] * xH + J[1::2] * yH)                # exact d(L, P)/dH along the line of sight (rows 1, 5)
    # The ray as cubics of (lon, lat) in u = h - h0 metres.
    G = R * np.array([[rpc.long_scale / hs ** k] for k in range(4)] + [[rpc.lat_scale / hs ** k] for k in range(4)])
    G[0] += rpc.long_off
    G[4] += rpc.lat_off

    # 2. Height on the ray, DEM samples only, where the ray crosses the DEM once (smooth terrain, steep view).
    tol_a = max(tol_m, _TOL_A)
    u = np.zeros(m)
    slope = np.full(m, -1.0)
    ready = np.zeros(m, dtype=bool)
    finite = np.isfinite(G[0::4])                              # lon0, lat0, then their slopes: one row each
    finite &= np.isfinite(R[1::4])
    idx = np.flatnonzero(finite[0] & finite[1])
    idx = idx[_one_crossing_near(dem, G[:, idx], h0)]
    Ga = G[:, idx]
    uu = np.zeros(idx.size)
    f_prev = np.full(idx.size, np.nan)
    u_prev = np.full(idx.size, np.nan)
    for it in range(ray_iter):
        if idx.size == 0:
            break
        z, zp, zq = sample(*_horner_pair(Ga, uu))
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
        if good.all():                       # none settled, none dropped (a small call's usual step): no compaction
            f_prev, u_prev, uu = f, uu, unew
            continue
        j = idx[done]
        u[j], slope[j], ready[j] = unew[done], d[done], True
        keep = np.flatnonzero(good)
        idx, Ga, f_prev, u_prev, uu = idx[keep], Ga[:, keep], f[keep], uu[keep], unew[keep]
    return R, J, G, u, slope, ready


def _dem_chunk_polish(rpc, x, y, R, J, u, slope, ready, bridged, h0, heights, tol_m, polish_iter):
    """Stage 3 of :func:`_rpc_localize_dem_fast` on one chunk: (3, m) lon, lat, h, NaN where unsettled;
    ``bridged`` heights (interpolated across a hole) are taken as they are once localised exactly."""
    out = np.full((3, x.size), np.nan)
    hs = rpc.height_scale
    Hm = (h0 - rpc.height_off) / hs
    # 3. Polish: exact localisation at h, then the DEM check; re-anchor the ray at the exact point and step in h.
    idx = np.flatnonzero(ready)
    if idx.size == 0:
        return out
    Rp, Jp, xp, yp = R[:, idx], J[:, idx], x[idx], y[idx]
    up, sp, bp = u[idx], slope[idx], bridged[idx]
    u_last = np.full(idx.size, np.nan)          # the previous polish step's height and |DEM - h| (secant slope)
    f_last = np.full(idx.size, np.nan)
    dL = np.zeros(idx.size)
    dP = np.zeros(idx.size)
    tol_x, tol_y = 1e-8 / abs(rpc.samp_scale), 1e-8 / abs(rpc.line_scale)
    for _ in range(polish_iter):
        if idx.size == 0:
            break
        t = up / hs
        H = t + Hm
        Lr, Pr = _horner_pair(Rp, t)
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
        f = heights(lon, lat) - h
        done = exact & ((np.abs(f) <= tol_m) | bp)          # bridged: the height interpolated across a hole
        j = idx[done]
        out[0, j], out[1, j], out[2, j] = lon[done], lat[done], h[done]
        if j.size == idx.size:               # all settled (a small call's usual first step)
            break
        keep = np.flatnonzero(~done & exact & np.isfinite(f))
        secant = (f - f_last) / (up - u_last)                # (under the caller's errstate)
        sp = np.where(np.isfinite(secant) & (secant < 0), secant, sp)
        idx, Rp, Jp, xp, yp, sp = idx[keep], Rp[:, keep], Jp[:, keep], xp[keep], yp[keep], sp[keep]
        bp = bp[keep]
        dL, dP = (L - Lr)[keep], (P - Pr)[keep]
        u_last, f_last = up[keep], f[keep]
        up = up[keep] - f[keep] / sp
    return out


def _march_rpc_ray(G, h0, dem, todo, u, slope, ready, bridged, missed):
    """Stage 2b of :func:`_rpc_localize_dem_fast`: the first crossing from the top on the cubic rays ``G`` (lon,
    lat in u = h - h0), refined on them by Illinois steps; fills u, slope, ready, bridged at ``todo`` and marks
    the rays without crossing in ``missed``."""
    h_lo, h_hi = _dem_height_bounds(dem)

    def lonlat_at(h):
        uu = h - h0
        return _horner_pair(G, uu)

    near = _near_footprint(dem, np.concatenate([lonlat_at(h_lo), lonlat_at(h_hi)]))
    missed[todo[~near]] = True
    todo, G = todo[near], G[:, near]
    ray = _LineOfSight.from_lonlat(lonlat_at, dem, np.full(todo.size, h_lo), np.full(todo.size, h_hi))
    br = _march(ray, dem)
    missed[todo[~br.found]] = True
    k = np.flatnonzero(br.found & ~br.bridged)
    h, d, stepped = _illinois_on_ray(ray, dem, k, br.a[k], br.b[k], br.fa[k], br.fb[k], _TOL_A)
    hb = br.h.copy()
    hb[k] = h
    br.bridged[k] = stepped
    sl = np.full(todo.size, -1.0)
    sl[k] = d
    ok = br.found & np.isfinite(hb)
    j = todo[ok]
    u[j], slope[j], ready[j], bridged[j] = hb[ok] - h0, sl[ok], True, br.bridged[ok]


def _near_footprint(dem, ends) -> np.ndarray:
    """False for the rays whose ground track from (lon0, lat0) to (lon1, lat1), the rows of ``ends`` (4, n), lies
    wholly beyond one side of the DEM's lon/lat bounds widened by 10 % (they cannot cross it: known at once, before
    any fit or sample). Both ends against all four sides in two comparisons (a small call's fixed cost)."""
    w, s_, e, n = dem.bounds_lonlat()
    mx, my = 0.1 * (e - w) + 1e-6, 0.1 * (n - s_) + 1e-6
    if not dem.is_geographic and (e - w > 5.0 or n - s_ > 5.0 or max(abs(s_), abs(n)) > 80.0):
        return np.ones(ends.shape[1], dtype=bool)     # a projected footprint its corners may not bound
    lons = ends[0::2]
    if dem.is_geographic and lons.size and not (w <= lons.min() and lons.max() < w + 360.0):
        ends = ends.copy()                   # compared modulo 360 (as sampled), when needed
        ends[0::2] = w + np.mod(lons - w, 360.0)
    lo = ends < np.array([[w - mx], [s_ - my], [w - mx], [s_ - my]])      # NaN: False, as before
    hi = ends > np.array([[e + mx], [n + my], [e + mx], [n + my]])
    lo[:2] &= lo[2:]                         # both ends west of the DEM, south of it
    hi[:2] &= hi[2:]
    lo[:2] |= hi[:2]
    return ~(lo[0] | lo[1])


def _illinois_on_ray(ray, dem, i, a, b, fa, fb, tol, max_iter: int = 30):
    """Illinois regula falsi on the cubic rays ``i`` of ``ray`` within brackets [a, b] (heights, fa < 0 <= fb):
    ``(h, df/dh, stepped)``: the root to ``tol`` m, the slope of f just above it (NaN where it failed), and
    where a step fell into no-data, h is the linear interpolation of the bracket across it (``stepped``)."""
    h = np.full(i.size, np.nan)
    d = np.full(i.size, np.nan)
    stepped = np.zeros(i.size, dtype=bool)
    k = np.arange(i.size)
    side = np.zeros(i.size)
    a, b, fa, fb = a.copy(), b.copy(), fa.copy(), fb.copy()
    for _ in range(max_iter):
        if k.size == 0:
            break
        ak, bk, fak, fbk = a[k], b[k], fa[k], fb[k]
        c = np.where(fbk != fak, bk - fbk * (bk - ak) / (fbk - fak), 0.5 * (ak + bk))
        ik = i[k]
        fc = ray.f(dem, ik, (c - ray.h_mid[ik]) / ray.h_half[ik])
        done = np.isfinite(fc) & (np.abs(fc) <= tol)
        h[k[done]] = c[done]
        hole = np.isnan(fc)         # a hole's edge inside the bracket: step over it (f linear across it)
        h[k[hole]] = c[hole]
        stepped[k[hole]] = True
        left = np.sign(fc) == np.sign(fak)
        a[k] = np.where(left, c, ak)
        fa[k] = np.where(left, fc, np.where(side < 0, fak / 2, fak))
        b[k] = np.where(left, bk, c)
        fb[k] = np.where(left, np.where(side > 0, fbk / 2, fbk), fc)
        side = np.where(left, 1.0, -1.0)
        keep = ~done & ~hole
        k, side = k[keep], side[keep]
    ok = np.flatnonzero(np.isfinite(h) & ~stepped)
    io = i[ok]
    step = 1e-2                                     # slope of f just above the root (m/m), for the polish
    with np.errstate(invalid="ignore"):
        d[ok] = ray.f(dem, io, (h[ok] + step - ray.h_mid[io]) / ray.h_half[io]) / step
        d[~(d < 0)] = -1.0
    return h, d, stepped
