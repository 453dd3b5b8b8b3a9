"""Ground control point tables: one schema for the whole project (DESIGN.md "GCP table schema").

A GCP table is a :class:`pandas.DataFrame` (no geometry: :func:`to_geodataframe` adds the EPSG:4326 ground point
for export), with columns

``id`` (str), ``lon``, ``lat`` (degrees WGS84), ``h`` (ellipsoidal metres), ``sample``, ``line`` (pixels, GDAL
convention: centre of the first pixel at 0.5), ``role`` (``"control"`` or ``"check"``), ``sigma`` (px, a priori
measurement precision) and optionally ``truth_sample``, ``truth_line``, quality columns and ``outlier``.

The schema itself (:func:`make_gcps`, :func:`validate_gcps`) lives in :mod:`gdal_gf4cal.observations`: this table
is the one-image view of the observation table. :func:`read_gcps` / :func:`write_gcps` dispatch to the format
readers and writers of :mod:`gdal_gf4cal.gcp_formats` (CSV with or without header, GeoPackage/GeoJSON layers,
orthority GeoJSON, QGIS ``.points``, ASP ``.gcp``, OTB tie points, raster GCPs). Import order, without cycles:
``observations`` <- ``gcp_formats`` <- ``gcp``.
"""
from __future__ import annotations

import os
from typing import Optional

import numpy as np

from . import gcp_formats
from .atomic import atomic_output
from .errors import GCPError

# The schema lives with the observation table (this table is its one-image view); re-exported here.
from .observations import REQUIRED, ROLES, SCHEMA, fill_heights, make_gcps, to_geodataframe, validate_gcps
from .outputs import check_output_path

__all__ = ["REQUIRED", "SCHEMA", "ROLES", "make_gcps", "validate_gcps", "fill_heights", "read_gcps", "write_gcps",
           "split_roles", "to_geodataframe"]


def read_gcps(path, *, dem=None, layer: Optional[str] = None, need_height: bool = True,
              columns: Optional[str] = None, pixel_convention: Optional[str] = None, image: Optional[str] = None,
              crs=None):
    """Read a GCP table from any supported file; see :func:`gdal_gf4cal.gcp_formats.read_gcps_any`.

    Parameters
    ----------
    dem : DEM (geoid-aware) to take missing heights from.
    layer : layer of a GeoPackage.
    need_height : without a DEM, a GCP without height is an error when true.
    columns : column map of a header-less CSV/text file, e.g. ``"id,sample,line,lon,lat,h"`` (CLI ``--columns``).
    pixel_convention : ``"corner"`` (GDAL: pixel corners at integers, centre of the first pixel at 0.5) or
        ``"center"`` (pixel centres at integers, as orthority, ASP and the RPC00B offsets): the convention of the
        file's image coordinates (CLI ``--gcp-pixel-convention``). None = the format's own (centre for orthority
        GeoJSON and ASP ``.gcp``, corner for everything else, and GDAL's own reading of GeoTIFF tie points).
        The table returned is always in the GDAL convention.
    image : the image the GCPs belong to: selects its rows in multi-image files (orthority ``filename``, ASP
        ``.gcp``, observation tables; matched on the file stem) and maps QGIS ``.points`` through its geotransform.
    crs : CRS of the ground coordinates when the file does not say (.points, layers, rasters, CSV ``x,y``).
    """
    path = os.fspath(path)
    if not os.path.exists(path) and not path.startswith("/vsi"):
        raise GCPError(f"GCP file not found: {path}")
    try:
        return gcp_formats.read_gcps_any(path, dem=dem, layer=layer, crs=crs, image=image, columns=columns,
                                         pixel_convention=pixel_convention, need_height=need_height)
    except GCPError:
        raise
    except Exception as exc:  # pandas/pyogrio raise many types; report one line
        raise GCPError(f"cannot read GCPs from {path}: {str(exc).splitlines()[0]}") from None


def write_gcps(gdf, path, *, layer: str = "gcps", overwrite: bool = False, format: Optional[str] = None,
               image: Optional[str] = None) -> str:
    """Write a GCP table, atomically, as ``.csv``, ``.gpkg``, ``.geojson``, QGIS ``.points`` or ASP ``.gcp``.

    The format follows the extension unless ``format`` says otherwise: ``"csv"``, ``"gpkg"``, ``"geojson"``,
    ``"points"``, ``"asp"`` or ``"orthority"`` (orthority's GCP GeoJSON, which needs ``image``: the image's file
    name). ``sample, line`` are written in each format's own convention (GDAL for ours and QGIS, centre for ASP and
    orthority). Raises :class:`~gdal_gf4cal.errors.InputOverwriteError` if ``path`` exists and ``overwrite`` is
    false.
    """
    path = check_output_path(path, overwrite=overwrite)
    ext = os.path.splitext(path)[1].lower()
    fmt = (format or {".csv": "csv", ".gpkg": "gpkg", ".geojson": "geojson", ".json": "geojson",
                      ".points": "points", ".gcp": "asp"}.get(ext, "")).lower()
    if fmt in ("points", "asp", "orthority"):
        writer = {"points": gcp_formats.write_points_file, "asp": gcp_formats.write_asp_gcp,
                  "orthority": gcp_formats.write_orthority_geojson}[fmt]
        kwargs = {"image": image} if fmt != "points" else {}
        return writer(gdf, path, overwrite=overwrite, **kwargs)
    if fmt not in ("csv", "gpkg", "geojson"):
        raise GCPError(f"cannot write GCPs as {ext or format!r}; use .csv, .gpkg, .geojson, .points, .gcp "
                       "or format='orthority'")
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with atomic_output(path) as tmp:
        if fmt == "csv":
            df = gdf.drop(columns="geometry") if "geometry" in gdf.columns else gdf
            df.to_csv(tmp, index=False)   # shortest repr: floats read back identical
        elif fmt == "gpkg":
            to_geodataframe(gdf).to_file(tmp, layer=layer, driver="GPKG")
        else:
            to_geodataframe(gdf).to_file(tmp, driver="GeoJSON")
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
