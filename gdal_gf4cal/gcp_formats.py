"""More GCP sources than :mod:`gdal_gf4cal.gcp` reads, and role assignment (METHODS §4, §6).

Everything returns the project's one GCP schema (DESIGN.md): a GeoDataFrame in EPSG:4326 with ``id, lon, lat, h,
sample, line, role, sigma`` (image coordinates in GDAL's convention, centre of the first pixel at 0.5).

* QGIS Georeferencer ``.points`` files (``mapX,mapY,sourceX,sourceY,enable,...``, optional ``#CRS: WKT`` line):
  ``sourceX, sourceY`` are the pixel position from the image's top-left *corner* with y negative downwards (QGIS
  shows an ungeoreferenced raster with the geotransform ``(0, 1, 0, 0, 0, -1)``), so ``sample = sourceX`` and
  ``line = -sourceY``. If the image had a geotransform, pass ``image=`` and the source coordinates are mapped back
  to pixels through it.
* GCPs embedded in a raster (``GetGCPs``: GeoTIFF tie points, VRT ``GCPList``, NITF, ...): ``GCPPixel/GCPLine``
  are already GDAL pixel coordinates; the GCP CRS comes from ``GetGCPSpatialRef``.
* GeoPackage / GeoJSON / Shapefile point layers in any CRS with ``sample``/``line`` fields (field names are
  matched case-insensitively, with common aliases ``col/row``, ``pixel/line``, ``x_img/y_img``); the height comes
  from a ``h``/``height``/``z``/``elevation`` field or the geometry's Z.
* Missing heights are taken from a DEM (:class:`gdal_gf4cal.dem.DEM`, which converts geoid heights to ellipsoidal
  ones when opened with ``geoid=``); without a DEM they are an error that says so.

Role assignment: :func:`assign_roles` (``--check-fraction``, seeded, spread over the image) and
:func:`leave_one_out_splits`.
"""
from __future__ import annotations

import os
import re
from typing import Iterator, Optional, Tuple

import numpy as np

from .errors import GCPError
from ._gdal import with_gdal_exceptions

__all__ = ["read_gcps_any", "read_points_file", "read_raster_gcps", "read_gcp_layer", "fill_heights",
           "assign_roles", "leave_one_out_splits"]

_SAMPLE_ALIASES = ("sample", "samp", "col", "column", "pixel", "px", "x_img", "img_x", "image_x", "sourcex")
_LINE_ALIASES = ("line", "row", "ln", "y_img", "img_y", "image_y", "sourcey")
_H_ALIASES = ("h", "height", "hae", "z", "elevation", "elev", "alt", "altitude")
_ID_ALIASES = ("id", "gcp_id", "name", "label", "fid_gcp")
_RASTER_EXT = (".tif", ".tiff", ".vrt", ".ntf", ".nitf", ".img", ".jp2", ".hdf", ".h5", ".xml", ".dim")
_LAYER_EXT = (".gpkg", ".geojson", ".json", ".shp", ".fgb", ".kml", ".gml", ".sqlite")


def _crs(value):
    import pyproj
    try:
        return pyproj.CRS.from_user_input(value)
    except Exception as exc:  # pyproj raises CRSError and others
        raise GCPError(f"unknown CRS {str(value)[:60]!r}: {str(exc).splitlines()[0]}") from None


def _to_lonlat(x, y, crs):
    """Map coordinates in ``crs`` -> (lon, lat) WGS84 degrees (always x=east, y=north order)."""
    import pyproj
    crs = _crs(crs)
    if crs.is_geographic and crs.equals(pyproj.CRS.from_epsg(4326), ignore_axis_order=True):
        return np.asarray(x, float), np.asarray(y, float)
    tf = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    lon, lat = tf.transform(np.asarray(x, float), np.asarray(y, float))
    return np.asarray(lon, float), np.asarray(lat, float)


def _finish(df, source, dem, need_height=True):
    from .gcp import validate_gcps
    return validate_gcps(df, source=source, dem=dem, need_height=need_height)   # fills heights from the DEM


