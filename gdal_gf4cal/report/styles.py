"""QGIS styles (QML) and OGC SLD as text for the residual GeoPackage's layers (never imports qgis)."""
from __future__ import annotations

from typing import Any, Mapping, Tuple
from xml.sax.saxutils import escape, quoteattr

import numpy as np

from ._common import _RAMP, _ROLE_COLOURS, _OUTLIER_COLOUR, _FOOTPRINT_COLOUR, _nice


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


def _qml(renderer: str, label_field: str = "") -> str:
    """A QML document with ``renderer``; with ``label_field`` also labels with that field (the GCP ids)."""
    if not label_field:
        return ("<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n"
                '<qgis version="3.22.0" styleCategories="Symbology">' + renderer + "</qgis>\n")
    labeling = (f'<labeling type="simple"><settings calloutType="simple"><text-style fieldName={quoteattr(label_field)} '
                'isExpression="0" fontSize="8" fontSizeUnit="Point" textColor="0,0,0,255" textOpacity="1">'
                '<text-buffer bufferDraw="1" bufferSize="0.8" bufferSizeUnits="MM" bufferColor="255,255,255,255" '
                'bufferOpacity="1"/></text-style><placement placement="0" dist="1.5" distUnits="MM" '
                'offsetType="0"/><rendering drawLabels="1" obstacle="1"/></settings></labeling>')
    return ("<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n"
            '<qgis version="3.22.0" styleCategories="Symbology|Labeling" labelsEnabled="1">' + renderer + labeling +
            "</qgis>\n")


def _class_breaks(magnitudes: np.ndarray, n: int = len(_RAMP)) -> list:
    """Equal-interval class breaks 0 .. max, at two significant digits, last class open-ended."""
    m = magnitudes[np.isfinite(magnitudes)]
    top = float(m.max()) if m.size and m.max() > 0 else 1.0
    step = _nice(top / n)
    while step * n < top * 0.999:  # rounding down may leave the largest value out of the classes
        nxt = _nice(step * 1.05)
        step = nxt if nxt > step else _nice(step * 1.2)   # 1.05 x 1.0 rounds back to 1.0 (round half to even)
    return [i * step for i in range(n)] + [max(step * n, top) * 1e6]


def _graduated_range(breaks, i: int):
    """Class ``i`` of graduated ``breaks`` (px): ``(lower, upper, label, QML <range>)``; the last class is open."""
    lo, hi = breaks[i], breaks[i + 1]
    label = f"{lo:g} - {hi:g} px" if i < len(breaks) - 2 else f">= {lo:g} px"
    return lo, hi, label, (f'<range lower="{lo:.10g}" upper="{hi:.10g}" symbol="{i}" label={quoteattr(label)} '
                           'render="true"/>')

def _vector_style(breaks, alpha: float = 1.0) -> Tuple[str, str]:
    """Graduated arrows on ``res_px`` (QML) and the equivalent SLD rules."""
    ranges, symbols, rules = [], [], []
    for i in range(len(breaks) - 1):
        lo, hi, label, xml = _graduated_range(breaks, i)
        ranges.append(xml)
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
               f"<symbols>{''.join(symbols)}</symbols></renderer-v2>", label_field="id")
    return qml, "".join(sld)


def seams_ground_scale(columns: Mapping[str, Any], lon, lat) -> Tuple[float, float]:
    """(ground metres per pixel, median metres between neighbouring tie points) of a seams layer, from its points:
    along each pair's seam (``pair``), the ground distance between consecutive points (sorted by ``line_b``) over
    their line difference. NaN when no pair has two points on different lines."""
    from ..geodesy import metres_per_degree
    lon, lat = np.asarray(lon, float), np.asarray(lat, float)
    pair = np.asarray(columns["pair"]).astype(str)
    line = np.asarray(columns["line_b"], float)
    order = np.lexsort((line, pair))
    p, ln, x, y = pair[order], line[order], lon[order], lat[order]
    same = (p[1:] == p[:-1]) & (np.abs(np.diff(ln)) > 0.5)
    mx, my = metres_per_degree(0.5 * (y[1:] + y[:-1]))
    step = np.hypot(np.diff(x) * mx, np.diff(y) * my)
    if not np.any(same):
        return float("nan"), float("nan")
    return (float(np.median(step[same] / np.abs(np.diff(ln))[same])), float(np.median(step[same])))


