"""GIS-ready outputs: residual GeoPackages with default QGIS styles, residual plots and ``report.json``.

Three writers, each atomic (temporary file in the destination folder, then :func:`os.replace`):

* :func:`write_residuals_gpkg` - a GeoPackage a GIS user can open at once: GCP points, residual vectors drawn as
  arrows coloured by magnitude, the scene footprint, and their default QGIS styles in ``layer_styles``.
* :func:`plot_residuals` - a PNG of the residual vectors in image space, before and after (like Fig. 5 of the GF4
  paper, seed 000), with a scale arrow.
* :func:`write_report_json` - a JSON report that accepts NumPy scalars/arrays (NaN becomes ``null``).

Residuals are ``measured - predicted`` in pixels, per axis (METHODS §0, §6). Image coordinates follow GDAL's pixel
convention (centre of the first pixel at 0.5, 0.5).

**Direction of the residual vectors on the map.** A residual ``(res_sample, res_line)`` is drawn from the GCP's
ground position with *sample -> east* and *line -> south* (image rows go down), each axis scaled by the mean
ground size of one pixel along that image axis (estimated from the GCPs themselves by an affine fit), times an
exaggeration factor. For a north-up image this is the residual's true ground direction; for a rotated image (e.g.
a descending or geostationary view) it is the image-space direction laid on the map, which is what one wants when
comparing residual patterns with the detector layout.

This module never imports qgis or PyQt: the styles are written as QGIS QML (and OGC SLD) text.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence, Tuple, Union
from xml.sax.saxutils import escape, quoteattr

import numpy as np

from .errors import GCPError, Gf4calError

__all__ = [
    "write_residuals_gpkg", "plot_residuals", "write_report_json", "footprint_from_rpc", "assess_accuracy",
    "RESIDUAL_FIELDS", "STANDARD_BEFORE", "STANDARD_AFTER",
]

STANDARD_BEFORE = ("res_sample_before", "res_line_before")
STANDARD_AFTER = ("res_sample_after", "res_line_after")
#: Residual fields of the ``gcps`` layer, in order (pixels).
RESIDUAL_FIELDS = ("res_sample_before", "res_line_before", "res_px_before",
                   "res_sample_after", "res_line_after", "res_px_after")
_BASE_FIELDS = ("id", "lon", "lat", "h", "sample", "line", "role", "sigma")
# Colours of the magnitude classes (ColorBrewer RdYlBu, reversed: small residuals blue, large red).
_RAMP = ("#2c7bb6", "#00a6ca", "#90eb9d", "#f9d057", "#f29e2e", "#d7191c")
_ROLE_COLOURS = {"control": "#1f4fd1", "check": "#18a025"}
_OUTLIER_COLOUR = "#e4002b"
_FOOTPRINT_COLOUR = "#555555"

PathLike = Union[str, os.PathLike]


# ----------------------------------------------------------------------------------------------------------------
# atomic writing
# ----------------------------------------------------------------------------------------------------------------
def _temp_path(path: Path) -> Path:
    """A fresh path in the destination folder (so that os.replace is atomic), with the same suffix."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    os.unlink(tmp)  # GDAL drivers want to create the file themselves
    return Path(tmp)


def _cleanup(tmp: Path) -> None:
    for p in (tmp, Path(str(tmp) + "-wal"), Path(str(tmp) + "-shm"), Path(str(tmp) + "-journal")):
        try:
            p.unlink()
        except FileNotFoundError:
            pass


# ----------------------------------------------------------------------------------------------------------------
# report.json
# ----------------------------------------------------------------------------------------------------------------
def _jsonable(obj: Any) -> Any:
    """Convert NumPy scalars/arrays, paths, dataclasses, sets and non-finite floats to plain JSON values."""
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if obj is None or isinstance(obj, str):
        return obj
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, (_dt.datetime, _dt.date)):
        return obj.isoformat()
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return _jsonable(dataclasses.asdict(obj))
    if hasattr(obj, "to_dict"):
        return _jsonable(obj.to_dict())
    if hasattr(obj, "item") and callable(obj.item):  # other NumPy-like scalars
        return _jsonable(obj.item())
    raise TypeError(f"report value of type {type(obj).__name__} is not JSON-serialisable")


