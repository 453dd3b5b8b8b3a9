"""The residual GeoPackage (GCP points, residual arrows, footprint, default styles); OGR return codes checked.

Layers of :func:`write_residuals_gpkg` (the styles are the layers' defaults in ``layer_styles``, QML and SLD):

``gcps``
    One point per GCP at its ground position, fields ``id, lon, lat, h, sample, line, role, sigma,
    res_sample_before, res_line_before, res_px_before, res_sample_after, res_line_after, res_px_after, outlier``
    and every other column of the table (quality measures, truth, normalised residuals...). Residuals in px,
    ``res_px`` = planar magnitude ``hypot(res_sample, res_line)``. Drawn by role (control: blue triangle, check:
    green circle) with outliers as red crosses.
``residual_vectors``
    One line per GCP from its ground position in the residual direction (sample -> east, line -> south), length =
    residual x ground pixel size x exaggeration; the *after* residuals when given, else the *before*. Fields
    ``id, role, epoch, res_sample, res_line, res_px, outlier, clipped, exaggeration, map_units_per_px``; the factor
    is also in the layer description and metadata (``EXAGGERATION``). Drawn as arrows coloured by ``res_px``
    (graduated, 6 classes from 0 to the largest non-outlier residual; larger ones fall in the last, open class).
``residual_vectors_before``
    Same for the *before* residuals, only when both are given, with the SAME factor (the gain of the refinement
    shows as shorter arrows).
``footprint``
    The scene footprint polygon, when given.

Writing: OGR creates every layer, field, metadata item and style in one transaction; the rows go in through OGR
features in that same transaction up to :data:`OGR_MAX_ROWS` rows in all, and through the bulk writer of
:mod:`.gpkg_bulk` above (one seam, :func:`writes_in_bulk`: plain OGR took 3.9 s for 200k points, the bulk writer
0.3 s). A new file is written to a temporary in its folder and renamed (nothing kept on failure or cancel).
"""
from __future__ import annotations

import datetime as _dt
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Sequence, Tuple

import numpy as np
import pandas as pd
import shapely.ops
from osgeo import ogr, osr
from shapely.geometry import Polygon
from shapely.geometry.base import BaseGeometry

from .._gdal import open_vector, with_quiet_errors
from ..errors import CancelledError, GCPError, Gf4calError
from ..outputs import check_output_path
from ._common import (
    STANDARD_AFTER,
    STANDARD_BEFORE,
    PathLike,
    _as_bool_array,
    _cleanup,
    _column,
    _lonlat,
    _nice,
    _pixel_size,
    _residual_pair,
    _temp_path,
    _transformer,
)
from .gpkg_bulk import CHUNK_ROWS, bulk_write, column_chunk, line_records, point_records, srs_ids, wkb_records
from .styles import _class_breaks, _footprint_style, _points_style, _sld, _vector_style, seams_style

#: Rows (all layers together) up to which the GeoPackage is written through OGR features; the bulk writer above.
OGR_MAX_ROWS = 100_000
_TEXT, _REAL, _BOOL = (ogr.OFTString, ogr.OFSTNone), (ogr.OFTReal, ogr.OFSTNone), (ogr.OFTInteger, ogr.OFSTBoolean)
_ARROW_FIELDS = [("id", _TEXT), ("role", _TEXT), ("epoch", _TEXT), ("res_sample", _REAL), ("res_line", _REAL),
                 ("res_px", _REAL), ("outlier", _BOOL), ("clipped", _BOOL), ("exaggeration", _REAL),
                 ("map_units_per_px", _REAL)]


@dataclass
class _Layer:
    """One layer to write: OGR creates it, then the OGR or the bulk path fills it (:func:`_write_layers`)."""
    name: str
    geom_type: int
    fields: list                   # [(field name, (OGR type, subtype))]
    n_rows: int
    make: Callable                 # make(srs_id) -> (geometry records, ok mask, {field: array or scalar})
    description: str
    style: Tuple[str, str, str]    # (QML, SLD, style description)
    metadata: Optional[dict] = None
    identifier: Optional[str] = None


def _ogr_type(values: np.ndarray):
    kind = values.dtype.kind
    if kind == "b":
        return _BOOL
    if kind in "iu":
        return ogr.OFTInteger64, ogr.OFSTNone
    if kind == "f":
        return _REAL
    return _TEXT


