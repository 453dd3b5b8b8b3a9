"""Line-of-sight / DEM intersection for any model with ``localize(sample, line, h)`` (METHODS §1, §2).

The intersection height solves ``f(h) = DEM(localize(s, l, h)) - h = 0``. Most points converge by the plain
height iteration ``h <- DEM(localize(s, l, h))`` in a few steps; where it oscillates or diverges (steep terrain
seen obliquely: |slope x tan(view angle)| >= 1) the root is bracketed by scanning heights from the top of the
DEM's range down (the first sign change seen from the satellite is the visible surface) and refined by the
Illinois variant of regula falsi. Every stage is vectorised over the points still unsolved.
"""
from __future__ import annotations

import logging

import numpy as np

from .dem import DEM

log = logging.getLogger(__name__)


def _as_dem(dem) -> DEM:
    return DEM.coerce(dem)


def _shape_out(values, shape):
    return float(values.reshape(-1)[0]) if shape == () else values.reshape(shape)


def localize_dem(model, sample, line, dem, *, pixel_convention: str = "gdal", tol_m: float = 1e-4,
                 max_iter: int = 30, scan_steps: int = 64, full_output: bool = False):
    """Intersect the lines of sight of image points with a DEM.

    Parameters
    ----------
    model : any object with ``localize(sample, line, h, pixel_convention=...) -> (lon, lat)`` (NaN on failure).
    sample, line : image coordinates (GDAL convention unless ``pixel_convention="rpc"``).
    dem : :class:`DEM` or a constant height (m).
    tol_m : convergence on |DEM(localize(h)) - h| in metres.

    Returns
    -------
    lon, lat, h : arrays (or scalars); NaN where there is no intersection (off the DEM, no convergence).
    With ``full_output=True`` a fourth item, the number of points that failed.
    """
    dem = _as_dem(dem)
    sample, line = np.broadcast_arrays(np.asarray(sample, dtype=float), np.asarray(line, dtype=float))
    shape = sample.shape
    s, l = sample.ravel(), line.ravel()
    n = s.size
    kw = {"pixel_convention": pixel_convention} if pixel_convention != "gdal" else {}

    def loc(idx, h):
        lo, la = model.localize(s[idx], l[idx], h, **kw)
        return np.asarray(lo, dtype=float).reshape(-1), np.asarray(la, dtype=float).reshape(-1)

    def terrain(lo, la):
        ok = np.isfinite(lo) & np.isfinite(la)
        out = np.full(lo.shape, np.nan)
        if np.any(ok):
            out[ok] = _dem_height_nan(dem, lo[ok], la[ok])
        return out

    lon = np.full(n, np.nan)
    lat = np.full(n, np.nan)
    hgt = np.full(n, np.nan)

    if dem.is_constant:
        lo, la = loc(np.arange(n), np.full(n, dem.constant_height))
        lon[:], lat[:], hgt[:] = lo, la, np.where(np.isfinite(lo), dem.constant_height, np.nan)
        return _finish(lon, lat, hgt, shape, full_output)

    h_lo_dem, h_hi_dem = _dem_height_bounds(dem)
    # Stage 1: height iteration from the middle of the DEM's range: a fixed-point step, then secant steps on
    # f(h) = DEM(localize(h)) - h (superlinear; the plain fixed point is only linear and fails where |f'+1| >= 1).
    idx = np.arange(n)
    h = np.full(n, 0.5 * (h_lo_dem + h_hi_dem))
    h_prev = np.full(n, np.nan)
    f_prev = np.full(n, np.nan)
    for _ in range(max_iter):
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
        _bracket_and_refine(loc, terrain, todo, h_lo_dem, h_hi_dem, tol_m, max_iter, scan_steps, lon, lat, hgt)
    n_failed = int(np.count_nonzero(~np.isfinite(hgt)))
    if n_failed:
        log.info("DEM intersection: %d of %d points found no intersection (NaN)", n_failed, n)
    return _finish(lon, lat, hgt, shape, full_output)


def _finish(lon, lat, hgt, shape, full_output):
    out = (_shape_out(lon, shape), _shape_out(lat, shape), _shape_out(hgt, shape))
    if full_output:
        return out + (int(np.count_nonzero(~np.isfinite(hgt))),)
    return out


def _dem_height_nan(dem: DEM, lon, lat):
    """DEM heights inside iterations: NaN off the DEM / in voids for the 'error' and 'nan' policies (a point
    without intersection is NaN, never an exception), the fallback height for a numeric policy."""
    policy = dem.nodata_policy
    return dem._height(lon, lat, "nan" if isinstance(policy, str) else policy)


def _dem_height_bounds(dem: DEM):
    lo, hi = dem.height_range()
    # Geoid undulation is within about +-110 m worldwide; widen the bracket by it and a margin.
    return lo - 120.0, hi + 120.0


def _bracket_and_refine(loc, terrain, todo, h_lo, h_hi, tol_m, max_iter, scan_steps, lon, lat, hgt):
    """Scan heights downwards for the first sign change of f(h) = DEM(h) - h, then Illinois regula falsi."""
    heights = np.linspace(h_hi, h_lo, scan_steps)
    f_prev = np.full(todo.size, np.nan)
    h_prev = np.full(todo.size, np.nan)
    a = np.full(todo.size, np.nan)
    b = np.full(todo.size, np.nan)
    fa = np.full(todo.size, np.nan)
    fb = np.full(todo.size, np.nan)
    found = np.zeros(todo.size, dtype=bool)
    for hk in heights:
        open_ = np.flatnonzero(~found)
        if open_.size == 0:
            break
        lo_, la_ = loc(todo[open_], np.full(open_.size, hk))
        f = terrain(lo_, la_) - hk
        change = np.isfinite(f) & np.isfinite(f_prev[open_]) & (np.sign(f) != np.sign(f_prev[open_]))
        sel = open_[change]
        a[sel], fa[sel] = h_prev[sel], f_prev[sel]
        b[sel], fb[sel] = hk, f[change]
        found[sel] = True
        f_prev[open_] = f
        h_prev[open_] = hk
    k = np.flatnonzero(found)
    side = np.zeros(k.size)  # Illinois bookkeeping: which end was kept last time
    for _ in range(4 * max_iter):
        if k.size == 0:
            return
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
