"""GCP file formats (ours and other tools'), and role assignment (METHODS §4, §6).

Everything returns the project's one GCP schema (DESIGN.md): a DataFrame (WGS84 degrees) with ``id, lon, lat, h,
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
* orthority's GCP GeoJSON (points ``[lon, lat, h]`` in EPSG:4979, property ``ji`` = ``[column, row]`` with pixel
  centres at integers, ``filename`` = the image): :func:`read_orthority_geojson` / :func:`write_orthority_geojson`.
* ASP ``.gcp`` (``id lat lon height 3 sigmas`` then ``image col row 2 sigmas`` per image, pixel centres at
  integers): :func:`read_asp_gcp` / :func:`write_asp_gcp`.
* OTB tie-point text (``col row lon lat [h]``): :func:`read_otb_points`.
* CSV/text with a header, or header-less with a column map (``columns="id,sample,line,lon,lat,h"``):
  :func:`read_gcp_csv`. QGIS ``.points`` are also written: :func:`write_points_file`.
* Pixel conventions: every reader takes ``pixel_convention="corner"|"center"`` (:func:`pixel_offset`), the
  convention of the file's image coordinates, defaulting to the format's own; tables are always returned in
  GDAL's (corner) convention. Files holding several images (ASP, orthority, observation tables) are read into
  the observation table (:mod:`gdal_gf4cal.observations`) and give one image's view.
* Missing heights are taken from a DEM (:class:`gdal_gf4cal.dem.DEM`, which converts geoid heights to ellipsoidal
  ones when opened with ``geoid=``); without a DEM they are an error that says so.

Role assignment: :func:`assign_roles` (``--check-fraction``, seeded, spread over the image) and
:func:`leave_one_out_splits`.
"""
from __future__ import annotations

import json
import os
import re
from io import StringIO
from typing import Iterator, Optional, Tuple

import geopandas as gpd
import numpy as np
import pandas as pd
import pyproj
from osgeo import gdal

from ._gdal import with_gdal_exceptions
from .atomic import atomic_output
from .errors import GCPError
from .geodesy import crs_transformer
from .observations import (
    _resolve_image,
    fill_heights,
    gcp_view,
    image_ids,
    read_observations,
    validate_gcps,
    validate_observations,
)
from .outputs import check_output_path

__all__ = ["read_gcps_any", "read_points_file", "read_raster_gcps", "read_gcp_layer", "read_gcp_csv",
           "read_orthority_geojson", "read_asp_gcp", "read_otb_points", "write_points_file",
           "write_orthority_geojson", "write_asp_gcp", "pixel_offset", "fill_heights", "assign_roles",
           "leave_one_out_splits"]

_SAMPLE_ALIASES = ("sample", "samp", "col", "column", "pixel", "px", "x_img", "img_x", "image_x", "sourcex")
_LINE_ALIASES = ("line", "row", "ln", "y_img", "img_y", "image_y", "sourcey")
_H_ALIASES = ("h", "height", "hae", "z", "elevation", "elev", "alt", "altitude")
_ID_ALIASES = ("id", "gcp_id", "name", "label", "fid_gcp")
_RASTER_EXT = (".tif", ".tiff", ".vrt", ".ntf", ".nitf", ".img", ".jp2", ".hdf", ".h5", ".xml", ".dim")
_LAYER_EXT = (".gpkg", ".geojson", ".json", ".shp", ".fgb", ".kml", ".gml", ".sqlite")


def _crs(value):
    try:
        return pyproj.CRS.from_user_input(value)
    except Exception as exc:  # pyproj raises CRSError and others
        raise GCPError(f"unknown CRS {str(value)[:60]!r}: {str(exc).splitlines()[0]}") from None