def _create_layer(ds, spec: _Layer, srs):
    opts = [f"DESCRIPTION={spec.description}"] if spec.description else []
    if spec.identifier:
        opts.append(f"IDENTIFIER={spec.identifier}")   # gpkg_contents.identifier: the layer's human-readable title
    layer = ds.CreateLayer(spec.name, srs, spec.geom_type, options=opts)
    if layer is None:
        raise Gf4calError(f"cannot create layer {spec.name!r} in the GeoPackage")
    for fname, (ftype, subtype) in spec.fields:
        fd = ogr.FieldDefn(fname, ftype)
        fd.SetSubType(subtype)
        if layer.CreateField(fd) != 0:
            raise Gf4calError(f"cannot create field {fname!r} in layer {spec.name!r}; check the disk is not full")
    for k, v in (spec.metadata or {}).items():
        layer.SetMetadataItem(k, str(v))
    return layer


def _wkb_offset(blob: bytes) -> int:
    """Where the WKB starts in a GeoPackage geometry blob: 8 header bytes + the envelope its flags announce."""
    return 8 + (0, 32, 48, 48, 64)[(blob[3] >> 1) & 7]


_SETTERS = {ogr.OFTReal: ogr.Feature.SetField, ogr.OFTInteger: ogr.Feature.SetFieldInteger64,
            ogr.OFTInteger64: ogr.Feature.SetFieldInteger64}


def _ogr_rows(layer, records, ok, columns, fields, cancelled) -> None:
    """One layer's rows as OGR features (in the caller's transaction): the geometry from the WKB of the same
    records the bulk writer stores, the fields as it binds them (None = NULL)."""
    defn, size = layer.GetLayerDefn(), records.dtype.itemsize
    setters = [_SETTERS.get(ftype, ogr.Feature.SetFieldString) for _, (ftype, _) in fields]
    for start in range(0, records.size, CHUNK_ROWS):
        stop = min(records.size, start + CHUNK_ROWS)
        values = [column_chunk(columns[f], ftype, start, stop) for f, (ftype, _) in fields]
        for i, blob in enumerate(records[start:stop].view(f"V{size}").tolist()):
            feature = ogr.Feature(defn)
            if ok[start + i]:
                feature.SetGeometryDirectly(ogr.CreateGeometryFromWkb(blob[_wkb_offset(blob):]))
            for j, (col, put) in enumerate(zip(values, setters)):
                if col[i] is not None:          # fields of a new feature are unset: NULL in the GeoPackage
                    put(feature, j, col[i])
            if layer.CreateFeature(feature) != 0:
                raise Gf4calError(f"cannot write to layer {layer.GetName()!r}: the disk is full or the folder not writable")
        if cancelled():
            raise CancelledError("cancelled while writing the residual GeoPackage; nothing was kept")


def writes_in_bulk(n_rows: int, *, concurrent: bool = False) -> bool:
    """The one choice of GeoPackage writer: OGR features up to :data:`OGR_MAX_ROWS` rows, the bulk writer above,
    and at any size when ``concurrent`` (the caller writes while its other threads compute: OGR's path makes ~90
    Python calls a row, each holding the GIL, where the bulk writer binds the rows in C; register-pan-ms's cells,
    written while the plots draw: 127k calls -> 31k, 1/3 less CPU at 1,452 rows)."""
    return concurrent or n_rows > OGR_MAX_ROWS


