"""WGS84 geodesy for the rigorous simulator (METHODS §10): geodetic <-> ECEF, local frames, ray/height intersection.

Everything is vectorised over the leading axes; vectors are ``(..., 3)`` arrays in metres (ECEF).
Precision matters: the simulator's round trip ``localize -> project`` must hold to 1e-6 px, i.e. well below a
micrometre on the ground for sub-metre sensors, so the ECEF -> geodetic conversion iterates to machine precision.
"""
from __future__ import annotations

import numpy as np

from ..geodesy import WGS84_A, WGS84_B, WGS84_E2, WGS84_F  # noqa: F401  (the one set of ellipsoid constants)
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)
GM_EARTH = 3.986004418e14          # m^3 s^-2
OMEGA_EARTH = 7.2921151467e-5      # rad s^-1 (sidereal rotation rate)
GEO_RADIUS = 42164169.0            # geostationary orbit radius, m


def geodetic_to_ecef(lon, lat, h):
    """ECEF (..., 3) from geodetic longitude, latitude (degrees) and ellipsoidal height (m)."""
    lam = np.radians(np.asarray(lon, dtype=float))
    phi = np.radians(np.asarray(lat, dtype=float))
    h = np.asarray(h, dtype=float)
    sp, cp = np.sin(phi), np.cos(phi)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sp * sp)
    x = (n + h) * cp * np.cos(lam)
    y = (n + h) * cp * np.sin(lam)
    z = (n * (1.0 - WGS84_E2) + h) * sp
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(xyz):
    """Geodetic ``(lon, lat, h)`` (degrees, degrees, m) from ECEF (..., 3).

    Bowring's parametric-latitude iteration, three passes: converged to machine precision for any point
    between the Earth's centre region and geostationary altitude.
    """
    xyz = np.asarray(xyz, dtype=float)
    # Contiguous coordinates: on AVX-512 CPUs NumPy computes arctan2, sin, exp ... with SIMD code (SVML) unless a
    # strided input's span (stride x length, past its buffer's end) touches the output's memory, where it falls back
    # to libm, 1 ulp away: on strided columns the bits then depended on where the allocator put the output.
    x, y, z = (np.ascontiguousarray(xyz[..., k]) for k in range(3))
    p = np.hypot(x, y)
    lon = np.degrees(np.arctan2(y, x))
    beta = np.arctan2(z * WGS84_A, p * WGS84_B)
    for _ in range(3):
        sb, cb = np.sin(beta), np.cos(beta)
        phi = np.arctan2(z + WGS84_EP2 * WGS84_B * sb ** 3, p - WGS84_E2 * WGS84_A * cb ** 3)
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(phi), np.cos(phi))
    sp, cp = np.sin(phi), np.cos(phi)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sp * sp)
    # The two height formulas are well conditioned at low / high latitude respectively.
    h = np.where(np.abs(cp) > 0.3, p / np.where(cp == 0, 1, cp) - n, z / np.where(sp == 0, 1, sp) - n * (1 - WGS84_E2))
    return lon, np.degrees(phi), h


def up_vector(lon, lat):
    """Unit ellipsoid normal (..., 3) at geodetic (lon, lat) in degrees."""
    lam = np.radians(np.asarray(lon, dtype=float))
    phi = np.radians(np.asarray(lat, dtype=float))
    return np.stack([np.cos(phi) * np.cos(lam), np.cos(phi) * np.sin(lam), np.sin(phi)], axis=-1)


def enu_basis(lon, lat):
    """East, north, up unit vectors (each (..., 3)) at geodetic (lon, lat)."""
    lam = np.radians(np.asarray(lon, dtype=float))
    phi = np.radians(np.asarray(lat, dtype=float))
    sl, cl, sp, cp = np.sin(lam), np.cos(lam), np.sin(phi), np.cos(phi)
    zero = np.zeros_like(sl)
    east = np.stack([-sl, cl, zero], axis=-1)
    north = np.stack([-sp * cl, -sp * sl, cp], axis=-1)
    up = np.stack([cp * cl, cp * sl, sp], axis=-1)
    return east, north, up


def rot_x(a):
    """Rotation matrices (..., 3, 3) about x by angle(s) ``a`` (rad), active convention."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def rot_y(a):
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def rot_z(a):
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def ray_height_intersection(origin, direction, h, *, first=True):
    """Distance ``t`` along ``origin + t * direction`` (unit direction) where the geodetic height equals ``h``.

    Starts from the exact intersection with the ellipsoid of semi-axes (a + h, b + h) -- close to, but not
    exactly, the surface of constant geodetic height -- then refines ``t`` by Newton steps on the geodetic height
    (derivative = direction . normal). NaN where the ray misses. ``first`` picks the near intersection (the one
    a camera sees); otherwise the far one.
    """
    origin = np.asarray(origin, dtype=float)
    direction = np.asarray(direction, dtype=float)
    h = np.asarray(h, dtype=float)
    ae, be = WGS84_A + h, WGS84_B + h
    w = np.stack(np.broadcast_arrays(1.0 / ae, 1.0 / ae, 1.0 / be), axis=-1)
    ow, dw = origin * w, direction * w
    qa = np.sum(dw * dw, -1)
    qb = 2.0 * np.sum(ow * dw, -1)
    qc = np.sum(ow * ow, -1) - 1.0
    disc = qb * qb - 4 * qa * qc
    sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
    # Numerically stable roots of the quadratic.
    q = -0.5 * (qb + np.copysign(sq, qb))
    r1, r2 = q / qa, qc / q
    t = np.minimum(r1, r2) if first else np.maximum(r1, r2)
    for _ in range(3):
        p = origin + t[..., None] * direction
        lon, lat, hh = ecef_to_geodetic(p)
        slope = np.sum(direction * up_vector(lon, lat), -1)
        t = t - (hh - h) / slope
    return t