def write_report_json(report: Mapping[str, Any], path: PathLike, *, indent: int = 2) -> Path:
    """Write ``report`` as JSON, atomically.

    NumPy scalars and arrays, paths, dataclasses and objects with ``to_dict()`` are converted; NaN and infinities
    become ``null`` so the file is strict JSON that any reader accepts.

    Returns
    -------
    pathlib.Path
        The written path.
    """
    path = Path(path)
    text = json.dumps(_jsonable(report), indent=indent, allow_nan=False, ensure_ascii=False) + "\n"
    tmp = _temp_path(path)
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    finally:
        _cleanup(tmp)
    return path


# ----------------------------------------------------------------------------------------------------------------
# the GCP table in, normalised
# ----------------------------------------------------------------------------------------------------------------
def _column(df, name) -> Optional[np.ndarray]:
    if name is None or name not in df.columns:
        return None
    return np.asarray(df[name].to_numpy(), dtype=float)


def _lonlat(df) -> Tuple[np.ndarray, np.ndarray]:
    """Ground longitude/latitude (WGS84) from the ``lon``/``lat`` columns, else from the geometry."""
    if "lon" in df.columns and "lat" in df.columns:
        return _column(df, "lon"), _column(df, "lat")
    geom = getattr(df, "geometry", None) if "geometry" in df.columns else None
    if geom is None:
        raise GCPError("the GCP table has neither lon/lat columns nor a point geometry; give the ground positions")
    if getattr(df, "crs", None) is not None and not df.crs.equals("EPSG:4326"):
        geom = geom.to_crs("EPSG:4326")
    return np.asarray(geom.x, dtype=float), np.asarray(geom.y, dtype=float)


def _residual_pair(df, names) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    if names is None:
        return None
    s, l = _column(df, names[0]), _column(df, names[1])
    if s is None or l is None:
        return None
    return s, l


def _transformer(crs):
    from pyproj import CRS, Transformer
    crs = CRS.from_user_input(crs)
    if crs.equals(CRS.from_epsg(4326)):
        return crs, None
    return crs, Transformer.from_crs("EPSG:4326", crs, always_xy=True)


def _pixel_size(x, y, sample, line, fallback) -> Tuple[float, float, str]:
    """Map units per pixel along the sample and line axes, from an affine fit of map (x, y) on (sample, line)."""
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(sample) & np.isfinite(line)
    if ok.sum() >= 3:
        A = np.column_stack([np.ones(ok.sum()), sample[ok], line[ok]])
        # Condition check: collinear GCPs give no pixel size along one axis.
        if np.linalg.matrix_rank(A - np.r_[0, A[:, 1:].mean(0)], tol=1e-6 * max(np.ptp(A[:, 1:]), 1.0)) == 3:
            cx, *_ = np.linalg.lstsq(A, x[ok], rcond=None)
            cy, *_ = np.linalg.lstsq(A, y[ok], rcond=None)
            ps, pl = float(np.hypot(cx[1], cy[1])), float(np.hypot(cx[2], cy[2]))
            if ps > 0 and pl > 0 and math.isfinite(ps) and math.isfinite(pl):
                return ps, pl, "affine fit of the GCPs' map positions on their image positions"
    if fallback is not None:
        ps, pl = (float(fallback), float(fallback)) if np.isscalar(fallback) else map(float, fallback)
        return ps, pl, "given pixel size"
    return 1.0, 1.0, "unknown (fewer than 3 non-collinear GCPs): 1 map unit per pixel assumed"


def _nice(v: float) -> float:
    """Round to two significant digits (a factor a reader can quote)."""
    if not math.isfinite(v) or v <= 0:
        return 1.0
    e = math.floor(math.log10(v)) - 1
    return round(v / 10 ** e) * 10 ** e


# ----------------------------------------------------------------------------------------------------------------
# QGIS styles (QML) and OGC SLD, as text
# ----------------------------------------------------------------------------------------------------------------
def _rgba(hex_colour: str, alpha: int = 255) -> str:
    h = hex_colour.lstrip("#")
    return f"{int(h[0:2], 16)},{int(h[2:4], 16)},{int(h[4:6], 16)},{alpha}"