def _write_layers(path: Path, layers: Sequence[_Layer], srs, *, append: bool, cancelled,
                  concurrent: bool = False) -> None:
    """Create ``layers`` with their default styles in the GeoPackage ``path`` and fill them, through OGR or in bulk
    (:func:`writes_in_bulk`): the seam between the two. A new file goes through a temporary renamed at the end;
    ``append`` adds to an existing file (the caller's temporary: it owns atomicity). Filled in bulk, each layer's
    table is made at once (OGR defers it to the first feature): the layers keep their order in the file."""
    bulk = writes_in_bulk(sum(spec.n_rows for spec in layers), concurrent=concurrent)
    appending = append and path.exists()
    tmp = path if appending else _temp_path(path)
    check_cancel = cancelled if cancelled is not None else (lambda: False)
    ds = None
    try:
        ds = ogr.Open(str(tmp), update=1) if appending else ogr.GetDriverByName("GPKG").CreateDataSource(str(tmp))
        if ds is None or ds.StartTransaction() != 0:
            raise Gf4calError(f"cannot write the GeoPackage {path}; check the folder is writable")
        styles = []
        for spec in layers:
            layer = _create_layer(ds, spec, srs)
            if not bulk:
                _ogr_rows(layer, *spec.make(0), spec.fields, check_cancel)
            elif layer.SyncToDisk() != 0:
                raise Gf4calError(f"cannot write the GeoPackage {path}; check the disk is not full")
            styles.append((spec.name, layer.GetGeometryColumn(), *spec.style))
        _write_layer_styles(ds, styles)
        if ds.CommitTransaction() != 0:
            raise Gf4calError(f"cannot write the GeoPackage {path}: the disk is full (the commit failed); nothing was kept")
        ds = None
        if bulk and not check_cancel():
            sids = srs_ids(tmp, [spec.name for spec in layers])
            bulk_write(tmp, [(spec.name, spec.fields, (lambda m=spec.make, sid=sids[spec.name]: m(sid)))
                             for spec in layers], check_cancel)
        if check_cancel():
            raise CancelledError("cancelled while writing the residual GeoPackage; nothing was kept")
        if not appending:
            os.replace(tmp, path)
    finally:
        ds = None
        if not appending:
            _cleanup(tmp)


def _write_layer_styles(ds, styles: Sequence[Tuple[str, str, str, str, str]]) -> None:
    """QGIS's ``layer_styles`` table (same fields, types and FID name as QGIS creates), one default per layer."""
    layer = ds.GetLayerByName("layer_styles")
    if layer is not None:                      # appending layers to a GeoPackage that has styles already
        _add_styles(layer, styles)
        return
    layer = ds.CreateLayer("layer_styles", None, ogr.wkbNone, options=["FID=id"])
    spec = [("f_table_catalog", ogr.OFTString, 256), ("f_table_schema", ogr.OFTString, 256),
            ("f_table_name", ogr.OFTString, 256), ("f_geometry_column", ogr.OFTString, 256),
            ("styleName", ogr.OFTString, 30), ("styleQML", ogr.OFTString, 0), ("styleSLD", ogr.OFTString, 0),
            ("useAsDefault", ogr.OFTInteger, 0), ("description", ogr.OFTString, 0), ("owner", ogr.OFTString, 30),
            ("ui", ogr.OFTString, 30), ("update_time", ogr.OFTDateTime, 0)]
    for name, ftype, width in spec:
        fd = ogr.FieldDefn(name, ftype)
        if width:
            fd.SetWidth(width)
        if name == "useAsDefault":
            fd.SetSubType(ogr.OFSTBoolean)
        if name == "update_time":
            fd.SetDefault("CURRENT_TIMESTAMP")
        layer.CreateField(fd)
    _add_styles(layer, styles)


def _add_styles(layer, styles) -> None:
    now = _dt.datetime.now(_dt.timezone.utc)
    for table, geom_col, qml, sld, description in styles:
        f = ogr.Feature(layer.GetLayerDefn())
        f.SetField("f_table_catalog", "")
        f.SetField("f_table_schema", "")
        f.SetField("f_table_name", table)
        f.SetField("f_geometry_column", geom_col)
        f.SetField("styleName", table[:30])          # QGIS's field width
        f.SetField("styleQML", qml)
        f.SetField("styleSLD", sld)
        f.SetField("useAsDefault", 1)
        f.SetField("description", description)
        f.SetField("owner", "gdal_gf4cal")
        f.SetFieldNull("ui")
        f.SetField("update_time", now.year, now.month, now.day, now.hour, now.minute, now.second, 100)
        layer.CreateFeature(f)


def _footprint_geometry(footprint, transform):
    """A footprint (shapely geometry in lon/lat, or a GeoSeries/GeoDataFrame with a CRS) in the output CRS."""
    if footprint is None:
        return None
    if isinstance(footprint, BaseGeometry):
        geom = footprint
    else:  # GeoSeries / GeoDataFrame
        gs = getattr(footprint, "geometry", footprint)
        if getattr(gs, "crs", None) is not None:
            gs = gs.to_crs("EPSG:4326")
        geom = shapely.ops.unary_union(list(gs))
    if transform is not None:
        geom = shapely.ops.transform(lambda x, y, z=None: transform.transform(x, y), geom)
    return geom


