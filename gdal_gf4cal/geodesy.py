"""WGS84 ellipsoid constants, radii of curvature and coordinate transformers: the one geodesy helper of the engine
(METHODS §6, §7).

Used wherever image or angular offsets become metres on the ground (CE90 in metres, intersection's local east /
north / up frame), and wherever coordinates change CRS (:func:`crs_transformer`: DEMs, reference orthos, GCP files,
the ortho's extent, reports); the rigorous simulator (:mod:`gdal_gf4cal.simulate.geodesy`) takes its constants from
here.
"""
from __future__ import annotations

from functools import lru_cache
from typing import Tuple

import numpy as np

WGS84_A = 6378137.0                      # semi-major axis, m
WGS84_F = 1.0 / 298.257223563            # flattening
WGS84_B = WGS84_A * (1.0 - WGS84_F)      # semi-minor axis, m
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)     # first eccentricity squared

__all__ = ["WGS84_A", "WGS84_F", "WGS84_B", "WGS84_E2", "radii_of_curvature", "metres_per_degree",
           "crs_transformer"]


def radii_of_curvature(lat_deg) -> Tuple[np.ndarray, np.ndarray]:
    """Prime-vertical ``N`` and meridian ``M`` radii of curvature (m) of WGS84 at geodetic latitude ``lat_deg``.

    ``N = a / W``, ``M = a (1 - e^2) / W^3`` with ``W = sqrt(1 - e^2 sin^2 phi)``.
    """
    phi = np.radians(np.asarray(lat_deg, dtype=float))
    w = np.sqrt(1.0 - WGS84_E2 * np.sin(phi) ** 2)
    return WGS84_A / w, WGS84_A * (1.0 - WGS84_E2) / w ** 3


def metres_per_degree(lat_deg, h_m=0.0) -> Tuple[np.ndarray, np.ndarray]:
    """Metres per degree of longitude and of latitude at ``lat_deg`` and ellipsoidal height ``h_m`` (WGS84)."""
    rn, rm = radii_of_curvature(lat_deg)
    phi = np.radians(np.asarray(lat_deg, dtype=float))
    h = np.asarray(h_m, dtype=float)
    return np.radians(1.0) * (rn + h) * np.cos(phi), np.radians(1.0) * (rm + h)


@lru_cache(maxsize=32)
def crs_transformer(source, target):
    """The :class:`pyproj.Transformer` from CRS ``source`` to CRS ``target`` (anything
    :meth:`pyproj.CRS.from_user_input` takes: ``"EPSG:4326"``, a WKT, a CRS), x = easting or longitude first.

    One per pair of CRSs in a process: building one costs 3-8 ms of PROJ database work (a DEM opened twice in one
    ``refine --ortho`` paid it twice), using one costs nothing; pyproj's Transformer is thread-safe (from 3.1: each
    thread gets its own PROJ object). A CRS pyproj cannot read raises its :class:`pyproj.exceptions.CRSError`.
    """
    import pyproj
    return pyproj.Transformer.from_crs(pyproj.CRS.from_user_input(source), pyproj.CRS.from_user_input(target),
                                       always_xy=True)