def fill_heights(gcps, dem, *, source: str = "GCPs"):
    """Take missing (NaN / absent) heights from ``dem`` (ellipsoidal; geoid-aware through the DEM).

    Raises :class:`GCPError` if the DEM has no value under a GCP that needs one.
    """
    df = gcps.copy()
    if "h" not in df.columns:
        df["h"] = np.nan
    h = np.asarray(df["h"], dtype=float)
    miss = ~np.isfinite(h)
    if miss.any():
        if dem is None:
            raise GCPError(f"{source}: {int(miss.sum())} GCP(s) without height; give a DEM (--dem) to take them from")
        try:
            fill = np.asarray(dem.height(np.asarray(df["lon"], float)[miss], np.asarray(df["lat"], float)[miss]),
                              dtype=float)
        except GCPError:
            raise
        except Exception as exc:  # DEMError and friends: keep one line
            raise GCPError(f"{source}: cannot take GCP heights from the DEM: {str(exc).splitlines()[0]}") from None
        if not np.all(np.isfinite(fill)):
            raise GCPError(f"{source}: the DEM has no height under {int((~np.isfinite(fill)).sum())} GCP(s); "
                           "give their heights or a DEM that covers them")
        h = h.copy()
        h[miss] = fill
        df["h"] = h
    return df


# ----------------------------------------------------------------------------------------------------------------
# QGIS Georeferencer .points
# ----------------------------------------------------------------------------------------------------------------
def read_points_file(path, *, dem=None, crs=None, image: Optional[str] = None, disabled: str = "drop"):
    """Read a QGIS Georeferencer ``.points`` file.

    Parameters
    ----------
    crs : CRS of ``mapX, mapY`` when the file has no ``#CRS:`` line (default: EPSG:4326 if the numbers look like
        degrees, otherwise an error asking for it).
    image : the raster the points were taken on; needed only if it had a geotransform in QGIS.
    disabled : ``"drop"`` (default) or ``"check"``: what to do with rows whose ``enable`` is 0.
    """
    import pandas as pd
    path = os.fspath(path)
    if not os.path.exists(path):
        raise GCPError(f"GCP file not found: {path}")
    with open(path, encoding="utf-8-sig") as f:
        lines = f.read().splitlines()
    file_crs = None
    body = []
    for ln in lines:
        s = ln.strip()
        if not s:
            continue
        if s.startswith("#"):
            m = re.match(r"#\s*CRS\s*:\s*(.*)$", s, flags=re.I)
            if m and m.group(1).strip():
                file_crs = m.group(1).strip()
            continue
        body.append(s)
    if not body or not body[0].lower().startswith("mapx"):
        raise GCPError(f"{path}: not a QGIS .points file (expected a 'mapX,mapY,sourceX,sourceY,...' header)")
    from io import StringIO
    df = pd.read_csv(StringIO("\n".join(body)))
    df.columns = [c.strip().lower() for c in df.columns]
    src_x = "sourcex" if "sourcex" in df.columns else "pixelx"
    src_y = "sourcey" if "sourcey" in df.columns else "pixely"
    for c in ("mapx", "mapy", src_x, src_y):
        if c not in df.columns:
            raise GCPError(f"{path}: column {c!r} missing from the .points header")
    enabled = (pd.to_numeric(df["enable"], errors="coerce").fillna(1).to_numpy() != 0) if "enable" in df.columns \
        else np.ones(len(df), bool)
    mx, my = df["mapx"].to_numpy(float), df["mapy"].to_numpy(float)
    sx, sy = df[src_x].to_numpy(float), df[src_y].to_numpy(float)
    use_crs = crs if crs is not None else file_crs
    if use_crs is None or str(use_crs).strip().upper() in ("", "LOCAL"):
        if crs is None and np.all(np.abs(mx) <= 360) and np.all(np.abs(my) <= 90):
            use_crs = "EPSG:4326"
        else:
            raise GCPError(f"{path}: the map coordinates' CRS is unknown (no '#CRS:' line); give it (--gcp-crs)")
    lon, lat = _to_lonlat(mx, my, use_crs)
    sample, line = _source_to_pixel(sx, sy, image)
    if disabled not in ("drop", "check"):
        raise GCPError(f"disabled must be 'drop' or 'check', not {disabled!r}")
    role = np.where(enabled, "control", "check")
    keep = enabled | (disabled == "check")
    out = pd.DataFrame({"id": [str(i + 1) for i in range(len(df))], "lon": lon, "lat": lat, "h": np.nan,
                        "sample": sample, "line": line, "role": role})[keep].reset_index(drop=True)
    if len(out) == 0:
        raise GCPError(f"{path}: no enabled GCPs")
    return _finish(out, path, dem)