def _to_lonlat(x, y, crs):
    """Map coordinates in ``crs`` -> (lon, lat) WGS84 degrees (always x=east, y=north order)."""
    crs = _crs(crs)
    if crs.is_geographic and crs.equals(pyproj.CRS.from_epsg(4326), ignore_axis_order=True):
        return np.asarray(x, float), np.asarray(y, float)
    tf = crs_transformer(crs, "EPSG:4326")
    lon, lat = tf.transform(np.asarray(x, float), np.asarray(y, float))
    return np.asarray(lon, float), np.asarray(lat, float)


def _finish(df, source, dem, need_height=True):
    return validate_gcps(df, source=source, dem=dem, need_height=need_height)   # fills heights from the DEM


_CORNER = ("corner", "gdal", "area")
_CENTER = ("center", "centre", "rpc", "point")


def pixel_offset(pixel_convention: Optional[str], default: str = "corner") -> float:
    """What to add to a file's image coordinates to get GDAL's: 0 for ``"corner"``, 0.5 for ``"center"``.

    ``"corner"`` (aliases ``"gdal"``, ``"area"``): pixel corners at integers, the centre of the first pixel at
    (0.5, 0.5), GDAL's convention and ours. ``"center"`` (aliases ``"centre"``, ``"rpc"``, ``"point"``): pixel
    centres at integers (orthority, ASP, RPC00B offsets). None takes ``default`` (the format's own).
    """
    conv = str(pixel_convention if pixel_convention is not None else default).strip().lower()
    if conv in _CORNER:
        return 0.0
    if conv in _CENTER:
        return 0.5
    raise GCPError(f"pixel convention must be 'center' or 'corner', not {pixel_convention!r} "
                   "(--gcp-pixel-convention)")


# ----------------------------------------------------------------------------------------------------------------
# QGIS Georeferencer .points
# ----------------------------------------------------------------------------------------------------------------
def read_points_file(path, *, dem=None, crs=None, image: Optional[str] = None, disabled: str = "drop",
                     pixel_convention: Optional[str] = None, need_height: bool = True):
    """Read a QGIS Georeferencer ``.points`` file.

    Parameters
    ----------
    crs : CRS of ``mapX, mapY`` when the file has no ``#CRS:`` line (default: EPSG:4326 if the numbers look like
        degrees, otherwise an error asking for it).
    image : the raster the points were taken on; needed only if it had a geotransform in QGIS.
    disabled : ``"drop"`` (default) or ``"check"``: what to do with rows whose ``enable`` is 0.
    pixel_convention : of ``sourceX, sourceY`` (default ``"corner"``, QGIS's); see :func:`pixel_offset`.
    """
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
    off = pixel_offset(pixel_convention, "corner")
    sample, line = np.asarray(sample, float) + off, np.asarray(line, float) + off
    if disabled not in ("drop", "check"):
        raise GCPError(f"disabled must be 'drop' or 'check', not {disabled!r}")
    role = np.where(enabled, "control", "check")
    keep = enabled | (disabled == "check")
    out = pd.DataFrame({"id": [str(i + 1) for i in range(len(df))], "lon": lon, "lat": lat, "h": np.nan,
                        "sample": sample, "line": line, "role": role})[keep].reset_index(drop=True)
    if len(out) == 0:
        raise GCPError(f"{path}: no enabled GCPs")
    return _finish(out, path, dem, need_height)