def _gcp_columns(df, before, after) -> Tuple[dict, list, dict]:
    """The ``gcps`` layer's columns (schema, residuals before/after with their magnitude, outlier, then every other
    column of the table), its fields, and the residual pairs ``{epoch: (sample, line) or None}``."""
    n = len(df)
    lon, lat = _lonlat(df)
    for col in ("sample", "line"):
        if col not in df.columns:
            raise GCPError(f"the GCP table has no {col!r} column; residual vectors need image positions")
    nan = np.full(n, np.nan)
    columns = {"id": df["id"].astype(str).to_numpy() if "id" in df.columns else np.array([str(i) for i in range(n)]),
               "lon": lon, "lat": lat, "h": _column(df, "h") if "h" in df.columns else nan,
               "sample": _column(df, "sample"), "line": _column(df, "line"),
               "role": df["role"].astype(str).to_numpy() if "role" in df.columns else np.full(n, "control", object),
               "sigma": _column(df, "sigma") if "sigma" in df.columns else nan}
    res = {"before": _residual_pair(df, before), "after": _residual_pair(df, after)}
    for epoch in ("before", "after"):
        s_, l_ = res[epoch] if res[epoch] is not None else (nan, nan)
        columns[f"res_sample_{epoch}"], columns[f"res_line_{epoch}"] = s_, l_
        columns[f"res_px_{epoch}"] = np.hypot(s_, l_)
    columns["outlier"] = _as_bool_array(df["outlier"]) if "outlier" in df.columns else np.zeros(n, bool)
    fields = [(k, _TEXT if k in ("id", "role") else _BOOL if k == "outlier" else _REAL) for k in columns]
    skip = set(columns) | {"geometry"} | {c for pair in (before, after) if pair for c in pair}
    for col in df.columns:
        if col in skip or not isinstance(col, str):
            continue
        vals = df[col].to_numpy()
        columns[col] = vals if vals.dtype.kind in "biufO" else vals.astype(str)   # object: text, nulls kept
        fields.append((col, _ogr_type(columns[col])))
    return columns, fields, res


def _regular(finite, outlier):
    """The points that set scales and classes: finite and not outliers (all finite ones when none is left)."""
    return finite & ~outlier if (finite & ~outlier).any() else finite


def _arrow_offsets(res, metric, x, y, ps, pl, outlier) -> Tuple[dict, float]:
    """Per epoch the arrows' map offsets ``(res_sample, res_line, dx, dy)`` (sample -> east, line -> south, or the
    RPC ground offsets where the table has them) and the longest regular arrow (map units, before exaggeration):
    of the ground offsets when there are any, else of the pixel offsets."""
    offsets, longest_px, longest_m = {}, 0.0, []
    for epoch, pair in res.items():
        if pair is None:
            continue
        s_, l_ = pair
        length = np.hypot(s_ * ps, l_ * pl)
        regular = _regular(np.isfinite(length) & np.isfinite(x) & np.isfinite(y), outlier)
        if regular.any():
            longest_px = max(longest_px, float(length[regular].max()))
        dx, dy = s_ * ps, -l_ * pl                                   # image rows go down
        if metric[epoch] is not None:
            dx, dy = metric[epoch]
            v = np.hypot(dx, dy)
            v = v[_regular(np.isfinite(v), outlier)]
            longest_m += [float(v.max())] if v.size else []
        offsets[epoch] = (s_, l_, dx, dy)
    if any(m is not None for m in metric.values()):
        return offsets, max(longest_m + [0.0]) or longest_px
    return offsets, longest_px


