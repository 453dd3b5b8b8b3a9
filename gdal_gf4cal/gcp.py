"""Ground control point tables: one schema for the whole project (DESIGN.md "GCP table schema").

A GCP table is a :class:`geopandas.GeoDataFrame` in EPSG:4326 whose geometry is the ground point, with columns

``id`` (str), ``lon``, ``lat`` (degrees WGS84), ``h`` (ellipsoidal metres), ``sample``, ``line`` (pixels, GDAL
convention: centre of the first pixel at 0.5), ``role`` (``"control"`` or ``"check"``), ``sigma`` (px, a priori
measurement precision) and optionally ``truth_sample``, ``truth_line``, quality columns and ``outlier``.

Readers accept CSV (header required), GeoPackage and GeoJSON; more formats (QGIS ``.points``, raster GCPs, layers
in other CRSs) live in :mod:`gdal_gf4cal.gcp_formats`.
"""
from __future__ import annotations

import os
from typing import Optional, Sequence

import numpy as np

from .atomic import atomic_output
from .errors import GCPError, InputOverwriteError

REQUIRED = ("lon", "lat", "sample", "line")
SCHEMA = ("id", "lon", "lat", "h", "sample", "line", "role", "sigma")
ROLES = ("control", "check")


def make_gcps(lon, lat, h, sample, line, *, ids: Optional[Sequence] = None, role="control", sigma=1.0, **extra):
    """Build a GCP GeoDataFrame from arrays (extra keyword arrays become columns)."""
    import pandas as pd
    lon = np.asarray(lon, dtype=float).ravel()
    n = lon.size
    data = {
        "id": [str(i) for i in (ids if ids is not None else range(1, n + 1))],
        "lon": lon,
        "lat": np.asarray(lat, dtype=float).ravel(),
        "h": np.broadcast_to(np.asarray(h, dtype=float), (n,)).copy() if np.ndim(h) == 0 else
        np.asarray(h, dtype=float).ravel(),
        "sample": np.asarray(sample, dtype=float).ravel(),
        "line": np.asarray(line, dtype=float).ravel(),
        "role": np.broadcast_to(np.asarray(role, dtype=object), (n,)).copy(),
        "sigma": np.broadcast_to(np.asarray(sigma, dtype=float), (n,)).copy(),
    }
    for key, value in extra.items():
        data[key] = np.broadcast_to(np.asarray(value), (n,)).copy() if np.ndim(value) == 0 else np.asarray(value)
    df = pd.DataFrame(data)
    return _to_geodataframe(df)


def _to_geodataframe(df):
    import geopandas as gpd
    geometry = gpd.points_from_xy(df["lon"].to_numpy(float), df["lat"].to_numpy(float))
    return gpd.GeoDataFrame(df, geometry=geometry, crs="EPSG:4326")


def validate_gcps(gdf, *, source: str = "GCPs", dem=None, need_height: bool = True):
    """Check and complete a GCP table: required columns, finite numbers, ids, roles, sigma, heights.

    A missing or NaN height is taken from ``dem`` (a :class:`gdal_gf4cal.dem.DEM`, geoid-aware) when given,
    else it is an error. Returns a new GeoDataFrame following the schema.
    """
    import pandas as pd
    df = pd.DataFrame(gdf).copy()
    df.columns = [str(c).strip() for c in df.columns]
    lower = {c.lower(): c for c in df.columns}
    df = df.rename(columns={lower[k]: k for k in ("id", "lon", "lat", "h", "sample", "line", "role", "sigma")
                            if k in lower and lower[k] != k})
    missing = [c for c in REQUIRED if c not in df.columns]
    if missing:
        raise GCPError(f"{source}: missing column(s) {', '.join(missing)}; expected "
                       "id,lon,lat,h,sample,line[,role][,sigma]")
    if len(df) == 0:
        raise GCPError(f"{source}: no GCPs")
    for c in ("lon", "lat", "sample", "line") + (("h",) if "h" in df.columns else ()):
        values = pd.to_numeric(df[c], errors="coerce").astype(float)
        bad = ~np.isfinite(values.to_numpy())
        if c != "h" and bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise GCPError(f"{source}: column {c} has a missing, non-numeric or infinite value (row {row + 1})")
        df[c] = values
    if "id" not in df.columns:
        df["id"] = [str(i) for i in range(1, len(df) + 1)]
    df["id"] = df["id"].astype(str)
    if df["id"].duplicated().any():
        raise GCPError(f"{source}: duplicate GCP id {df['id'][df['id'].duplicated()].iloc[0]!r}")
    if "h" not in df.columns:
        df["h"] = np.nan
    if not np.all(np.isfinite(df["h"].to_numpy())):
        if dem is None:
            if need_height:
                raise GCPError(f"{source}: {int((~np.isfinite(df['h'].to_numpy())).sum())} GCP(s) without height; "
                               "give a DEM (--dem) to take heights from it")
        else:
            # Errors when the DEM has no value under a GCP (never a NaN height from a nodata="nan" DEM).
            from .gcp_formats import fill_heights
            df = fill_heights(df, dem, source=source)
    if ((df["lat"].abs() > 90) | (df["lon"].abs() > 360)).any():
        raise GCPError(f"{source}: lon/lat out of range; GCP ground coordinates must be WGS84 degrees "
                       "(reproject the layer to EPSG:4326 or give its CRS)")
    if "role" not in df.columns:
        df["role"] = "control"
    df["role"] = df["role"].fillna("control").astype(str).str.strip().str.lower()
    bad = ~df["role"].isin(ROLES)
    if bad.any():
        raise GCPError(f"{source}: role {df['role'][bad].iloc[0]!r} is not 'control' or 'check'")
    if "sigma" not in df.columns:
        df["sigma"] = 1.0
    df["sigma"] = pd.to_numeric(df["sigma"], errors="coerce").fillna(1.0).astype(float)
    if (df["sigma"] <= 0).any():
        raise GCPError(f"{source}: sigma must be positive")
    if "geometry" in df.columns:
        df = df.drop(columns="geometry")
    ordered = list(SCHEMA) + [c for c in df.columns if c not in SCHEMA]
    return _to_geodataframe(df[ordered].reset_index(drop=True))


