"""The residual GeoPackage (GCP points, residual arrows, footprint, default styles); OGR return codes checked."""
from __future__ import annotations

import datetime as _dt
import math
import os
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence, Tuple

import numpy as np

from ..errors import GCPError, Gf4calError
from ._common import _as_bool_array, STANDARD_BEFORE, STANDARD_AFTER, PathLike, _temp_path, _cleanup, _column, _lonlat, _residual_pair, _transformer, _pixel_size, _nice
from .styles import _class_breaks, _vector_style, _points_style, _footprint_style, _sld


# ----------------------------------------------------------------------------------------------------------------
# GeoPackage
# ----------------------------------------------------------------------------------------------------------------
def _ogr_type(values: np.ndarray):
    from osgeo import ogr
    kind = values.dtype.kind
    if kind == "b":
        return ogr.OFTInteger, ogr.OFSTBoolean
    if kind in "iu":
        return ogr.OFTInteger64, ogr.OFSTNone
    if kind == "f":
        return ogr.OFTReal, ogr.OFSTNone
    return ogr.OFTString, ogr.OFSTNone



def _create_layer(ds, name, srs, geom_type, fields, description, metadata=None):
    from osgeo import ogr
    opts = [f"DESCRIPTION={description}"] if description else []
    layer = ds.CreateLayer(name, srs, geom_type, options=opts)
    if layer is None:
        raise Gf4calError(f"cannot create layer {name!r} in the GeoPackage")
    for fname, (ftype, subtype) in fields:
        fd = ogr.FieldDefn(fname, ftype)
        fd.SetSubType(subtype)
        if layer.CreateField(fd) != 0:
            raise Gf4calError(f"cannot create field {fname!r} in layer {name!r}; check the disk is not full")
    for k, v in (metadata or {}).items():
        layer.SetMetadataItem(k, str(v))
    return layer


def _column_values(values, ftype) -> list:
    """One column as Python values of the field's type, ``None`` where it is null (NaN, inf, None)."""
    from osgeo import ogr
    out = []
    for v in (values.tolist() if isinstance(values, np.ndarray) else list(values)):
        if v is None or (isinstance(v, float) and not math.isfinite(v)):
            out.append(None)
        elif ftype == ogr.OFTReal:
            out.append(float(v))
        elif ftype in (ogr.OFTInteger, ogr.OFTInteger64):
            out.append(int(v))
        else:
            out.append(str(v))
    return out


def _write_features(layer, fields, columns: Mapping[str, np.ndarray], geoms: Sequence) -> None:
    """Write one feature per geometry; fields by index with typed setters (the by-name setters looked the field
    up for every value: 1e5 GCPs took minutes)."""
    from osgeo import ogr
    defn = layer.GetLayerDefn()
    plan = []
    for fname, (ftype, _) in fields:
        idx = defn.GetFieldIndex(fname)
        if ftype == ogr.OFTReal:
            setter = "SetField"           # by index: no name lookup (no SetFieldDouble in GDAL 3.6)
        elif ftype in (ogr.OFTInteger, ogr.OFTInteger64):
            setter = "SetFieldInteger64"
        else:
            setter = "SetFieldString"
        plan.append((idx, setter, _column_values(columns[fname], ftype)))
    for i, g in enumerate(geoms):
        feat = ogr.Feature(defn)
        for idx, setter, vals in plan:
            v = vals[i]
            if v is None:
                feat.SetFieldNull(idx)
            else:
                getattr(feat, setter)(idx, v)
        if g is not None:
            feat.SetGeometry(ogr.CreateGeometryFromWkb(g))
        if layer.CreateFeature(feat) != 0:
            raise Gf4calError(f"cannot write feature {i} of layer {layer.GetName()!r}")


def _write_layer_styles(ds, styles: Sequence[Tuple[str, str, str, str, str]]) -> None:
    """QGIS's ``layer_styles`` table (same fields, types and FID name as QGIS creates), one default per layer."""
    from osgeo import ogr
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
    from osgeo import ogr
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
    import shapely.ops
    from shapely.geometry.base import BaseGeometry
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