@with_gdal_exceptions
def _source_to_pixel(sx, sy, image):
    """QGIS layer coordinates -> GDAL pixel coordinates (via the image's geotransform if it has one)."""
    if image is None:
        return sx, -sy
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
def read_raster_gcps(path, *, dem=None, crs=None, pixel_convention: Optional[str] = None, need_height: bool = True):
    """GCPs embedded in a raster (``GetGCPs``), e.g. a GeoTIFF with tie points or a VRT ``GCPList``.

    ``pixel_convention``: None takes ``GCPPixel/GCPLine`` as GDAL reports them (GDAL's convention; GDAL already
    shifts the tie points of a GeoTIFF declared ``PixelIsPoint``); ``"corner"`` says the same explicitly;
    ``"center"`` says the writer put pixel centres at integers although GDAL cannot know it (adds 0.5).

    ``GCPZ`` is used as the ellipsoidal height unless every GCP has Z = 0 (GDAL's "no height"), in which case the
    heights come from ``dem``.
    """
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
    off = pixel_offset(pixel_convention, "corner")
    df = pd.DataFrame({"id": ids, "lon": lon, "lat": lat, "h": h,
                       "sample": np.array([g.GCPPixel for g in gcps], float) + off,
                       "line": np.array([g.GCPLine for g in gcps], float) + off, "role": "control"})
    return _finish(df, path, dem, need_height)


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
                   line_field: Optional[str] = None, height_field: Optional[str] = None, crs=None,
                   pixel_convention: Optional[str] = None, need_height: bool = True):
    """A point layer (GeoPackage, GeoJSON, Shapefile, ...) in any CRS with image-coordinate fields.

    Ground position: the point geometry reprojected to EPSG:4326 (``crs`` overrides a missing layer CRS); the
    height: ``height_field`` or a field named ``h/height/z/elevation``, else the geometry's Z, else the DEM.
    ``pixel_convention`` of the image fields: default ``"corner"`` (GDAL's), see :func:`pixel_offset`.
    """
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
    off = pixel_offset(pixel_convention, "corner")
    df["sample"] = df["sample"] + off
    df["line"] = df["line"] + off
    return _finish(df, path, dem, need_height)


# ----------------------------------------------------------------------------------------------------------------
# CSV / text tables (with a header, or header-less with a column map), OTB tie points
# ----------------------------------------------------------------------------------------------------------------
_COLUMN_NAMES = {"id": "id", "name": "id", "gcp_id": "id", "sample": "sample", "col": "sample", "column": "sample",
                 "x_img": "sample", "line": "line", "row": "line", "y_img": "line", "lon": "lon", "long": "lon",
                 "longitude": "lon", "lat": "lat", "latitude": "lat", "h": "h", "height": "h", "z": "h",
                 "elevation": "h", "x": "x", "y": "y", "role": "role", "sigma": "sigma"}
_SKIP = ("-", "_", "skip", "")
_NUMBER = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")


def _data_lines(path):
    with open(path, encoding="utf-8-sig", errors="replace") as f:
        return [ln.strip() for ln in f.read().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]


def _split(line):
    sep = "," if "," in line else (";" if ";" in line else None)
    return [t.strip() for t in (line.split(sep) if sep else line.split())], sep


def parse_columns(columns) -> list:
    """A column map (``"id,sample,line,lon,lat,h"`` or a sequence) -> canonical names (``None`` = skip).

    Names: ``id, sample, line, lon, lat, h, role, sigma`` (aliases ``col/row``, ``longitude/latitude``,
    ``height/z/elevation``, ``name``), ``x, y`` for ground coordinates in ``crs``, and ``-`` or ``skip`` for a
    column to ignore.
    """
    names = [c.strip().lower() for c in (columns.split(",") if isinstance(columns, str) else columns)]
    out = []
    for n in names:
        if n in _SKIP:
            out.append(None)
        elif n in _COLUMN_NAMES:
            out.append(_COLUMN_NAMES[n])
        else:
            raise GCPError(f"unknown column {n!r} in the column map (--columns); use id, sample, line, lon, lat, h, "
                           "role, sigma, x, y or - to skip")
    real = [n for n in out if n is not None]
    if len(set(real)) != len(real):
        raise GCPError("a column is named twice in the column map (--columns)")
    ground = {"lon", "lat"} <= set(real) or {"x", "y"} <= set(real)
    if not ({"sample", "line"} <= set(real) and ground):
        raise GCPError("the column map (--columns) must name sample, line and lon, lat (or x, y), e.g. "
                       "id,sample,line,lon,lat,h")
    return out


def _to_float(col):
    """Text -> float with Python's exact parser; anything non-numeric becomes NaN (reported by validation)."""
    try:
        return pd.Series(np.asarray(col, dtype=str).astype(float), index=col.index)
    except ValueError:
        return pd.to_numeric(col, errors="coerce")