def _arrow_layers(offsets, x, y, ids, role, outlier, *, factor, clip_at, scale, ps, pl, ps_source, title,
                  prefix) -> list:
    """The residual-arrow layers, one per epoch ('after' first, named ``residual_vectors``), ONE exaggeration for
    all (before/after compare at a glance); blunders drawn at most ``clip_at`` long and flagged ``clipped``."""
    layers = []
    for k, epoch in enumerate(e for e in ("after", "before") if e in offsets):
        s_, l_, dx, dy = offsets[epoch]
        drawn = factor * np.hypot(dx, dy)
        keep = np.isfinite(drawn) & np.isfinite(x) & np.isfinite(y)
        clipped = drawn > clip_at
        f = factor * np.where(clipped, clip_at / np.where(drawn > 0, drawn, 1.0), 1.0)[keep]
        cols = {"id": ids[keep], "role": role[keep], "epoch": epoch, "res_sample": s_[keep], "res_line": l_[keep],
                "res_px": np.hypot(s_, l_)[keep], "outlier": outlier[keep], "clipped": clipped[keep],
                "exaggeration": factor, "map_units_per_px": scale}          # scalars: the same in every row
        xk, yk, dxk, dyk = x[keep], y[keep], f * dx[keep], f * dy[keep]
        make = (lambda sid, a=(xk, yk, xk + dxk, yk + dyk), c=cols: (*line_records(*a, sid), c))
        desc = (f"{title}: {epoch} residuals (measured - predicted, px) drawn from each GCP's ground position with "
                f"sample -> east and line -> south, exaggerated {factor:g}x (1 px of residual = {scale:.6g} map "
                f"units; pixel size {ps:.6g} x {pl:.6g} map units from {ps_source})")
        if clipped[keep].any():
            desc += f"; {int(clipped[keep].sum())} blunder arrow(s) shortened to 3x the longest other one (clipped = 1)"
        meta = {"EXAGGERATION": f"{factor:g}", "MAP_UNITS_PER_PX": f"{scale:.10g}", "EPOCH": epoch,
                "DIRECTION": "sample->east, line->south", "PIXEL_SIZE_MAP_UNITS": f"{ps:.10g} {pl:.10g}"}
        name = prefix + ("residual_vectors" if k == 0 else "residual_vectors_before")
        # Classes from the regular points (blunders in the open last class); 'before' half-transparent.
        qml, sld = _vector_style(_class_breaks(np.hypot(s_, l_)[_regular(keep, outlier)]), 0.5 if k else 1.0)
        layers.append(_Layer(name, ogr.wkbLineString, _ARROW_FIELDS, int(keep.sum()), make, desc,
                             (qml, _sld(name, sld), f"residual arrows coloured by magnitude; {desc}"), meta,
                             prefix + residual_layer_title(epoch, factor)))
    return layers


def _footprint_layer(fp, title, prefix) -> list:
    """The footprint layer (none without a footprint)."""
    if fp is None or fp.is_empty:
        return []
    name = prefix + "footprint"
    wkb = ogr.ForceToMultiPolygon(ogr.CreateGeometryFromWkb(fp.wkb)).ExportToWkb(ogr.wkbNDR)
    qml, sld = _footprint_style()
    return [_Layer(name, ogr.wkbMultiPolygon, [("name", _TEXT)], 1,
                   lambda sid, bb=fp.bounds: (*wkb_records(wkb, bb, sid), {"name": "footprint"}),
                   f"{title}: scene footprint", (qml, _sld(name, sld), "scene footprint"))]


def _exaggeration(exaggeration, x, y, fp, longest, ps, pl) -> Tuple[float, float]:
    """The arrows' factor and clip length: ``exaggeration``, or automatic: the longest regular arrow ~10 % of the
    extent of the GCPs and footprint (two significant digits), blunders clipped at 3x that length."""
    if exaggeration is not None:
        return float(exaggeration), np.inf
    xs, ys = [x[np.isfinite(x)]], [y[np.isfinite(y)]]
    if fp is not None and not fp.is_empty:
        b = fp.bounds
        xs.append(np.array([b[0], b[2]]))
        ys.append(np.array([b[1], b[3]]))
    allx, ally = np.concatenate(xs), np.concatenate(ys)
    extent = max(float(np.ptp(allx)) if allx.size else 0.0, float(np.ptp(ally)) if ally.size else 0.0)
    extent = extent if extent > 0 else 100.0 * max(ps, pl)
    factor = _nice(0.1 * extent / longest) if longest > 0 else 1.0
    return factor, 3.0 * longest * factor