def write_residuals_gpkg(gcps, path: PathLike, *, footprint=None, exaggeration: Optional[float] = None,
                         before: Optional[Tuple[str, str]] = STANDARD_BEFORE,
                         after: Optional[Tuple[str, str]] = STANDARD_AFTER,
                         crs: Any = "EPSG:4326", pixel_size=None, overwrite: bool = True,
                         title: str = "GCP residuals", layer_prefix: str = "", append: bool = False) -> Path:
    """Write GCPs and their residuals as a styled GeoPackage that QGIS draws at once.

    Layers (the styles are the layers' defaults in ``layer_styles``, QML and SLD):

    ``gcps``
        One point per GCP at its ground position, fields ``id, lon, lat, h, sample, line, role, sigma,
        res_sample_before, res_line_before, res_px_before, res_sample_after, res_line_after, res_px_after,
        outlier`` and every other column of ``gcps`` (quality measures, truth, normalised residuals...).
        Residuals in px, ``res_px`` = planar magnitude ``hypot(res_sample, res_line)``. Drawn by role
        (control: blue triangle, check: green circle) with outliers as red crosses.
    ``residual_vectors``
        One line per GCP from its ground position in the residual direction (sample -> east, line -> south),
        length = residual x ground pixel size x ``exaggeration``; the *after* residuals when given, else the
        *before*. Fields ``id, role, epoch, res_sample, res_line, res_px, outlier, clipped, exaggeration,
        map_units_per_px``; the factor is also in the layer description and metadata (``EXAGGERATION``).
        Drawn as arrows coloured by ``res_px`` (graduated, 6 classes from 0 to the largest non-outlier
        residual; larger ones fall in the last, open class).
    ``residual_vectors_before``
        Same for the *before* residuals, only when both before and after are given, with the SAME factor as
        ``residual_vectors`` (the gain of the refinement shows as shorter arrows).
    ``footprint``
        The scene footprint polygon, when ``footprint`` is given.

    Parameters
    ----------
    gcps : geopandas.GeoDataFrame or pandas.DataFrame
        GCP table (DESIGN.md schema): ``id, lon, lat, h, sample, line, role`` (+ ``sigma``, ``outlier``, ...).
        Without ``lon``/``lat`` columns the point geometry is used.
    path : path-like
        Output ``.gpkg``; written atomically (temporary file + :func:`os.replace`).
    footprint : shapely geometry (lon/lat) or GeoSeries/GeoDataFrame, optional
        Scene footprint, see :func:`footprint_from_rpc`.
    exaggeration : float, optional
        Factor applied to the residuals' ground size. Default: one factor for every layer, chosen so that the
        longest vector (any epoch) of a point not flagged ``outlier`` is about 10 % of the extent of the GCPs (and
        footprint), rounded to two significant digits; then longer (blunder) arrows are shortened to 3x that length and flagged ``clipped``.
    before, after : (str, str) or None
        Names of the (sample, line) residual columns in ``gcps``, in pixels (``measured - predicted``). Missing
        columns are skipped; the output fields always have the standard names.
    crs : anything pyproj accepts
        CRS of the output layers (default EPSG:4326).
    pixel_size : float or (float, float), optional
        Ground size of a pixel in map units, used only when it cannot be estimated from the GCPs (< 3 points).
    overwrite : bool
        Replace an existing file (default True).
    layer_prefix : str
        Prefix of every layer name (``<prefix>gcps``, ...): several images' layers in one GeoPackage.
    append : bool
        Add the layers to the existing GeoPackage ``path`` (in one transaction; the caller owns atomicity, e.g. an
        :class:`~gdal_gf4cal.outputs.OutputSet` temporary) instead of replacing it.

    Returns
    -------
    pathlib.Path
        The written path.
    """
    from osgeo import ogr, osr
    import pandas as pd

    path = Path(path)
    if path.suffix.lower() != ".gpkg":
        raise GCPError(f"residuals are written as a GeoPackage: give a .gpkg path, not {path.name!r}")
    if path.exists() and not overwrite and not append:
        from ..errors import InputOverwriteError
        raise InputOverwriteError(f"{path} exists; remove it or pass overwrite=True")
    df = gcps if isinstance(gcps, pd.DataFrame) else pd.DataFrame(gcps)
    n = len(df)
    lon, lat = _lonlat(df)
    for col in ("sample", "line"):
        if col not in df.columns:
            raise GCPError(f"the GCP table has no {col!r} column; residual vectors need image positions")
    sample, line = _column(df, "sample"), _column(df, "line")
    h = _column(df, "h") if "h" in df.columns else np.full(n, np.nan)
    ids = (df["id"].astype(str).to_numpy() if "id" in df.columns else np.array([str(i) for i in range(n)]))
    role = (df["role"].astype(str).to_numpy() if "role" in df.columns else np.full(n, "control", dtype=object))
    sigma = _column(df, "sigma") if "sigma" in df.columns else np.full(n, np.nan)
    outlier = _as_bool_array(df["outlier"]) if "outlier" in df.columns else np.zeros(n, bool)
    res = {"before": _residual_pair(df, before), "after": _residual_pair(df, after)}

    out_crs, tf = _transformer(crs)
    x, y = (lon, lat) if tf is None else tf.transform(lon, lat)
    x, y = np.asarray(x, float), np.asarray(y, float)
    fp = _footprint_geometry(footprint, tf)
    ps, pl, ps_source = _pixel_size(x, y, sample, line, pixel_size)

    # Extent for the automatic factor: the GCPs' and the footprint's bounding box.
    xs, ys = [x[np.isfinite(x)]], [y[np.isfinite(y)]]
    if fp is not None and not fp.is_empty:
        b = fp.bounds
        xs.append(np.array([b[0], b[2]]))
        ys.append(np.array([b[1], b[3]]))
    allx, ally = np.concatenate(xs), np.concatenate(ys)
    extent = max(float(np.ptp(allx)) if allx.size else 0.0, float(np.ptp(ally)) if ally.size else 0.0)
    if extent <= 0:
        extent = 100.0 * max(ps, pl)

    # gcps layer columns
    columns = {"id": ids, "lon": lon, "lat": lat, "h": h, "sample": sample, "line": line, "role": role,
               "sigma": sigma}
    for epoch in ("before", "after"):
        r = res[epoch]
        s_, l_ = (r if r is not None else (np.full(n, np.nan), np.full(n, np.nan)))
        columns[f"res_sample_{epoch}"], columns[f"res_line_{epoch}"] = s_, l_
        columns[f"res_px_{epoch}"] = np.hypot(s_, l_)
    columns["outlier"] = outlier
    text_t, real_t = (ogr.OFTString, ogr.OFSTNone), (ogr.OFTReal, ogr.OFSTNone)
    bool_t = (ogr.OFTInteger, ogr.OFSTBoolean)
    fields = [(k, text_t if k in ("id", "role") else bool_t if k == "outlier" else real_t) for k in columns]
    skip = set(columns) | {"geometry"} | {c for pair in (before, after) if pair for c in pair}
    for col in df.columns:
        if col in skip or not isinstance(col, str):
            continue
        vals = df[col].to_numpy()
        if vals.dtype.kind == "O":
            vals = np.array([None if v is None or (isinstance(v, float) and math.isnan(v)) else str(v)
                             for v in vals], dtype=object)
        elif vals.dtype.kind not in "biuf":
            vals = vals.astype(str)
        columns[col] = vals
        fields.append((col, _ogr_type(vals)))

    def point_wkb(i):
        if not (math.isfinite(x[i]) and math.isfinite(y[i])):
            return None
        g = ogr.Geometry(ogr.wkbPoint)
        g.AddPoint_2D(float(x[i]), float(y[i]))
        return g.ExportToWkb()

    srs = osr.SpatialReference()
    srs.ImportFromWkt(out_crs.to_wkt())
    srs.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)

    # residual vectors, one layer per epoch, ONE exaggeration for all epochs (so before/after compare at a glance):
    # the automatic factor comes from the longest regular arrow of any epoch (usually 'before').
    vector_layers = []
    epochs = [e for e in ("after", "before") if res[e] is not None]
    longest_all = 0.0
    for epoch in epochs:
        s_, l_ = res[epoch]
        length = np.hypot(s_ * ps, l_ * pl)
        finite = np.isfinite(length) & np.isfinite(x) & np.isfinite(y)
        regular = finite & ~outlier if (finite & ~outlier).any() else finite
        if regular.any():
            longest_all = max(longest_all, float(length[regular].max()))
    metric = {e: _metric_offsets(df, e, lon, lat, x, y, tf) for e in epochs}
    if any(m is not None for m in metric.values()):       # arrows from the RPC ground offsets: rescale the factor
        lens = [np.hypot(*m) for m in metric.values() if m is not None]
        lens = [v[np.isfinite(v) & ~outlier] if (np.isfinite(v) & ~outlier).any() else v[np.isfinite(v)]
                for v in lens]
        longest_all = max([float(v.max()) for v in lens if v.size] + [0.0]) or longest_all
    for k, epoch in enumerate(epochs):
        s_, l_ = res[epoch]
        dx, dy = s_ * ps, -l_ * pl  # sample -> east, line -> south (image rows go down)
        if metric[epoch] is not None:
            dx, dy = metric[epoch]   # the RPC ground offsets (res_east_m_/res_north_m_ columns), in map units
        length = np.hypot(dx, dy)
        mag = np.hypot(s_, l_)
        finite = np.isfinite(length) & np.isfinite(x) & np.isfinite(y)
        # Scale and classes follow the ordinary points: one blunder must not shrink every other arrow to nothing.
        regular = finite & ~outlier if (finite & ~outlier).any() else finite
        clip_at = np.inf
        if exaggeration is not None:
            factor = float(exaggeration)
        else:
            factor = _nice(0.1 * extent / longest_all) if longest_all > 0 else 1.0
            clip_at = 3.0 * longest_all * factor  # auto mode: blunders drawn at most 3x the longest regular arrow
        name = layer_prefix + ("residual_vectors" if k == 0 else "residual_vectors_before")
        scale = factor * math.sqrt(ps * pl)
        drawn = factor * length
        shrink = np.where(drawn > clip_at, clip_at / np.where(drawn > 0, drawn, 1.0), 1.0)
        clipped = drawn > clip_at
        geoms = []
        for i in np.flatnonzero(finite):
            g = ogr.Geometry(ogr.wkbLineString)
            g.AddPoint_2D(float(x[i]), float(y[i]))
            g.AddPoint_2D(float(x[i] + factor * shrink[i] * dx[i]), float(y[i] + factor * shrink[i] * dy[i]))
            geoms.append(g.ExportToWkb())
        keep = finite
        cols = {"id": ids[keep], "role": role[keep], "epoch": np.full(keep.sum(), epoch, dtype=object),
                "res_sample": s_[keep], "res_line": l_[keep], "res_px": mag[keep], "outlier": outlier[keep],
                "clipped": clipped[keep], "exaggeration": np.full(keep.sum(), factor),
                "map_units_per_px": np.full(keep.sum(), scale)}
        vfields = [("id", (ogr.OFTString, ogr.OFSTNone)), ("role", (ogr.OFTString, ogr.OFSTNone)),
                   ("epoch", (ogr.OFTString, ogr.OFSTNone))] + \
                  [(c, (ogr.OFTReal, ogr.OFSTNone)) for c in ("res_sample", "res_line", "res_px")] + \
                  [("outlier", (ogr.OFTInteger, ogr.OFSTBoolean)), ("clipped", (ogr.OFTInteger, ogr.OFSTBoolean)),
                   ("exaggeration", (ogr.OFTReal, ogr.OFSTNone)), ("map_units_per_px", (ogr.OFTReal, ogr.OFSTNone))]
        desc = (f"{title}: {epoch} residuals (measured - predicted, px) drawn from each GCP's ground position with "
                f"sample -> east and line -> south, exaggerated {factor:g}x (1 px of residual = {scale:.6g} map "
                f"units; pixel size {ps:.6g} x {pl:.6g} map units from {ps_source})")
        if clipped.any():
            desc += f"; {int(clipped.sum())} blunder arrow(s) shortened to 3x the longest other one (clipped = 1)"
        meta = {"EXAGGERATION": f"{factor:g}", "MAP_UNITS_PER_PX": f"{scale:.10g}", "EPOCH": epoch,
                "DIRECTION": "sample->east, line->south", "PIXEL_SIZE_MAP_UNITS": f"{ps:.10g} {pl:.10g}"}
        mag = mag[regular]  # class breaks from the regular points; blunders fall in the open last class
        vector_layers.append((name, vfields, cols, geoms, desc, meta, mag))

    if path.exists() and not overwrite and not append:  # pragma: no cover - checked above; re-checked for races
        raise Gf4calError(f"{path} exists")
    appending = append and path.exists()
    tmp = path if appending else _temp_path(path)
    driver = ogr.GetDriverByName("GPKG")
    try:
        ds = ogr.Open(str(path), update=1) if appending else driver.CreateDataSource(str(tmp))
        if ds is None:
            raise Gf4calError(f"cannot create a GeoPackage in {path.parent}; check the folder is writable")
        styles = []
        if ds.StartTransaction() != 0:
            raise Gf4calError(f"cannot write the GeoPackage {path}; check the folder is writable")
        gname = layer_prefix + "gcps"
        gl = _create_layer(ds, gname, srs, ogr.wkbPoint, fields,
                           f"{title}: ground control / check points with residuals (measured - predicted, px)")
        _write_features(gl, fields, columns, [point_wkb(i) for i in range(n)])
        qml, sld = _points_style()
        styles.append((gname, gl.GetGeometryColumn(), qml, _sld(gname, sld), "GCPs by role; outliers as red crosses"))
        for name, vfields, cols, geoms, desc, meta, mag in vector_layers:
            vl = _create_layer(ds, name, srs, ogr.wkbLineString, vfields, desc, meta)
            _write_features(vl, vfields, cols, geoms)
            # The 'before' arrows are drawn half-transparent so the 'after' ones stand out where both are shown.
            qml, sld = _vector_style(_class_breaks(mag), 1.0 if name.endswith("residual_vectors") else 0.5)
            styles.append((name, vl.GetGeometryColumn(), qml, _sld(name, sld),
                           f"residual arrows coloured by magnitude; {desc}"))
        if fp is not None and not fp.is_empty:
            fname = layer_prefix + "footprint"
            fl = _create_layer(ds, fname, srs, ogr.wkbMultiPolygon, [("name", (ogr.OFTString, ogr.OFSTNone))],
                               f"{title}: scene footprint")
            g = ogr.ForceToMultiPolygon(ogr.CreateGeometryFromWkb(fp.wkb))
            _write_features(fl, [("name", (ogr.OFTString, ogr.OFSTNone))], {"name": ["footprint"]}, [g.ExportToWkb()])
            qml, sld = _footprint_style()
            styles.append((fname, fl.GetGeometryColumn(), qml, _sld(fname, sld), "scene footprint"))
        _write_layer_styles(ds, styles)
        if ds.CommitTransaction() != 0:
            raise Gf4calError(f"cannot write the GeoPackage {path} (the commit failed: disk full?); nothing was kept")
        ds = None
        if not appending:
            os.replace(tmp, path)
    finally:
        ds = None
        if not appending:
            _cleanup(tmp)
    return path