def _props(props: Mapping[str, Any]) -> str:
    # QGIS 3.22 writes both the <Option> map and the legacy <prop> list; later versions read either.
    opts = "".join(f'<Option type="QString" name={quoteattr(k)} value={quoteattr(str(v))}/>' for k, v in props.items())
    legacy = "".join(f"<prop k={quoteattr(k)} v={quoteattr(str(v))}/>" for k, v in props.items())
    return f'<Option type="Map">{opts}</Option>{legacy}'


def _symbol(kind: str, name: str, layers: str, alpha: float = 1.0) -> str:
    return (f'<symbol type="{kind}" name={quoteattr(name)} alpha="{alpha:g}" clip_to_extent="1" force_rhr="0">'
            f"{layers}</symbol>")


def _layer(cls: str, props: Mapping[str, Any], inner: str = "") -> str:
    return f'<layer class="{cls}" enabled="1" locked="0" pass="0">{_props(props)}{inner}</layer>'


def _arrow_symbol(name: str, colour: str, alpha: float = 1.0) -> str:
    """A line symbol drawn as a filled arrow (head in mm so that short vectors still show their direction)."""
    fill = _symbol("fill", "@" + name + "@0", _layer("SimpleFill", {
        "color": _rgba(colour), "style": "solid", "outline_color": "35,35,35,255", "outline_style": "solid",
        "outline_width": "0.1", "outline_width_unit": "MM", "joinstyle": "miter"}))
    return _symbol("line", name, _layer("ArrowLine", {
        "arrow_width": "0.6", "arrow_width_unit": "MM", "arrow_start_width": "0.6", "arrow_start_width_unit": "MM",
        "head_length": "2.2", "head_length_unit": "MM", "head_thickness": "1.5", "head_thickness_unit": "MM",
        "head_type": "0", "arrow_type": "0", "is_curved": "0", "is_repeated": "1", "offset": "0",
        "offset_unit": "MM", "ring_filter": "0"}, fill), alpha)


def _marker_symbol(name: str, shape: str, colour: str, size: float) -> str:
    return _symbol("marker", name, _layer("SimpleMarker", {
        "name": shape, "color": _rgba(colour), "outline_color": "0,0,0,255", "outline_style": "solid",
        "outline_width": "0.2", "outline_width_unit": "MM", "size": f"{size:g}", "size_unit": "MM", "angle": "0",
        "joinstyle": "bevel", "scale_method": "diameter", "vertical_anchor_point": "1",
        "horizontal_anchor_point": "1"}))


def _qml(renderer: str) -> str:
    return ("<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n"
            '<qgis version="3.22.0" styleCategories="Symbology">' + renderer + "</qgis>\n")


def _class_breaks(magnitudes: np.ndarray, n: int = len(_RAMP)) -> list:
    """Equal-interval class breaks 0 .. max, at two significant digits, last class open-ended."""
    m = magnitudes[np.isfinite(magnitudes)]
    top = float(m.max()) if m.size and m.max() > 0 else 1.0
    step = _nice(top / n)
    while step * n < top * 0.999:  # rounding down may leave the largest value out of the classes
        step = _nice(step * 1.05)
    return [i * step for i in range(n)] + [max(step * n, top) * 1e6]