@with_quiet_errors
def write_residuals_gpkg(gcps, path: PathLike, *, footprint=None, exaggeration: Optional[float] = None,
                         before: Optional[Tuple[str, str]] = STANDARD_BEFORE,
                         after: Optional[Tuple[str, str]] = STANDARD_AFTER,
                         crs: Any = "EPSG:4326", pixel_size=None, overwrite: bool = False,
                         title: str = "GCP residuals", cancelled: Optional[Callable[[], bool]] = None,
                         layer_prefix: str = "", append: bool = False, points_title: Optional[str] = None,
                         concurrent: bool = False) -> Path:
    """Write GCPs and their residuals as a styled GeoPackage that QGIS draws at once (layers: module docstring).

    ``gcps``: GCP table (``id, lon, lat, h, sample, line, role`` + ``sigma``, ``outlier``, ...; the point geometry
    without ``lon``/``lat``). ``path``: a ``.gpkg``, written atomically; an existing one is refused unless
    ``overwrite`` (the :mod:`~gdal_gf4cal.outputs` rule). ``footprint``: shapely geometry (lon/lat) or
    GeoSeries/GeoDataFrame (:func:`footprint_from_rpc`). ``exaggeration``: the arrows' factor; default one factor
    for every layer making the longest arrow of a point not flagged ``outlier`` ~10 % of the extent, longer
    (blunder) arrows shortened to 3x that length and flagged ``clipped``. ``before``, ``after``: the (sample, line)
    residual columns (px, ``measured - predicted``; missing ones skipped; output fields have the standard names).
    ``crs``: of the output layers. ``pixel_size``: ground size of a pixel in map units when the GCPs cannot give
    it (< 3 points). ``cancelled``: asked between layers and every 20,000 rows; True stops with
    :class:`~gdal_gf4cal.errors.CancelledError`, nothing kept. ``points_title``: the points layer's title
    (``IDENTIFIER``) when they are not GCPs (e.g. pan-MS cells). ``layer_prefix``: of every layer name and title
    (several images in one file). ``append``: add the layers to the existing ``path`` (the caller owns atomicity,
    e.g. an :class:`~gdal_gf4cal.outputs.OutputSet` temporary). ``concurrent``: the caller's other threads compute
    meanwhile: the rows go in through the bulk writer at any size (:func:`writes_in_bulk`). Returns the path.
    """
    path = Path(path)
    if path.suffix.lower() != ".gpkg":
        raise GCPError(f"residuals are written as a GeoPackage: give a .gpkg path, not {path.name!r}")
    if not append:
        check_output_path(path, overwrite=overwrite)
    df = gcps if isinstance(gcps, pd.DataFrame) else pd.DataFrame(gcps)
    columns, fields, res = _gcp_columns(df, before, after)
    out_crs, tf = _transformer(crs)
    x, y = (columns["lon"], columns["lat"]) if tf is None else tf.transform(columns["lon"], columns["lat"])
    x, y = np.asarray(x, float), np.asarray(y, float)
    fp = _footprint_geometry(footprint, tf)
    ps, pl, ps_source = _pixel_size(x, y, columns["sample"], columns["line"], pixel_size)
    metric = {e: _metric_offsets(df, e, columns["lon"], columns["lat"], x, y, tf) for e in res if res[e] is not None}
    offsets, longest = _arrow_offsets(res, metric, x, y, ps, pl, columns["outlier"])
    factor, clip_at = _exaggeration(exaggeration, x, y, fp, longest, ps, pl)
    qml, sld = _points_style()
    gname = layer_prefix + "gcps"
    layers = [_Layer(gname, ogr.wkbPoint, fields, len(df), lambda sid: (*point_records(x, y, sid), columns),
                     f"{title}: ground control / check points with residuals (measured - predicted, px)",
                     (qml, _sld(gname, sld), "GCPs by role; outliers as red crosses"), None, points_title)]
    layers += _arrow_layers(offsets, x, y, columns["id"], columns["role"], columns["outlier"], factor=factor,
                            clip_at=clip_at, scale=factor * math.sqrt(ps * pl), ps=ps, pl=pl, ps_source=ps_source,
                            title=title, prefix=layer_prefix)
    layers += _footprint_layer(fp, title, layer_prefix)
    _write_layers(path, layers, _srs(out_crs.to_wkt()), append=append, cancelled=cancelled, concurrent=concurrent)
    return path


def _srs(crs):
    """An OGR spatial reference (lon/lat axis order) of a WKT string or an EPSG code."""
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(crs) if isinstance(crs, int) else srs.ImportFromWkt(crs)
    srs.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    return srs