@with_gdal_exceptions
def _source_to_pixel(sx, sy, image):
    """QGIS layer coordinates -> GDAL pixel coordinates (via the image's geotransform if it has one)."""
    if image is None:
        return sx, -sy
    from osgeo import gdal
    try:
        ds = gdal.Open(str(image))
    except RuntimeError as exc:
        raise GCPError(f"cannot open the image the .points were taken on ({image}): "
                       f"{str(exc).splitlines()[0]}; give the raster GDAL opens") from None
    gt = ds.GetGeoTransform(can_return_null=True)
    if gt is None:
        return sx, -sy
    inv = gdal.InvGeoTransform(gt)
    return (inv[0] + inv[1] * sx + inv[2] * sy, inv[3] + inv[4] * sx + inv[5] * sy)


# ----------------------------------------------------------------------------------------------------------------
# raster GCPs
# ----------------------------------------------------------------------------------------------------------------
@with_gdal_exceptions
def read_raster_gcps(path, *, dem=None, crs=None):
    """GCPs embedded in a raster (``GetGCPs``), e.g. a GeoTIFF with tie points or a VRT ``GCPList``.

    ``GCPZ`` is used as the ellipsoidal height unless every GCP has Z = 0 (GDAL's "no height"), in which case the
    heights come from ``dem``.
    """
    import pandas as pd
    from osgeo import gdal
    path = os.fspath(path)
    try:
        ds = gdal.Open(path)
    except RuntimeError as exc:
        raise GCPError(f"cannot open {path}: {str(exc).splitlines()[0]}") from None
    gcps = ds.GetGCPs() or []
    if not gcps:
        raise GCPError(f"{path} has no embedded GCPs; give a GCP table (CSV, GeoPackage, .points)")
    srs = ds.GetGCPSpatialRef()
    use_crs = crs if crs is not None else (srs.ExportToWkt() if srs is not None else None)
    x = np.array([g.GCPX for g in gcps], float)
    y = np.array([g.GCPY for g in gcps], float)
    z = np.array([g.GCPZ for g in gcps], float)
    if use_crs is None:
        if np.all(np.abs(x) <= 360) and np.all(np.abs(y) <= 90):
            use_crs = "EPSG:4326"
        else:
            raise GCPError(f"{path}: its GCPs have no CRS; give it (--gcp-crs)")
    lon, lat = _to_lonlat(x, y, use_crs)
    h = z if np.any(z != 0) else np.full(len(gcps), np.nan)
    ids = [str(g.Id) if str(g.Id).strip() else str(i + 1) for i, g in enumerate(gcps)]
    if len(set(ids)) != len(ids):
        ids = [str(i + 1) for i in range(len(gcps))]
    df = pd.DataFrame({"id": ids, "lon": lon, "lat": lat, "h": h,
                       "sample": [g.GCPPixel for g in gcps], "line": [g.GCPLine for g in gcps], "role": "control"})
    return _finish(df, path, dem)


# ----------------------------------------------------------------------------------------------------------------
# vector layers in any CRS
# ----------------------------------------------------------------------------------------------------------------
def _find(cols, aliases):
    low = {str(c).lower(): c for c in cols}
    for a in aliases:
        if a in low:
            return low[a]
    return None