def read_gcps(path, *, dem=None, layer: Optional[str] = None, need_height: bool = True):
    """Read a GCP table from CSV (header required), GeoPackage or GeoJSON; see the module docstring.

    Vector layers go through :func:`gdal_gf4cal.gcp_formats.read_gcp_layer` (any CRS, field aliases, Z heights);
    other formats (QGIS ``.points``, rasters with GCPs) through :func:`gdal_gf4cal.gcp_formats.read_gcps_any`.
    """
    import pandas as pd
    path = os.fspath(path)
    if not os.path.exists(path):
        raise GCPError(f"GCP file not found: {path}")
    ext = os.path.splitext(path)[1].lower()
    try:
        if ext in (".csv", ".txt"):
            df = pd.read_csv(path, skipinitialspace=True, comment="#")
        elif ext in (".gpkg", ".geojson", ".json", ".shp", ".fgb"):
            # Vector layers in any CRS, field-name aliases (col/row, x/y, ...), heights from a Z geometry.
            from .gcp_formats import read_gcp_layer
            return read_gcp_layer(path, layer=layer, dem=dem)
        else:
            from .gcp_formats import read_gcps_any  # .points files, rasters with embedded GCPs
            return read_gcps_any(path, dem=dem)
    except GCPError:
        raise
    except Exception as exc:  # pandas/fiona raise many types; report one line
        raise GCPError(f"cannot read GCPs from {path}: {str(exc).splitlines()[0]}") from None
    return validate_gcps(df, source=path, dem=dem, need_height=need_height)


def write_gcps(gdf, path, *, layer: str = "gcps", overwrite: bool = True) -> str:
    """Write a GCP table to ``.csv``, ``.gpkg`` or ``.geojson`` (by extension), atomically.

    ``sample, line`` are written as they are (GDAL convention). Raises
    :class:`~gdal_gf4cal.errors.InputOverwriteError` if ``path`` exists and ``overwrite`` is false.
    """
    path = os.fspath(path)
    if not overwrite and os.path.exists(path):
        raise InputOverwriteError(f"{path} exists; choose another output or allow overwriting")
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".csv", ".gpkg", ".geojson", ".json"):
        raise GCPError(f"cannot write GCPs as {ext!r}; use .csv, .gpkg or .geojson")
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with atomic_output(path) as tmp:
        if ext == ".csv":
            df = gdf.drop(columns="geometry") if "geometry" in gdf.columns else gdf
            df.to_csv(tmp, index=False)   # shortest repr: floats read back identical
        elif ext == ".gpkg":
            _to_geodataframe(gdf.drop(columns="geometry", errors="ignore")).to_file(tmp, layer=layer, driver="GPKG")
        else:
            _to_geodataframe(gdf.drop(columns="geometry", errors="ignore")).to_file(tmp, driver="GeoJSON")
    return path


def split_roles(gdf, check_fraction: float = 0.0, seed: int = 0):
    """Assign roles at random: ``check_fraction`` of the points become checkpoints (seeded), the rest control."""
    if not 0.0 <= check_fraction < 1.0:
        raise GCPError("check fraction must be in [0, 1)")
    out = gdf.copy()
    n = len(out)
    n_check = int(round(check_fraction * n))
    roles = np.array(["control"] * n, dtype=object)
    if n_check:
        idx = np.random.default_rng(seed).choice(n, size=n_check, replace=False)
        roles[idx] = "check"
    out["role"] = roles
    return out