def write_points_layer(path: PathLike, layer: str, columns: Mapping[str, np.ndarray], lon, lat, *,
                       description: str = "") -> Path:
    """Add a point layer (EPSG:4326, one feature per row of ``columns``) to the GeoPackage ``path`` (created when
    absent), styled as the ``gcps`` layers (e.g. block calibration's ``seams``: one feature per overlap tie point)."""
    from osgeo import ogr, osr
    path = Path(path)
    ds = ogr.Open(str(path), update=1) if path.exists() else ogr.GetDriverByName("GPKG").CreateDataSource(str(path))
    if ds is None:
        raise Gf4calError(f"cannot write the GeoPackage {path}; check the folder is writable")
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(4326)
    srs.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    cols = {k: np.asarray(v) for k, v in columns.items()}
    fields = [(k, _ogr_type(v)) for k, v in cols.items()]
    lon, lat = np.asarray(lon, float), np.asarray(lat, float)
    geoms = []
    for x, y in zip(lon, lat):
        if math.isfinite(x) and math.isfinite(y):
            g = ogr.Geometry(ogr.wkbPoint)
            g.AddPoint_2D(float(x), float(y))
            geoms.append(g.ExportToWkb())
        else:
            geoms.append(None)
    try:
        if ds.StartTransaction() != 0:
            raise Gf4calError(f"cannot write the GeoPackage {path}; check the folder is writable")
        lyr = _create_layer(ds, layer, srs, ogr.wkbPoint, fields, description)
        _write_features(lyr, fields, cols, geoms)
        qml, sld = _points_style()
        _write_layer_styles(ds, [(layer, lyr.GetGeometryColumn(), qml, _sld(layer, sld), description)])
        if ds.CommitTransaction() != 0:
            raise Gf4calError(f"cannot write the GeoPackage {path} (the commit failed: disk full?)")
    finally:
        ds = None
    return path


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
    from shapely.geometry import Polygon
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