def _vector_style(breaks, alpha: float = 1.0) -> Tuple[str, str]:
    """Graduated arrows on ``res_px`` (QML) and the equivalent SLD rules."""
    ranges, symbols, rules = [], [], []
    for i in range(len(breaks) - 1):
        lo, hi = breaks[i], breaks[i + 1]
        label = f"{lo:g} - {hi:g} px" if i < len(breaks) - 2 else f">= {lo:g} px"
        ranges.append(f'<range lower="{lo:.10g}" upper="{hi:.10g}" symbol="{i}" label={quoteattr(label)} '
                      'render="true"/>')
        symbols.append(_arrow_symbol(str(i), _RAMP[i], alpha))
        rules.append(
            f"<se:Rule><se:Name>{escape(label)}</se:Name><ogc:Filter><ogc:And>"
            f"<ogc:PropertyIsGreaterThanOrEqualTo><ogc:PropertyName>res_px</ogc:PropertyName>"
            f"<ogc:Literal>{lo:.10g}</ogc:Literal></ogc:PropertyIsGreaterThanOrEqualTo>"
            f"<ogc:PropertyIsLessThan><ogc:PropertyName>res_px</ogc:PropertyName>"
            f"<ogc:Literal>{hi:.10g}</ogc:Literal></ogc:PropertyIsLessThan></ogc:And></ogc:Filter>"
            f'<se:LineSymbolizer><se:Stroke><se:SvgParameter name="stroke">{_RAMP[i]}</se:SvgParameter>'
            f'<se:SvgParameter name="stroke-width">2</se:SvgParameter></se:Stroke></se:LineSymbolizer>'
            # SLD has no arrow line: mark the head (end point) with a triangle.
            f'<se:PointSymbolizer><se:Geometry><ogc:Function name="endPoint"><ogc:PropertyName>geom'
            f"</ogc:PropertyName></ogc:Function></se:Geometry><se:Graphic><se:Mark>"
            f"<se:WellKnownName>triangle</se:WellKnownName><se:Fill>"
            f'<se:SvgParameter name="fill">{_RAMP[i]}</se:SvgParameter></se:Fill></se:Mark>'
            f"<se:Size>8</se:Size></se:Graphic></se:PointSymbolizer></se:Rule>")
    qml = _qml('<renderer-v2 type="graduatedSymbol" attr="res_px" graduatedMethod="GraduatedColor" '
               'symbollevels="0" forceraster="0" enableorderby="0" referencescale="-1">'
               f"<ranges>{''.join(ranges)}</ranges><symbols>{''.join(symbols)}</symbols>"
               '<mode name="equal"/><rotation/><sizescale/></renderer-v2>')
    return qml, "".join(rules)


def _points_style() -> Tuple[str, str]:
    """Rule-based points: outliers (red cross) over control (blue triangle) and check (green circle) points."""
    # if() casts the boolean field (NULL counts as not an outlier); comparing a boolean with 0 does not.
    not_out = '(if("outlier", 1, 0) = 0)'
    rules = [
        (f"{not_out} AND \"role\" = 'control'", "control", "triangle", _ROLE_COLOURS["control"], 3.2),
        (f"{not_out} AND \"role\" = 'check'", "check", "circle", _ROLE_COLOURS["check"], 3.0),
        (f"{not_out} AND coalesce(\"role\", '') NOT IN ('control', 'check')", "other", "square", "#888888", 2.6),
        ('if("outlier", 1, 0) = 1', "outlier", "cross_fill", _OUTLIER_COLOUR, 3.6),
    ]
    qrules, symbols, sld = [], [], []
    for i, (flt, label, shape, colour, size) in enumerate(rules):
        qrules.append(f'<rule key="{{gf4cal-rule-{i}}}" symbol="{i}" label={quoteattr(label)} '
                      f'filter={quoteattr(flt)}/>')
        symbols.append(_marker_symbol(str(i), shape, colour, size))
    sld_filter = {
        "control": "<ogc:And><ogc:PropertyIsEqualTo><ogc:PropertyName>role</ogc:PropertyName><ogc:Literal>control"
                   "</ogc:Literal></ogc:PropertyIsEqualTo><ogc:Not><ogc:PropertyIsEqualTo><ogc:PropertyName>outlier"
                   "</ogc:PropertyName><ogc:Literal>1</ogc:Literal></ogc:PropertyIsEqualTo></ogc:Not></ogc:And>",
        "check": "<ogc:And><ogc:PropertyIsEqualTo><ogc:PropertyName>role</ogc:PropertyName><ogc:Literal>check"
                 "</ogc:Literal></ogc:PropertyIsEqualTo><ogc:Not><ogc:PropertyIsEqualTo><ogc:PropertyName>outlier"
                 "</ogc:PropertyName><ogc:Literal>1</ogc:Literal></ogc:PropertyIsEqualTo></ogc:Not></ogc:And>",
        "outlier": "<ogc:PropertyIsEqualTo><ogc:PropertyName>outlier</ogc:PropertyName><ogc:Literal>1</ogc:Literal>"
                   "</ogc:PropertyIsEqualTo>",
    }
    sld_shape = {"triangle": "triangle", "circle": "circle", "cross_fill": "cross"}
    for flt, label, shape, colour, size in rules:
        if label not in sld_filter:
            continue
        sld.append(f"<se:Rule><se:Name>{label}</se:Name><ogc:Filter>{sld_filter[label]}</ogc:Filter>"
                   f"<se:PointSymbolizer><se:Graphic><se:Mark><se:WellKnownName>{sld_shape[shape]}"
                   f'</se:WellKnownName><se:Fill><se:SvgParameter name="fill">{colour}</se:SvgParameter></se:Fill>'
                   f'<se:Stroke><se:SvgParameter name="stroke">#000000</se:SvgParameter></se:Stroke></se:Mark>'
                   f"<se:Size>{size * 3:.0f}</se:Size></se:Graphic></se:PointSymbolizer></se:Rule>")
    qml = _qml('<renderer-v2 type="RuleRenderer" symbollevels="0" forceraster="0" enableorderby="0" '
               f'referencescale="-1"><rules key="{{gf4cal-root}}">{"".join(qrules)}</rules>'
               f"<symbols>{''.join(symbols)}</symbols></renderer-v2>")
    return qml, "".join(sld)