@with_quiet_errors
def write_points_layer(path: PathLike, layer: str, columns: Mapping[str, np.ndarray], lon, lat, *,
                       description: str = "") -> Path:
    """Add a point layer (EPSG:4326, one feature per row of ``columns``) to the GeoPackage ``path`` (created when
    absent), styled as the ``gcps`` layers (e.g. block calibration's ``seams``: one feature per overlap tie point).
    Written as the residual layers are (:func:`_write_layers`)."""
    path = Path(path)
    cols = {k: np.asarray(v) for k, v in columns.items()}
    fields = [(k, _ogr_type(v)) for k, v in cols.items()]
    lon, lat = np.asarray(lon, float), np.asarray(lat, float)
    if layer == "seams":       # seam offsets: graduated arrows, the factor in the title (styles.seams_style)
        qml, sld, title, _ = seams_style(cols, lon, lat)
    else:
        (qml, sld), title = _points_style(), None
    spec = _Layer(layer, ogr.wkbPoint, fields, lon.size, lambda sid: (*point_records(lon, lat, sid), cols),
                  description, (qml, _sld(layer, sld), description), identifier=title)
    _write_layers(path, [spec], _srs(4326), append=True, cancelled=None)
    return path


def residual_layer_title(epoch: str, factor: float) -> str:
    """The title of a residual-arrow layer, stating its exaggeration: ``"residuals after (x37)"``. The GeoPackage
    stores it as the layer's ``IDENTIFIER`` (gpkg_contents), and QGIS shows it as the layer name, so before and
    after arrows drawn with one factor say so in the legend."""
    return f"residuals {epoch} (x{float(factor):g})"


def layer_titles(path: PathLike) -> dict:
    """``{table name: title}`` of a GeoPackage's layers: the ``IDENTIFIER`` when it differs from the table name
    (the residual arrows, see :func:`residual_layer_title`), else the table name."""
    ds = open_vector(path, what="GeoPackage")
    out = {}
    for i in range(ds.GetLayerCount()):
        layer = ds.GetLayer(i)
        name = layer.GetName()
        out[name] = layer.GetMetadataItem("IDENTIFIER") or name
    ds = None
    return out


def _metric_offsets(df, epoch, lon, lat, x, y, tf):
    """Map-unit (dx, dy) of the ground offsets ``res_east_m_<epoch>``, ``res_north_m_<epoch>`` (metres) at each GCP,
    or None when the table has no such columns."""
    ce, cn = f"res_east_m_{epoch}", f"res_north_m_{epoch}"
    if ce not in df.columns or cn not in df.columns:
        return None
    e, n = _column(df, ce), _column(df, cn)
    r = 6371008.8
    lon2 = lon + np.degrees(e / (r * np.cos(np.radians(lat))))
    lat2 = lat + np.degrees(n / r)
    x2, y2 = (lon2, lat2) if tf is None else tf.transform(lon2, lat2)
    return np.asarray(x2, float) - x, np.asarray(y2, float) - y


def footprint_from_rpc(rpc, size: Tuple[int, int], h=0.0, n: int = 16):
    """Scene footprint: the image border localised through ``rpc`` at height ``h`` (metres or a DEM).

    Parameters
    ----------
    rpc : object with ``localize(sample, line, h)`` (and ``localize_dem(sample, line, dem)`` for a DEM)
    size : (width, height) in pixels
    h : float or DEM
        Height of the border points (ellipsoidal m), or a DEM to intersect the lines of sight with.
    n : int
        Points per image side.

    Returns
    -------
    shapely.geometry.Polygon
        In lon/lat (EPSG:4326); border points that fail to localise are dropped.
    """
    w, hh = float(size[0]), float(size[1])
    t = np.linspace(0.0, 1.0, n, endpoint=False)
    s = np.concatenate([t * w, np.full(n, w), w - t * w, np.zeros(n)])
    l = np.concatenate([np.zeros(n), t * hh, np.full(n, hh), hh - t * hh])
    if np.isscalar(h):
        lon, lat = rpc.localize(s, l, np.full(s.shape, float(h)))[:2]
    else:
        lon, lat = rpc.localize_dem(s, l, h)[:2]
    lon, lat = np.asarray(lon, float), np.asarray(lat, float)
    ok = np.isfinite(lon) & np.isfinite(lat)
    if ok.sum() < 3:
        raise Gf4calError("the image border does not localise through the RPC; check the RPC and the height")
    return Polygon(np.column_stack([lon[ok], lat[ok]]))