def read_gcp_csv(path, *, columns=None, dem=None, crs=None, pixel_convention: Optional[str] = None,
                 need_height: bool = True):
    """A CSV/text GCP table: with a header (our schema, field aliases as for layers), or header-less with
    ``columns``, a column map such as ``"id,sample,line,lon,lat,h"`` (:func:`parse_columns`; separators ``,``,
    ``;`` or blanks; a header line, if any, is skipped). ``x, y`` columns are ground coordinates in ``crs``.
    ``pixel_convention`` of the file's sample/line: default ``"corner"`` (GDAL's), see :func:`pixel_offset`.
    """
    path = os.fspath(path)
    off = pixel_offset(pixel_convention, "corner")
    if columns is None:
        df = pd.read_csv(path, skipinitialspace=True, comment="#", dtype={"id": str},
                         float_precision="round_trip")        # the written floats, bit for bit
        if "sample" not in df.columns or "line" not in df.columns:
            cols = list(df.columns)
            fs, fl = _find(cols, _SAMPLE_ALIASES), _find(cols, _LINE_ALIASES)
            if fs is not None and fl is not None:
                df = df.rename(columns={fs: "sample", fl: "line"})
        if off:
            for c in ("sample", "line"):
                if c in df.columns:
                    df[c] = pd.to_numeric(df[c], errors="coerce") + off
        return _finish(df, path, dem, need_height)
    names = parse_columns(columns)
    lines = _data_lines(path)
    if not lines:
        raise GCPError(f"{path}: no GCPs")
    rows = [_split(ln)[0] for ln in lines]
    numeric = [i for i, n in enumerate(names) if n in ("sample", "line", "lon", "lat", "x", "y")]
    first = rows[0]
    if len(first) >= len(names) and not all(_NUMBER.match(first[i] or "") for i in numeric):
        rows = rows[1:]          # a header line: the map says what the columns are
    widths = {len(r) for r in rows}
    if widths != {len(names)}:
        raise GCPError(f"{path}: rows have {'/'.join(map(str, sorted(widths)))} columns but the column map "
                       f"(--columns) names {len(names)}; name every column (- to skip one)")
    arr = np.array(rows, dtype=object)
    df = pd.DataFrame({n: arr[:, i] for i, n in enumerate(names) if n is not None})
    for c in ("sample", "line", "lon", "lat", "h", "x", "y", "sigma"):
        if c in df.columns:
            df[c] = _to_float(df[c])
    if "x" in df.columns:
        if crs is None:
            raise GCPError(f"{path}: ground coordinates x, y need their CRS (--gcp-crs)")
        df["lon"], df["lat"] = _to_lonlat(df.pop("x").to_numpy(float), df.pop("y").to_numpy(float), crs)
    df["sample"] = df["sample"] + off
    df["line"] = df["line"] + off
    return _finish(df, path, dem, need_height)


def read_otb_points(path, *, dem=None, pixel_convention: Optional[str] = None, need_height: bool = True):
    """An OTB tie-point file (``RefineSensorModel`` / ``GenerateRPCSensorModel`` ``-inpoints``).

    One point per line, blank- or tab-separated: ``col row lon lat`` and optionally a fifth column, the height
    (taken as ellipsoidal metres; without it the heights come from ``dem``); ``#`` lines are comments. OTB gives
    an image without georeferencing its origin at the centre of the first pixel, (0.5, 0.5), so the default
    ``pixel_convention`` is ``"corner"`` (GDAL's); give ``"center"`` for files written with centres at integers.
    """
    path = os.fspath(path)
    rows = [ln.split() for ln in _data_lines(path)]
    if not rows:
        raise GCPError(f"{path}: no tie points")
    widths = {len(r) for r in rows}
    if not widths <= {4, 5} or len(widths) != 1:
        raise GCPError(f"{path}: an OTB tie-point file has 4 or 5 columns (col row lon lat [h]); for other "
                       "layouts give the column map (--columns)")
    try:
        arr = np.array(rows, dtype=float)
    except ValueError:
        raise GCPError(f"{path}: non-numeric value in an OTB tie-point file (col row lon lat [h])") from None
    off = pixel_offset(pixel_convention, "corner")
    df = pd.DataFrame({"id": [str(i + 1) for i in range(len(arr))], "lon": arr[:, 2], "lat": arr[:, 3],
                       "h": arr[:, 4] if arr.shape[1] == 5 else np.nan,
                       "sample": arr[:, 0] + off, "line": arr[:, 1] + off})
    return _finish(df, path, dem, need_height)