def _footprint_style() -> Tuple[str, str]:
    fill = _symbol("fill", "0", _layer("SimpleFill", {
        "color": _rgba(_FOOTPRINT_COLOUR, 30), "style": "solid", "outline_color": _rgba(_FOOTPRINT_COLOUR),
        "outline_style": "dash", "outline_width": "0.5", "outline_width_unit": "MM", "joinstyle": "miter"}))
    qml = _qml('<renderer-v2 type="singleSymbol" symbollevels="0" forceraster="0" enableorderby="0" '
               f'referencescale="-1"><symbols>{fill}</symbols><rotation/><sizescale/></renderer-v2>')
    sld = (f"<se:Rule><se:Name>footprint</se:Name><se:PolygonSymbolizer><se:Fill>"
           f'<se:SvgParameter name="fill">{_FOOTPRINT_COLOUR}</se:SvgParameter>'
           f'<se:SvgParameter name="fill-opacity">0.12</se:SvgParameter></se:Fill><se:Stroke>'
           f'<se:SvgParameter name="stroke">{_FOOTPRINT_COLOUR}</se:SvgParameter>'
           f'<se:SvgParameter name="stroke-width">1</se:SvgParameter>'
           f'<se:SvgParameter name="stroke-dasharray">4 2</se:SvgParameter></se:Stroke>'
           f'</se:PolygonSymbolizer></se:Rule>')
    return qml, sld


def _sld(layer: str, rules: str) -> str:
    return ('<?xml version="1.0" encoding="UTF-8"?>\n'
            '<StyledLayerDescriptor xmlns="http://www.opengis.net/sld" xmlns:ogc="http://www.opengis.net/ogc" '
            'xmlns:se="http://www.opengis.net/se" xmlns:xlink="http://www.w3.org/1999/xlink" '
            'xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" version="1.1.0" '
            'xsi:schemaLocation="http://www.opengis.net/sld '
            'http://schemas.opengis.net/sld/1.1.0/StyledLayerDescriptor.xsd">'
            f"<NamedLayer><se:Name>{escape(layer)}</se:Name><UserStyle><se:Name>{escape(layer)}</se:Name>"
            f"<se:FeatureTypeStyle>{rules}</se:FeatureTypeStyle></UserStyle></NamedLayer></StyledLayerDescriptor>\n")


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


def _as_bool_array(values) -> np.ndarray:
    a = np.asarray(values)
    if a.dtype.kind == "b":
        return a
    if a.dtype.kind in "iuf":
        return np.nan_to_num(a.astype(float), nan=0.0) != 0
    return np.array([str(v).strip().lower() in ("1", "true", "yes", "t") for v in a], dtype=bool)


def _create_layer(ds, name, srs, geom_type, fields, description, metadata=None):
    from osgeo import ogr
    opts = [f"DESCRIPTION={description}"] if description else []
    layer = ds.CreateLayer(name, srs, geom_type, options=opts)
    if layer is None:
        raise Gf4calError(f"cannot create layer {name!r} in the GeoPackage")
    for fname, (ftype, subtype) in fields:
        fd = ogr.FieldDefn(fname, ftype)
        fd.SetSubType(subtype)
        layer.CreateField(fd)
    for k, v in (metadata or {}).items():
        layer.SetMetadataItem(k, str(v))
    return layer