def read_gcp_layer(path, *, layer: Optional[str] = None, dem=None, sample_field: Optional[str] = None,
                   line_field: Optional[str] = None, height_field: Optional[str] = None, crs=None):
    """A point layer (GeoPackage, GeoJSON, Shapefile, ...) in any CRS with image-coordinate fields.

    Ground position: the point geometry reprojected to EPSG:4326 (``crs`` overrides a missing layer CRS); the
    height: ``height_field`` or a field named ``h/height/z/elevation``, else the geometry's Z, else the DEM.
    """
    import geopandas as gpd
    import pandas as pd
    path = os.fspath(path)
    try:
        gdf = gpd.read_file(path, layer=layer) if layer else gpd.read_file(path)
    except Exception as exc:  # fiona/pyogrio errors vary
        raise GCPError(f"cannot read GCP layer {path}: {str(exc).splitlines()[0]}") from None
    if len(gdf) == 0:
        raise GCPError(f"{path}: the layer has no features")
    cols = [c for c in gdf.columns if c != "geometry"]
    fs = sample_field or _find(cols, _SAMPLE_ALIASES)
    fl = line_field or _find(cols, _LINE_ALIASES)
    if fs is None or fl is None or fs not in gdf.columns or fl not in gdf.columns:
        raise GCPError(f"{path}: the layer needs image-coordinate fields 'sample' and 'line' (found: "
                       f"{', '.join(map(str, cols))})")
    geom = gdf.geometry
    if geom is None or geom.isna().any() or not (geom.geom_type == "Point").all():
        raise GCPError(f"{path}: every feature must be a point (the GCP's ground position)")
    src_crs = gdf.crs if gdf.crs is not None else crs
    if src_crs is None:
        if np.all(np.abs(geom.x) <= 360) and np.all(np.abs(geom.y) <= 90):
            src_crs = "EPSG:4326"
        else:
            raise GCPError(f"{path}: the layer has no CRS; give it (--gcp-crs)")
    lon, lat = _to_lonlat(geom.x.to_numpy(), geom.y.to_numpy(), src_crs)
    fh = height_field or _find(cols, _H_ALIASES)
    if fh is not None:
        h = pd.to_numeric(gdf[fh], errors="coerce").to_numpy(float)
    elif geom.has_z.all():
        h = geom.z.to_numpy(float)
    else:
        h = np.full(len(gdf), np.nan)
    fid = _find(cols, _ID_ALIASES)
    df = pd.DataFrame({"id": gdf[fid].astype(str).to_numpy() if fid else [str(i + 1) for i in range(len(gdf))],
                       "lon": lon, "lat": lat, "h": h,
                       "sample": pd.to_numeric(gdf[fs], errors="coerce").to_numpy(float),
                       "line": pd.to_numeric(gdf[fl], errors="coerce").to_numpy(float)})
    for extra in ("role", "sigma"):
        f = _find(cols, (extra,))
        if f is not None:
            df[extra] = gdf[f].to_numpy()
    # Every other field (truth, quality, flags) is carried through, as the CSV reader does.
    used = {fs, fl, fh, fid} | {_find(cols, (e,)) for e in ("role", "sigma")} | {"lon", "lat"}
    for c in cols:
        if c not in used and c not in df.columns:
            df[c] = gdf[c].to_numpy()
    return _finish(df, path, dem)


# ----------------------------------------------------------------------------------------------------------------
# dispatch
# ----------------------------------------------------------------------------------------------------------------
def read_gcps_any(path, dem=None, *, layer: Optional[str] = None, crs=None, image: Optional[str] = None):
    """Read GCPs from any supported source, chosen by extension and content.

    ``.csv``/``.txt`` -> :func:`gdal_gf4cal.gcp.read_gcps`; ``.points`` -> :func:`read_points_file`; vector layers
    -> :func:`read_gcp_layer`; anything GDAL opens as a raster with GCPs -> :func:`read_raster_gcps`.
    """
    path = os.fspath(path)
    if not os.path.exists(path) and not path.startswith("/vsi"):
        raise GCPError(f"GCP file not found: {path}")
    low = path.lower()
    if low.endswith(".points"):
        return read_points_file(path, dem=dem, crs=crs, image=image)
    if low.endswith(".csv") or (low.endswith(".txt") and not low.endswith("_rpc.txt")):
        with open(path, encoding="utf-8-sig", errors="replace") as f:
            head = f.readline()
        if head.lower().startswith("#crs") or head.lower().startswith("mapx"):
            return read_points_file(path, dem=dem, crs=crs, image=image)
        from .gcp import read_gcps
        return read_gcps(path, dem=dem)
    if low.endswith(_LAYER_EXT):
        return read_gcp_layer(path, layer=layer, dem=dem, crs=crs)
    try:
        return read_raster_gcps(path, dem=dem, crs=crs)
    except GCPError:
        raise
    except Exception:
        raise GCPError(f"{path}: unsupported GCP source; use CSV, GeoPackage/GeoJSON, QGIS .points or a raster "
                       "with embedded GCPs") from None