def seams_style(columns: Mapping[str, Any], lon, lat) -> Tuple[str, str, str, float]:
    """QGIS style of block calibration's ``seams`` point layer (one feature per overlap tie point, fields ``pair,
    line_b, ds_after, dl_after, offset_px_after, ...``): graduated by ``offset_px_after`` (the seam offset left
    after calibration, px), each tie point a dot with an arrow of its after-offset (sample -> east, line -> south,
    as the residual layers) drawn on the ground with ONE exaggeration, chosen so the longest regular arrow is about
    1.5 times the spacing of the tie points. Returns ``(qml, sld, title, factor)``; the title states the factor as
    the residual layers' titles do (``"seams after (x2500)"``); without a ground scale (a single point per pair) the
    factor is metres drawn per pixel of offset (``"seams after (1 px = 50 m)"``)."""
    from ..geodesy import metres_per_degree
    mag = np.asarray(columns["offset_px_after"], float)
    gsd, spacing = seams_ground_scale(columns, lon, lat)
    finite = mag[np.isfinite(mag)]
    longest = float(np.percentile(finite, 99)) if finite.size else 0.0
    if not (np.isfinite(spacing) and spacing > 0):
        w, so, e, n = np.nanmin(lon), np.nanmin(lat), np.nanmax(lon), np.nanmax(lat)
        mx, my = metres_per_degree(0.5 * (so + n))
        spacing = 0.05 * max(float(np.hypot((e - w) * mx, (n - so) * my)), 1.0)
    metres_per_px = _nice(1.5 * spacing / longest) if longest > 0 else _nice(spacing)
    if np.isfinite(gsd) and gsd > 0:
        factor = _nice(metres_per_px / gsd)
        metres_per_px, title = factor * gsd, f"seams after (x{factor:g})"
    else:
        factor, title = metres_per_px, f"seams after (1 px = {metres_per_px:g} m)"
    mpd_lat = float(metres_per_degree(float(np.nanmean(lat)))[1])
    k = metres_per_px / mpd_lat          # degrees of latitude per pixel of offset (longitude: / cos(lat))
    expr = (f'make_line($geometry, make_point($x + "ds_after" * {k:.10g} / cos(radians($y)), '
            f'$y - "dl_after" * {k:.10g}))')
    breaks = _class_breaks(mag)
    ranges, symbols, rules = [], [], []
    for i in range(len(breaks) - 1):
        lo, hi, label, xml = _graduated_range(breaks, i)
        ranges.append(xml)
        arrow = _layer("GeometryGenerator", {"SymbolType": "Line", "geometryModifier": expr, "units": "MapUnit"},
                       _arrow_symbol(f"@{i}@0", _RAMP[i]))
        dot = _marker_symbol(str(i), "circle", _RAMP[i], 1.6)
        symbols.append(dot.replace('<layer class="SimpleMarker"', arrow + '<layer class="SimpleMarker"', 1))
        rules.append(
            f"<se:Rule><se:Name>{escape(label)}</se:Name><ogc:Filter><ogc:And>"
            f"<ogc:PropertyIsGreaterThanOrEqualTo><ogc:PropertyName>offset_px_after</ogc:PropertyName>"
            f"<ogc:Literal>{lo:.10g}</ogc:Literal></ogc:PropertyIsGreaterThanOrEqualTo>"
            f"<ogc:PropertyIsLessThan><ogc:PropertyName>offset_px_after</ogc:PropertyName>"
            f"<ogc:Literal>{hi:.10g}</ogc:Literal></ogc:PropertyIsLessThan></ogc:And></ogc:Filter>"
            f"<se:PointSymbolizer><se:Graphic><se:Mark><se:WellKnownName>circle</se:WellKnownName><se:Fill>"
            f'<se:SvgParameter name="fill">{_RAMP[i]}</se:SvgParameter></se:Fill></se:Mark>'
            f"<se:Size>6</se:Size></se:Graphic></se:PointSymbolizer></se:Rule>")
    qml = _qml('<renderer-v2 type="graduatedSymbol" attr="offset_px_after" graduatedMethod="GraduatedColor" '
               'symbollevels="0" forceraster="0" enableorderby="0" referencescale="-1">'
               f"<ranges>{''.join(ranges)}</ranges><symbols>{''.join(symbols)}</symbols>"
               '<mode name="equal"/><rotation/><sizescale/></renderer-v2>')
    return qml, "".join(rules), title, factor


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


def diverging_raster_qml(band: int, limit: float, *, low: str = "#2166ac", mid: str = "#f7f7f7",
                         high: str = "#b2182b") -> str:
    """QML of a single-band pseudocolour style of ``band``: a diverging ramp blue - white - red from ``-limit`` to
    ``+limit`` (a signed correction component: zero white, the sign by hue)."""
    lim = float(limit) if np.isfinite(limit) and limit > 0 else 1.0
    items = "".join(f'<item alpha="255" value="{v:.6g}" label="{v:.3g}" color="{c}"/>'
                    for v, c in ((-lim, low), (0.0, mid), (lim, high)))
    shader = (f'<colorrampshader colorRampType="INTERPOLATED" classificationMode="1" clip="0" '
              f'minimumValue="{-lim:.6g}" maximumValue="{lim:.6g}">{items}</colorrampshader>')
    return ("<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n"
            '<qgis version="3.22.0" styleCategories="Symbology"><pipe>'
            f'<rasterrenderer type="singlebandpseudocolor" band="{int(band)}" opacity="1" alphaBand="-1" '
            f'classificationMin="{-lim:.6g}" classificationMax="{lim:.6g}"><rastershader>{shader}</rastershader>'
            "</rasterrenderer></pipe></qgis>\n")