def _set(feat, name, value, ftype):
    from osgeo import ogr
    if value is None or (isinstance(value, (float, np.floating)) and not math.isfinite(float(value))):
        feat.SetFieldNull(name)
    elif ftype == ogr.OFTReal:
        feat.SetField(name, float(value))
    elif ftype in (ogr.OFTInteger, ogr.OFTInteger64):
        feat.SetField(name, int(value))
    else:
        feat.SetField(name, str(value))


def _write_features(layer, fields, columns: Mapping[str, np.ndarray], geoms: Sequence) -> None:
    defn = layer.GetLayerDefn()
    from osgeo import ogr
    for i, g in enumerate(geoms):
        feat = ogr.Feature(defn)
        for fname, (ftype, _) in fields:
            _set(feat, fname, columns[fname][i], ftype)
        if g is not None:
            feat.SetGeometry(ogr.CreateGeometryFromWkb(g))
        if layer.CreateFeature(feat) != 0:
            raise Gf4calError(f"cannot write feature {i} of layer {layer.GetName()!r}")


def _write_layer_styles(ds, styles: Sequence[Tuple[str, str, str, str, str]]) -> None:
    """QGIS's ``layer_styles`` table (same fields, types and FID name as QGIS creates), one default per layer."""
    from osgeo import ogr
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
    now = _dt.datetime.now(_dt.timezone.utc)
    for table, geom_col, qml, sld, description in styles:
        f = ogr.Feature(layer.GetLayerDefn())
        f.SetField("f_table_catalog", "")
        f.SetField("f_table_schema", "")
        f.SetField("f_table_name", table)
        f.SetField("f_geometry_column", geom_col)
        f.SetField("styleName", table)
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
                         title: str = "GCP residuals") -> Path:
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
        Same for the *before* residuals, only when both before and after are given (its own factor).
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
        Factor applied to the residuals' ground size. Default: chosen per layer so that the longest vector of a
        point not flagged ``outlier`` is about 10 % of the extent of the GCPs (and footprint), rounded to two
        significant digits; then longer (blunder) arrows are shortened to 3x that length and flagged ``clipped``.
    before, after : (str, str) or None
        Names of the (sample, line) residual columns in ``gcps``, in pixels (``measured - predicted``). Missing
        columns are skipped; the output fields always have the standard names.
    crs : anything pyproj accepts
        CRS of the output layers (default EPSG:4326).
    pixel_size : float or (float, float), optional
        Ground size of a pixel in map units, used only when it cannot be estimated from the GCPs (< 3 points).
    overwrite : bool
        Replace an existing file (default True).

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
    if path.exists() and not overwrite:
        from .errors import InputOverwriteError
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

    # residual vectors, one layer per epoch
    vector_layers = []
    epochs = [e for e in ("after", "before") if res[e] is not None]
    for k, epoch in enumerate(epochs):
        s_, l_ = res[epoch]
        dx, dy = s_ * ps, -l_ * pl  # sample -> east, line -> south (image rows go down)
        length = np.hypot(dx, dy)
        mag = np.hypot(s_, l_)
        finite = np.isfinite(length) & np.isfinite(x) & np.isfinite(y)
        # Scale and classes follow the ordinary points: one blunder must not shrink every other arrow to nothing.
        regular = finite & ~outlier if (finite & ~outlier).any() else finite
        longest = float(length[regular].max()) if regular.any() else 0.0
        clip_at = np.inf
        if exaggeration is not None:
            factor = float(exaggeration)
        else:
            factor = _nice(0.1 * extent / longest) if longest > 0 else 1.0
            clip_at = 3.0 * longest * factor  # auto mode: blunders drawn at most 3x the longest regular arrow
        name = "residual_vectors" if k == 0 else "residual_vectors_before"
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

    if path.exists() and not overwrite:  # pragma: no cover - checked above; re-checked for races
        raise Gf4calError(f"{path} exists")
    tmp = _temp_path(path)
    driver = ogr.GetDriverByName("GPKG")
    try:
        ds = driver.CreateDataSource(str(tmp))
        if ds is None:
            raise Gf4calError(f"cannot create a GeoPackage in {path.parent}; check the folder is writable")
        styles = []
        ds.StartTransaction()
        gl = _create_layer(ds, "gcps", srs, ogr.wkbPoint, fields,
                           f"{title}: ground control / check points with residuals (measured - predicted, px)")
        _write_features(gl, fields, columns, [point_wkb(i) for i in range(n)])
        qml, sld = _points_style()
        styles.append(("gcps", gl.GetGeometryColumn(), qml, _sld("gcps", sld), "GCPs by role; outliers as red crosses"))
        for name, vfields, cols, geoms, desc, meta, mag in vector_layers:
            vl = _create_layer(ds, name, srs, ogr.wkbLineString, vfields, desc, meta)
            _write_features(vl, vfields, cols, geoms)
            # The 'before' arrows are drawn half-transparent so the 'after' ones stand out where both are shown.
            qml, sld = _vector_style(_class_breaks(mag), 1.0 if name == "residual_vectors" else 0.5)
            styles.append((name, vl.GetGeometryColumn(), qml, _sld(name, sld),
                           f"residual arrows coloured by magnitude; {desc}"))
        if fp is not None and not fp.is_empty:
            fl = _create_layer(ds, "footprint", srs, ogr.wkbMultiPolygon, [("name", (ogr.OFTString, ogr.OFSTNone))],
                               f"{title}: scene footprint")
            g = ogr.ForceToMultiPolygon(ogr.CreateGeometryFromWkb(fp.wkb))
            _write_features(fl, [("name", (ogr.OFTString, ogr.OFSTNone))], {"name": ["footprint"]}, [g.ExportToWkb()])
            qml, sld = _footprint_style()
            styles.append(("footprint", fl.GetGeometryColumn(), qml, _sld("footprint", sld), "scene footprint"))
        _write_layer_styles(ds, styles)
        ds.CommitTransaction()
        ds = None
        os.replace(tmp, path)
    finally:
        ds = None
        _cleanup(tmp)
    return path


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