# ----------------------------------------------------------------------------------------------------------------
# roles
# ----------------------------------------------------------------------------------------------------------------
def assign_roles(gcps, check_fraction: Optional[float] = None, *, seed: int = 0, min_control: int = 1,
                 spread: bool = True):
    """Assign ``role`` = control/check (METHODS §6: always split control from check).

    With ``check_fraction`` None the table's roles are kept (all control if it has none). Otherwise
    ``round(check_fraction * n)`` points become check points, chosen with a seeded generator; with ``spread`` the
    choice is stratified over the image (points sorted along a space-filling order and one check point drawn per
    stratum) so that neither role clusters in one corner. At least ``min_control`` points stay control.
    """
    out = gcps.copy()
    n = len(out)
    if check_fraction is None:
        if "role" not in out.columns:
            out["role"] = "control"
        return out
    f = float(check_fraction)
    if not 0.0 <= f < 1.0:
        raise GCPError(f"--check-fraction must be in [0, 1), got {check_fraction}")
    n_check = min(int(round(f * n)), max(n - int(min_control), 0))
    roles = np.array(["control"] * n, dtype=object)
    if n_check > 0:
        rng = np.random.default_rng(seed)
        if spread and n_check < n:
            s = np.asarray(out["sample"], float)
            l_ = np.asarray(out["line"], float)
            order = np.argsort(_hilbert_key(s, l_), kind="stable")
            edges = np.linspace(0, n, n_check + 1)
            picks = [order[int(np.floor(a)) + rng.integers(0, max(int(np.floor(b)) - int(np.floor(a)), 1))]
                     for a, b in zip(edges[:-1], edges[1:])]
            idx = np.unique(np.asarray(picks, dtype=int))
        else:
            idx = rng.choice(n, size=n_check, replace=False)
        roles[idx] = "check"
    out["role"] = roles
    return out


def _hilbert_key(x, y, order: int = 10):
    """Hilbert-curve index of points scaled into a 2^order grid (keeps spatial neighbours together)."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    side = 2 ** order

    def scale(a):
        lo, hi = np.nanmin(a), np.nanmax(a)
        return np.zeros(a.shape, np.int64) if hi <= lo else np.clip(((a - lo) / (hi - lo) * (side - 1)).astype(
            np.int64), 0, side - 1)

    xi, yi = scale(x), scale(y)
    d = np.zeros(x.shape, np.int64)
    s = side // 2
    while s > 0:
        rx = ((xi & s) > 0).astype(np.int64)
        ry = ((yi & s) > 0).astype(np.int64)
        d += s * s * ((3 * rx) ^ ry)
        # rotate the quadrant
        flip = ry == 0
        swap_x = np.where(flip & (rx == 1), side - 1 - xi, xi)
        swap_y = np.where(flip & (rx == 1), side - 1 - yi, yi)
        xi, yi = np.where(flip, swap_y, swap_x), np.where(flip, swap_x, swap_y)
        s //= 2
    return d


def leave_one_out_splits(gcps) -> Iterator[Tuple[str, object]]:
    """Yield ``(id, table)`` with that GCP as the only check point and every other control point as control.

    Only the table's control points take turns; its check points stay check. For linear compensation models
    :func:`gdal_gf4cal.compensation.fit_compensation` (``leave_one_out=True``) gives the same residuals in one fit.
    """
    roles = np.asarray(gcps["role"] if "role" in gcps.columns else ["control"] * len(gcps), dtype=object)
    ids = np.asarray(gcps["id"]).astype(str)
    for i in np.flatnonzero(roles == "control"):
        t = gcps.copy()
        r = roles.copy()
        r[i] = "check"
        t["role"] = r
        yield ids[i], t