# ----------------------------------------------------------------------------------------------------------------
# orthority GCP GeoJSON
# ----------------------------------------------------------------------------------------------------------------
def _is_orthority(path) -> bool:
    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
        feats = doc.get("features") or []
        return bool(feats) and "ji" in (feats[0].get("properties") or {})
    except Exception:   # not JSON, not a FeatureCollection: not orthority's format
        return False


def read_orthority_geojson(path, *, pixel_convention: Optional[str] = None):
    """orthority's GCP GeoJSON -> an observation table (one row per feature).

    Each feature is a GCP: geometry = ``[lon, lat, h]`` in WGS84 3-D geographic coordinates (EPSG:4979, so ``h``
    is ellipsoidal), property ``ji`` = the image ``[column, row]`` with the origin at the centre of the top-left
    pixel (default ``pixel_convention="center"``: GDAL's = ji + 0.5), ``filename`` = the image's file name
    (becomes ``image_id``), optional ``id`` and ``info``. Other properties become columns.
    """

    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
    except (OSError, ValueError) as exc:
        raise GCPError(f"cannot read {path}: {str(exc).splitlines()[0]}") from None
    feats = doc.get("features") if isinstance(doc, dict) else None
    if not feats:
        raise GCPError(f"{path}: no GCP features (orthority GCP GeoJSON is a FeatureCollection of points)")
    off = pixel_offset(pixel_convention, "center")
    recs = []
    for k, ft in enumerate(feats):   # parsing JSON records, not a numeric hot path
        props = dict(ft.get("properties") or {})
        geom = ft.get("geometry") or {}
        coords = list(geom.get("coordinates") or [])
        ji = props.pop("ji", None)
        if geom.get("type") != "Point" or len(coords) < 2 or not isinstance(ji, (list, tuple)) or len(ji) != 2:
            raise GCPError(f"{path}: feature {k + 1} is not an orthority GCP (a Point with a 'ji' property)")
        rec = {"point_id": str(props.pop("id", k + 1)), "image_id": str(props.pop("filename", "") or "unnamed"),
               "sample": float(ji[0]) + off, "line": float(ji[1]) + off, "lon": float(coords[0]),
               "lat": float(coords[1]), "h": float(coords[2]) if len(coords) > 2 else np.nan}
        rec.update({k2: v for k2, v in props.items() if k2 not in rec})
        recs.append(rec)
    return validate_observations(pd.DataFrame(recs), source=path, need_height=False)


def write_orthority_geojson(gcps, path, *, image: Optional[str] = None, overwrite: bool = False) -> str:
    """Write a GCP table as orthority's GCP GeoJSON (``ji`` = GDAL sample/line - 0.5, ``filename`` = ``image``'s
    file name; ``role``, ``sigma`` and ``info`` as extra properties). Heights are required (3-D points)."""
    g = validate_gcps(gcps, need_height=True, source="GCPs for orthority")
    name = _image_name(image, gcps, "orthority GeoJSON")
    feats = [{"type": "Feature",
              "properties": {"filename": name, "ji": [s - 0.5, ln - 0.5], "id": i, "info": str(i), "role": r,
                             "sigma": sg},
              "geometry": {"type": "Point", "coordinates": [x, y, z]}}
             for i, s, ln, x, y, z, r, sg in zip(g["id"], g["sample"].astype(float), g["line"].astype(float),
                                                 g["lon"].astype(float), g["lat"].astype(float),
                                                 g["h"].astype(float), g["role"], g["sigma"].astype(float))]
    text = json.dumps({"type": "FeatureCollection", "features": feats}, indent=1)   # repr floats: exact
    return _write_text(path, text, overwrite)