# ----------------------------------------------------------------------------------------------------------------
# plot
# ----------------------------------------------------------------------------------------------------------------
def _nice_scale(v: float) -> float:
    """1, 2 or 5 x 10^k, not above v (the scale arrow's length in px)."""
    if not math.isfinite(v) or v <= 0:
        return 1.0
    e = 10 ** math.floor(math.log10(v))
    for m in (5, 2, 1):
        if m * e <= v:
            return m * e
    return e


def plot_residuals(gcps, path: PathLike, *, before: Optional[Tuple[str, str]] = STANDARD_BEFORE,
                   after: Optional[Tuple[str, str]] = STANDARD_AFTER, image_size: Optional[Tuple[int, int]] = None,
                   title: str = "GCP residuals", dpi: int = 110) -> Path:
    """Residual vectors in image space, before and after, side by side (a PNG, written atomically).

    Each panel draws every GCP's residual ``(res_sample, res_line)`` (measured - predicted, px) as an arrow at its
    image position (line axis pointing down, like the image), control and check points in different colours and
    outliers circled, with a scale arrow and the per-axis RMS in the panel title. Each panel has its own
    exaggeration so both patterns are readable (like Fig. 5 of seed 000); the scale arrow gives it.

    Parameters
    ----------
    gcps : DataFrame
        With ``sample``, ``line`` (GDAL convention), the residual columns, optionally ``role`` and ``outlier``.
    path : path-like
        Output ``.png``.
    before, after : (str, str) or None
        (sample, line) residual columns; missing ones give no panel. At least one must exist.
    image_size : (width, height), optional
        Sets the axes to the whole image; default: the GCPs' extent.
    """
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    import pandas as pd

    path = Path(path)
    df = gcps if isinstance(gcps, pd.DataFrame) else pd.DataFrame(gcps)
    panels = [(lab, _residual_pair(df, names)) for lab, names in (("before", before), ("after", after))]
    panels = [(lab, r) for lab, r in panels if r is not None]
    if not panels:
        raise GCPError("no residual columns to plot; compute residuals first (res_sample_*/res_line_* columns)")
    for col in ("sample", "line"):
        if col not in df.columns:
            raise GCPError(f"the GCP table has no {col!r} column")
    s, l = _column(df, "sample"), _column(df, "line")
    role = df["role"].astype(str).to_numpy() if "role" in df.columns else np.full(len(df), "control", object)
    outlier = _as_bool_array(df["outlier"]) if "outlier" in df.columns else np.zeros(len(df), bool)
    if image_size is not None:
        xlim, ylim = (0, float(image_size[0])), (float(image_size[1]), 0)
    else:
        pad = 0.05 * max(np.nanmax(s) - np.nanmin(s), np.nanmax(l) - np.nanmin(l), 1.0)
        xlim, ylim = (np.nanmin(s) - pad, np.nanmax(s) + pad), (np.nanmax(l) + pad, np.nanmin(l) - pad)
    span = max(abs(xlim[1] - xlim[0]), abs(ylim[1] - ylim[0]))

    fig = Figure(figsize=(5.2 * len(panels), 5.6), dpi=dpi)
    FigureCanvasAgg(fig)
    fig.suptitle(title)
    with matplotlib.rc_context({"font.size": 9}):
        for k, (label, (rs, rl)) in enumerate(panels):
            ax = fig.add_subplot(1, len(panels), k + 1)
            mag = np.hypot(rs, rl)
            finite = np.isfinite(mag) & np.isfinite(s) & np.isfinite(l)
            longest = float(np.nanmax(mag[finite])) if finite.any() else 0.0
            # Data units per px of residual: the longest arrow spans ~8 % of the image.
            factor = 0.08 * span / longest if longest > 0 else 1.0
            for r, colour in (("control", _ROLE_COLOURS["control"]), ("check", _ROLE_COLOURS["check"])):
                m = finite & (role == r)
                if m.any():
                    # y axis is inverted (line down): +res_line draws downwards, like the image.
                    ax.quiver(s[m], l[m], rs[m], rl[m], color=colour, angles="xy", scale_units="xy",
                              scale=1.0 / factor, width=0.004, label=f"{r} ({int(m.sum())})")
            m = finite & ~np.isin(role, ["control", "check"])
            if m.any():
                ax.quiver(s[m], l[m], rs[m], rl[m], color="#888888", angles="xy", scale_units="xy",
                          scale=1.0 / factor, width=0.004, label=f"other ({int(m.sum())})")
            if (outlier & finite).any():
                ax.scatter(s[outlier & finite], l[outlier & finite], s=60, facecolors="none",
                           edgecolors=_OUTLIER_COLOUR, linewidths=1.2,
                           label=f"outlier ({int((outlier & finite).sum())})")
            ref = _nice_scale(longest) if longest > 0 else 1.0
            # Scale arrow in the lower-left corner.
            x0 = xlim[0] + 0.05 * (xlim[1] - xlim[0])
            y0 = ylim[0] - 0.05 * (ylim[0] - ylim[1])
            ax.quiver([x0], [y0], [ref], [0.0], color="black", angles="xy", scale_units="xy", scale=1.0 / factor,
                      width=0.006)
            ax.annotate(f"{ref:g} px", (x0, y0), xytext=(0, 6), textcoords="offset points", fontsize=8)
            use = finite & ~outlier
            rms_s = float(np.sqrt(np.mean(rs[use] ** 2))) if use.any() else float("nan")
            rms_l = float(np.sqrt(np.mean(rl[use] ** 2))) if use.any() else float("nan")
            ax.set_title(f"{label}: RMS sample {rms_s:.3g} px, line {rms_l:.3g} px", fontsize=9)
            ax.set_xlim(*xlim)
            ax.set_ylim(*ylim)
            ax.set_aspect("equal")
            ax.set_xlabel("sample (px)")
            ax.set_ylabel("line (px)")
            ax.legend(loc="upper right", fontsize=7)
        fig.tight_layout()
    tmp = _temp_path(path)
    try:
        fig.savefig(str(tmp), format="png")
        os.replace(tmp, path)
    finally:
        _cleanup(tmp)
    return path