def _image_name(image, gcps, what):
    if image is None and "image_id" in getattr(gcps, "columns", ()):
        ids = list(dict.fromkeys(gcps["image_id"].astype(str)))
        image = ids[0] if len(ids) == 1 else None
    if image is None:
        raise GCPError(f"{what} names the image the GCPs are in: give it (image=...)")
    return os.path.basename(str(image))


def _write_text(path, text, overwrite):
    path = check_output_path(path, overwrite=overwrite)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with atomic_output(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
    return path


# ----------------------------------------------------------------------------------------------------------------
# ASP (Ames Stereo Pipeline) .gcp
# ----------------------------------------------------------------------------------------------------------------
_ASP_ID = re.compile(r"^#\s*gdal_gf4cal id\s+(\S+)\s+(.+?)\s*$")


def read_asp_gcp(path, *, pixel_convention: Optional[str] = None):
    """An ASP ``.gcp`` file -> an observation table (one row per GCP and image it is seen in).

    Each line: ``id lat lon height sigma_lat sigma_lon sigma_h`` then, per image, ``image col row sigma_col
    sigma_row`` (blanks or commas; ``#`` lines are comments). Heights are above the WGS84 ellipsoid; ground sigmas
    (m) become ``sigma_lat_m, sigma_lon_m, sigma_h_m`` and the image sigmas ``sigma`` (the mean of the two). ASP
    puts pixel centres at integers: default ``pixel_convention="center"`` (GDAL's = col/row + 0.5).
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise GCPError(f"GCP file not found: {path}")
    with open(path, encoding="utf-8-sig", errors="replace") as f:
        raw = f.read().splitlines()
    ids = {m.group(1): m.group(2) for m in map(_ASP_ID.match, raw) if m}
    off = pixel_offset(pixel_convention, "center")
    recs = []
    for n, ln in enumerate(raw):   # one text line per GCP: parsing, not a numeric hot path
        s = ln.strip()
        if not s or s.startswith("#"):
            continue
        tok = [t for t in re.split(r"[,\s]+", s) if t]
        if len(tok) < 12 or (len(tok) - 7) % 5:
            raise GCPError(f"{path}: line {n + 1} is not an ASP GCP (id lat lon height 3 sigmas, then image col "
                           "row 2 sigmas per image)")
        try:
            lat, lon, h, slat, slon, sh = map(float, tok[1:7])
            for j in range(7, len(tok), 5):
                recs.append({"point_id": ids.get(tok[0], tok[0]), "image_id": tok[j],
                             "sample": float(tok[j + 1]) + off, "line": float(tok[j + 2]) + off,
                             "sigma": 0.5 * (float(tok[j + 3]) + float(tok[j + 4])), "lon": lon, "lat": lat,
                             "h": h, "sigma_lat_m": slat, "sigma_lon_m": slon, "sigma_h_m": sh})
        except ValueError:
            raise GCPError(f"{path}: line {n + 1} has a non-numeric coordinate or sigma") from None
    if not recs:
        raise GCPError(f"{path}: no GCPs")
    return validate_observations(pd.DataFrame(recs), source=path, need_height=False)


def write_asp_gcp(gcps, path, *, image: Optional[str] = None, overwrite: bool = False) -> str:
    """Write a GCP table (one image, ``image`` = its file name) or an observation table (every image) as an ASP
    ``.gcp`` file: col/row = GDAL sample/line - 0.5, heights above the WGS84 ellipsoid (required).

    ASP wants integer ids: other ids are written as 1..n and recorded in ``# gdal_gf4cal id`` comments, which
    :func:`read_asp_gcp` reads back. Ground sigmas come from ``sigma_lat_m, sigma_lon_m, sigma_h_m`` (else 1 m).
    """
    if "point_id" in gcps.columns:
        t = validate_observations(gcps, need_height=True, source="observations for ASP")
        t = t[t["kind"] == "gcp"]
    else:
        g = validate_gcps(gcps, need_height=True, source="GCPs for ASP")
        t = pd.DataFrame(g).rename(columns={"id": "point_id"})
        t["image_id"] = _image_name(image, gcps, "an ASP .gcp file")
    pids = list(dict.fromkeys(t["point_id"].astype(str)))
    numeric = all(re.fullmatch(r"\d+", p) for p in pids)
    asp_id = {p: (p if numeric else str(k + 1)) for k, p in enumerate(pids)}
    head = ["# ASP ground control points (gdal_gf4cal): id lat lon height sigma_lat sigma_lon sigma_h, then per "
            "image: image col row sigma_col sigma_row; pixel centres at integers; heights above WGS84"]
    if not numeric:
        head += [f"# gdal_gf4cal id {asp_id[p]} {p}" for p in pids]
    sig = {c: (t[c].astype(float).to_numpy() if c in t.columns else np.ones(len(t)))
           for c in ("sigma_lat_m", "sigma_lon_m", "sigma_h_m")}
    t = t.assign(_slat=sig["sigma_lat_m"], _slon=sig["sigma_lon_m"], _sh=sig["sigma_h_m"])
    body = []
    for pid, grp in t.groupby("point_id", sort=False):   # one text line per ground point
        r0 = grp.iloc[0]
        obs = " ".join(f"{im} {s - 0.5!r} {ln - 0.5!r} {sg!r} {sg!r}" for im, s, ln, sg in
                       zip(grp["image_id"], grp["sample"].astype(float), grp["line"].astype(float),
                           grp["sigma"].astype(float)))
        body.append(f"{asp_id[str(pid)]} {float(r0['lat'])!r} {float(r0['lon'])!r} {float(r0['h'])!r} "
                    f"{float(r0['_slat'])!r} {float(r0['_slon'])!r} {float(r0['_sh'])!r} {obs}")
    return _write_text(path, "\n".join(head + body) + "\n", overwrite)


# ----------------------------------------------------------------------------------------------------------------
# QGIS .points writer
# ----------------------------------------------------------------------------------------------------------------
def write_points_file(gcps, path, *, overwrite: bool = False) -> str:
    """Write a GCP table as a QGIS Georeferencer ``.points`` file (EPSG:4326 map coordinates, ``#CRS:`` line).

    ``sourceX = sample``, ``sourceY = -line`` (an image without geotransform in QGIS); check points are written
    disabled (``enable = 0``: read them back with ``disabled="check"``). The format has no height: reading it
    back takes heights from a DEM.
    """
    g = validate_gcps(gcps, need_height=False, source="GCPs for .points")
    wkt = pyproj.CRS.from_epsg(4326).to_wkt()
    rows = [f"{x!r},{y!r},{s!r},{-ln!r},{1 if r == 'control' else 0},0,0,0"
            for x, y, s, ln, r in zip(g["lon"].astype(float), g["lat"].astype(float), g["sample"].astype(float),
                                      g["line"].astype(float), g["role"])]
    text = f"#CRS: {wkt}\nmapX,mapY,sourceX,sourceY,enable,dX,dY,residual\n" + "\n".join(rows) + "\n"
    return _write_text(path, text, overwrite)


# ----------------------------------------------------------------------------------------------------------------
# dispatch
# ----------------------------------------------------------------------------------------------------------------
def read_gcps_any(path, dem=None, *, layer: Optional[str] = None, crs=None, image: Optional[str] = None,
                  columns=None, pixel_convention: Optional[str] = None, need_height: bool = True):
    """Read GCPs from any supported source, chosen by extension and content; returns the GCP table (GDAL pixel
    convention, heights from ``dem`` where the file has none).

    ``.points`` (or a CSV starting with ``#CRS``/``mapX``) -> :func:`read_points_file`; ``.gcp`` ->
    :func:`read_asp_gcp`; GeoJSON with ``ji`` properties -> :func:`read_orthority_geojson`; other vector layers
    -> :func:`read_gcp_layer`; ``.csv``/``.txt`` -> :func:`read_gcp_csv` (``columns`` for header-less files; an
    observation table with ``point_id, image`` columns gives ``image``'s view) or, for 4/5 numeric blank-separated
    columns, :func:`read_otb_points`; anything GDAL opens as a raster with GCPs -> :func:`read_raster_gcps`.
    Multi-image files (ASP, orthority, observation tables) need ``image`` unless they hold one image.
    """
    path = os.fspath(path)
    if not os.path.exists(path) and not path.startswith("/vsi"):
        raise GCPError(f"GCP file not found: {path}")
    low = path.lower()
    kw = {"pixel_convention": pixel_convention}
    if columns is not None and not low.endswith(".points"):    # a column map says: a delimited text table
        return read_gcp_csv(path, columns=columns, dem=dem, crs=crs, need_height=need_height, **kw)
    if low.endswith(".points"):
        return read_points_file(path, dem=dem, crs=crs, image=image, need_height=need_height, **kw)
    if low.endswith(".gcp"):
        return _view(read_asp_gcp(path, **kw), image, path, dem, need_height)
    if low.endswith((".geojson", ".json")) and _is_orthority(path):
        return _view(read_orthority_geojson(path, **kw), image, path, dem, need_height)
    if low.endswith(".csv") or (low.endswith(".txt") and not low.endswith("_rpc.txt")):
        lines = _data_lines(path)
        with open(path, encoding="utf-8-sig", errors="replace") as f:
            head = f.readline()
        if head.lower().startswith("#crs") or (lines and lines[0].lower().startswith("mapx")):
            return read_points_file(path, dem=dem, crs=crs, image=image, need_height=need_height, **kw)
        first = _split(lines[0])[0] if lines else []
        n_numeric = sum(bool(_NUMBER.match(t)) for t in first)
        if n_numeric >= 2:                       # data on the first line: no header
            if _split(lines[0])[1] is None and len(first) in (4, 5) and n_numeric == len(first):
                return read_otb_points(path, dem=dem, need_height=need_height, **kw)
            raise GCPError(f"{path}: the file has no header; give its column map (--columns), "
                           "e.g. id,sample,line,lon,lat,h")
        header = {t.lower() for t in first}
        if "point_id" in header and header & {"image", "image_id"}:
            table = read_observations(path, need_height=False)
            if pixel_offset(pixel_convention, "corner"):
                table = table.assign(sample=table["sample"] + 0.5, line=table["line"] + 0.5)
            return _view(table, image, path, dem, need_height)
        return read_gcp_csv(path, dem=dem, crs=crs, need_height=need_height, **kw)
    if low.endswith(_LAYER_EXT):
        return read_gcp_layer(path, layer=layer, dem=dem, crs=crs, need_height=need_height, **kw)
    try:
        return read_raster_gcps(path, dem=dem, crs=crs, need_height=need_height, **kw)
    except GCPError:
        raise
    except Exception:
        raise GCPError(f"{path}: unsupported GCP source; use CSV, GeoPackage/GeoJSON, QGIS .points, ASP .gcp, "
                       "orthority GeoJSON, OTB tie points or a raster with embedded GCPs") from None


def _view(table, image, path, dem, need_height):
    """One image's GCP table from an observation table read from ``path``.

    A file of one image is that image's, whatever ``image`` is called (a VRT or a renamed copy of the scene);
    in a file of several, ``image`` picks by name.
    """
    ids = image_ids(table)
    image_id = ids[0] if len(ids) == 1 else _resolve_image(table, image, path)
    return _finish(gcp_view(table, image_id), path, dem, need_height)


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
