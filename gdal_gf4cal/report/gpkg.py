"""The residual GeoPackage (GCP points, residual arrows, footprint, default styles); OGR return codes checked."""
from __future__ import annotations

import datetime as _dt
import math
import os
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Sequence, Tuple

import numpy as np

from .._gdal import with_quiet_errors
from ..errors import CancelledError, GCPError, Gf4calError
from ._common import _as_bool_array, STANDARD_BEFORE, STANDARD_AFTER, PathLike, _temp_path, _cleanup, _column, _lonlat, _residual_pair, _transformer, _pixel_size, _nice
from .styles import _class_breaks, _vector_style, _points_style, _footprint_style, _sld, seams_style


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



def _create_layer(ds, name, srs, geom_type, fields, description, metadata=None, identifier=None):
    from osgeo import ogr
    opts = [f"DESCRIPTION={description}"] if description else []
    if identifier:
        opts.append(f"IDENTIFIER={identifier}")   # gpkg_contents.identifier: the layer's human-readable title
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


# ----------------------------------------------------------------------------------------------------------------
# bulk writing: OGR creates the layers (fields, SRS, metadata, styles), the rows go in through SQLite in chunks
# (executemany of GeoPackage geometry blobs built with NumPy), then OGR builds the spatial indexes and the file is
# re-opened and counted. 1e6 GCPs: seconds, where one OGR feature at a time took minutes.
# ----------------------------------------------------------------------------------------------------------------
_CHUNK = 20_000     # rows per executemany: bounds the Python objects alive at once and the cancel latency


def _point_records(x, y, srs_id: int):
    """GeoPackage point blobs as one NumPy record array (header without envelope, as GDAL writes points, + WKB
    little endian)."""
    dt = np.dtype([("magic", "S2"), ("version", "u1"), ("flags", "u1"), ("srs", "<i4"), ("bo", "u1"),
                   ("type", "<u4"), ("x", "<f8"), ("y", "<f8")])
    rec = np.zeros(x.size, dt)
    rec["magic"], rec["flags"], rec["srs"], rec["bo"], rec["type"] = b"GP", 0x01, srs_id, 1, 1
    rec["x"], rec["y"] = x, y
    return rec, np.isfinite(x) & np.isfinite(y)


def _line_records(x0, y0, x1, y1, srs_id: int):
    """GeoPackage blobs of 2-point line strings (header with the [minx, maxx, miny, maxy] envelope + WKB)."""
    dt = np.dtype([("magic", "S2"), ("version", "u1"), ("flags", "u1"), ("srs", "<i4"), ("minx", "<f8"),
                   ("maxx", "<f8"), ("miny", "<f8"), ("maxy", "<f8"), ("bo", "u1"), ("type", "<u4"),
                   ("npts", "<u4"), ("x0", "<f8"), ("y0", "<f8"), ("x1", "<f8"), ("y1", "<f8")])
    rec = np.zeros(x0.size, dt)
    rec["magic"], rec["flags"], rec["srs"], rec["bo"], rec["type"], rec["npts"] = b"GP", 0x03, srs_id, 1, 2, 2
    rec["minx"], rec["maxx"] = np.minimum(x0, x1), np.maximum(x0, x1)
    rec["miny"], rec["maxy"] = np.minimum(y0, y1), np.maximum(y0, y1)
    rec["x0"], rec["y0"], rec["x1"], rec["y1"] = x0, y0, x1, y1
    return rec, np.isfinite(x0) & np.isfinite(y0) & np.isfinite(x1) & np.isfinite(y1)


def _wkb_records(wkb: bytes, bounds, srs_id: int):
    """One geometry (any type, its WKB) as a GeoPackage blob record with its envelope."""
    import struct
    blob = struct.pack("<2sBBi4d", b"GP", 0, 0x03, srs_id, bounds[0], bounds[2], bounds[1], bounds[3]) + wkb
    rec = np.frombuffer(blob, dtype=np.dtype((np.void, len(blob))))
    return rec, np.ones(1, bool)


def _sql_values(values, ftype) -> list:
    """A column chunk as Python values SQLite binds, ``None`` where null (NaN, inf, None)."""
    from osgeo import ogr
    a = np.asarray(values)
    if ftype == ogr.OFTReal and a.dtype.kind in "biuf":      # SQLite binds NaN as NULL; infinities made NaN
        f = a.astype(float)
        f[np.isinf(f)] = np.nan
        return f.tolist()
    if ftype == ogr.OFTReal or (ftype in (ogr.OFTInteger, ogr.OFTInteger64) and a.dtype.kind in "fO"):
        f = np.asarray(a, dtype=float) if a.dtype.kind != "O" else np.array(
            [np.nan if v is None else v for v in a], dtype=float)
        out = (f if ftype == ogr.OFTReal else np.trunc(f)).astype(object)
        if ftype != ogr.OFTReal:
            out[np.isfinite(f)] = f[np.isfinite(f)].astype(np.int64).astype(object)
        out[~np.isfinite(f)] = None
        return out.tolist()
    if ftype in (ogr.OFTInteger, ogr.OFTInteger64):
        return a.astype(np.int64).tolist()
    import pandas as pd
    ser = pd.Series(a, dtype=object)
    out = ser.astype(str).to_numpy(dtype=object)
    out[ser.isna().to_numpy()] = None
    return out.tolist()


_MAX_VARS = 999     # host parameters per statement: SQLite's historical minimum (3.32+ allow 32,766)


def _insert_many(conn, head: str, cols: Sequence[list], m: int) -> None:
    """``head`` (``INSERT INTO "t" ("a", "b")``) with ``m`` rows given column-wise (``cols``: one list of ``m``
    values per column), many rows per statement (multi-row ``VALUES``): sqlite3's ``executemany`` costs ~1.5 us a
    statement, and a table with AUTOINCREMENT (OGR's fid) another ~1 us for the sequence bookkeeping, so one row
    per statement took half the time of a residual GeoPackage. Rows go in in order (same fids)."""
    k = len(cols)
    per = max(1, min(256, _MAX_VARS // k))
    row = "(" + ", ".join("?" * k) + ")"
    full = m // per * per
    if full:
        flat = [None] * (full * k)
        for j, col in enumerate(cols):
            flat[j::k] = col[:full]
        it = iter(flat)
        conn.executemany(f"{head} VALUES {', '.join([row] * per)}", zip(*[it] * (per * k)))
        del flat, it
    if full < m:
        flat = [None] * ((m - full) * k)
        for j, col in enumerate(cols):
            flat[j::k] = col[full:m]
        conn.execute(f"{head} VALUES {', '.join([row] * (m - full))}", flat)


def _insert_rows(conn, table: str, geom_col: str, records, ok, fields, columns, cancelled) -> None:
    """Insert every row of one layer: geometry blobs (``records``, null where not ``ok``) and typed fields."""
    names = [geom_col] + [f for f, _ in fields]
    head = f'INSERT INTO "{table}" ({", ".join(chr(34) + n + chr(34) for n in names)})'
    size = records.dtype.itemsize
    n = records.size
    for start in range(0, n, _CHUNK):
        stop = min(n, start + _CHUNK)
        # bytearray, not bytes: sqlite3 binds bytearray directly where bytes go through its adapter lookup
        # (~0.7 us a row); void keeps trailing zeros
        blobs = list(map(bytearray, records[start:stop].view(f"V{size}").tolist()))
        for i in np.flatnonzero(~ok[start:stop]):
            blobs[i] = None
        cols = [blobs] + [[_sql_values(np.asarray([columns[f]]), ftype)[0]] * (stop - start)
                          if np.ndim(columns[f]) == 0 else _sql_values(np.asarray(columns[f])[start:stop], ftype)
                          for f, (ftype, _) in fields]
        _insert_many(conn, head, cols, stop - start)
        if cancelled is not None and cancelled():
            raise CancelledError("cancelled while writing the residual GeoPackage; nothing was kept")
    conn.execute("UPDATE gpkg_ogr_contents SET feature_count = ? WHERE lower(table_name) = lower(?)", (n, table))


def _extent(boxes):
    """(minx, miny, maxx, maxy) of a layer's geometry boxes (:func:`_boxes`), None when it has none."""
    if not len(boxes):
        return None
    return float(boxes[:, 0].min()), float(boxes[:, 2].min()), float(boxes[:, 1].max()), float(boxes[:, 3].max())


def _srs_ids(path: Path, tables) -> dict:
    """The ``srs_id`` OGR registered for each layer (gpkg_geometry_columns)."""
    import sqlite3
    conn = sqlite3.connect(str(path))
    try:
        got = dict(conn.execute("SELECT table_name, srs_id FROM gpkg_geometry_columns"))
    finally:
        conn.close()
    return {t: int(got[t]) for t in tables}


def _rtree_cells(boxes: np.ndarray) -> np.ndarray:
    """(n, 4) [minx, maxx, miny, maxy] as the float32 an SQLite R-tree stores, rounded outwards (as SQLite does)."""
    f = boxes.astype(np.float32)
    lo, hi = f[:, [0, 2]], f[:, [1, 3]]
    f[:, [0, 2]] = np.where(lo > boxes[:, [0, 2]], np.nextafter(lo, np.float32(-np.inf)), lo)
    f[:, [1, 3]] = np.where(hi < boxes[:, [1, 3]], np.nextafter(hi, np.float32(np.inf)), hi)
    return f


def _str_pack(boxes: np.ndarray, cap: int):
    """Sort-Tile-Recursive packing of one level: entry order, node of each (ordered) entry, node boxes."""
    n = len(boxes)
    n_nodes = -(-n // cap)
    slab = int(np.ceil(np.sqrt(n_nodes))) * cap
    cx, cy = boxes[:, 0] * 0.5 + boxes[:, 1] * 0.5, boxes[:, 2] * 0.5 + boxes[:, 3] * 0.5
    rank = np.empty(n, np.int64)
    rank[np.argsort(cx, kind="stable")] = np.arange(n)
    order = np.lexsort((cy, rank // slab))
    b = boxes[order]
    starts = np.arange(0, n, cap)
    nb = np.column_stack([np.minimum.reduceat(b[:, 0], starts), np.maximum.reduceat(b[:, 1], starts),
                          np.minimum.reduceat(b[:, 2], starts), np.maximum.reduceat(b[:, 3], starts)])
    return order, np.arange(n) // cap, nb


def _node_blobs(keys, boxes, node_of, n_nodes: int, node_size: int, cap: int, depth: int = 0) -> list:
    """The R-tree node blobs of one level: 2 bytes depth (root only), 2 bytes count, then per cell a 64-bit id and
    four float32, all big-endian, zero-padded to the node size (SQLite's rtree.c format)."""
    out = np.zeros((n_nodes, node_size), np.uint8)
    counts = np.bincount(node_of, minlength=n_nodes)
    out[:, 0:2] = np.frombuffer(np.array([depth], ">u2").tobytes(), np.uint8)
    out[:, 2:4] = np.frombuffer(counts.astype(">u2").tobytes(), np.uint8).reshape(n_nodes, 2)
    cells = np.zeros(len(keys), np.dtype([("id", ">i8"), ("box", ">f4", (4,))]))
    cells["id"], cells["box"] = keys, boxes
    slot = np.arange(len(keys)) - np.concatenate([[0], np.cumsum(counts)[:-1]])[node_of]
    view = out[:, 4:4 + cap * 24].reshape(n_nodes, cap, 24)
    view[node_of, slot] = cells.view(np.uint8).reshape(len(keys), 24)
    return [row.tobytes() for row in out]


def _rtree_bulk_load(conn, name: str, fids: np.ndarray, boxes: np.ndarray) -> None:
    """Fill the (empty) GeoPackage R-tree ``name`` in one go: STR-packed nodes written into its node, rowid and
    parent tables, where one INSERT per feature (OGR's triggers, or SQLite's own R*-tree insertion) costs
    tens of microseconds each. ``boxes`` = (n, 4) [minx, maxx, miny, maxy] of the features ``fids``."""
    if len(fids) == 0:
        return
    node_size = len(conn.execute(f'SELECT data FROM "{name}_node" WHERE nodeno = 1').fetchone()[0])
    cap = (node_size - 4) // 24
    boxes = _rtree_cells(boxes)
    keys = np.asarray(fids, np.int64)
    levels = []                       # bottom-up: (entry keys, entry boxes, node of each entry, number of nodes)
    leaf_order = None
    while len(keys) > cap:
        order, node_of, nb = _str_pack(boxes, cap)      # float32 boxes: exact min/max, ordering only approximate
        leaf_order = order if leaf_order is None else leaf_order
        levels.append((keys[order], boxes[order], node_of, len(nb)))
        keys, boxes = np.arange(len(nb), dtype=np.int64), nb   # next level: child indices
    # node numbers: the root is 1, then the levels from the top down
    base, nxt = [0] * len(levels), 2
    for k in range(len(levels) - 1, -1, -1):
        base[k], nxt = nxt, nxt + levels[k][3]
    nodes, parents = [], []
    for k, (lkeys, lboxes, node_of, n_nodes) in enumerate(levels):
        ids = lkeys if k == 0 else lkeys + base[k - 1]          # leaves hold fids; others their children's numbers
        nodes += zip(range(base[k], base[k] + n_nodes), _node_blobs(ids, lboxes, node_of, n_nodes, node_size, cap))
        if k > 0:
            parents += zip(ids.tolist(), (base[k] + node_of).tolist())
    root_ids = keys if not levels else keys + base[-1]
    nodes.append((1, _node_blobs(root_ids, boxes, np.zeros(len(keys), np.int64), 1, node_size, cap,
                                 depth=len(levels))[0]))
    fids = np.asarray(fids, np.int64)
    leaf_of = np.ones(len(fids), np.int64)           # the leaf node of each feature, in fid order
    if levels:
        parents += zip(root_ids.tolist(), [1] * len(root_ids))
        leaf_of[leaf_order] = base[0] + levels[0][2]
    for table in ("node", "rowid", "parent"):
        conn.execute(f'DELETE FROM "{name}_{table}"')
    conn.executemany(f'INSERT INTO "{name}_node"(nodeno, data) VALUES (?, ?)', nodes)
    conn.executemany(f'INSERT INTO "{name}_parent"(nodeno, parentnode) VALUES (?, ?)', parents)
    for start in range(0, len(fids), 5 * _CHUNK):     # appended in rowid order (no page splits), chunk by chunk
        stop = min(len(fids), start + 5 * _CHUNK)
        _insert_many(conn, f'INSERT INTO "{name}_rowid"(rowid, nodeno)',
                     [fids[start:stop].tolist(), leaf_of[start:stop].tolist()], stop - start)


def _boxes(records, ok) -> np.ndarray:
    """(n, 4) [minx, maxx, miny, maxy] of the geometry records ``ok``."""
    names = records.dtype.names
    if names:       # field by field: no copy of the whole records (77 bytes a line) at 1e6 rows
        out = np.empty((int(np.count_nonzero(ok)), 4))
        for j, f in enumerate(("minx", "maxx", "miny", "maxy") if "minx" in names else ("x", "x", "y", "y")):
            out[:, j] = records[f][ok]
        return out
    import struct   # one opaque blob (the footprint): its header envelope
    return np.array([struct.unpack_from("<4d", bytes(rec), 8) for rec in records[ok]], float).reshape(-1, 4)


def _bulk_write(path: Path, layers, cancelled) -> None:
    """Fill the layers OGR created in ``path``: ``layers`` = [(table, fields, make)], ``make()`` giving the geometry
    ``(records, ok)`` and the ``columns`` when the layer is written (one layer's data in memory at a time). One
    SQLite transaction (all or nothing): OGR's R-tree insert trigger (it calls OGR's SQL functions) is set aside,
    the rows go in, the R-tree is bulk-loaded and the trigger restored; then OGR re-opens the file and counts."""
    import sqlite3
    from osgeo import gdal
    from .._gdal import gdal_exceptions, first_line
    try:
        conn = sqlite3.connect(str(path), isolation_level=None)
        try:
            conn.execute("PRAGMA journal_mode = OFF")      # a temporary file: on failure it is removed whole
            conn.execute("PRAGMA synchronous = OFF")
            conn.execute("PRAGMA cache_size = -65536")         # 64 MB of page cache
            conn.execute("BEGIN")
            geom_cols = dict(conn.execute("SELECT table_name, column_name FROM gpkg_geometry_columns"))
            counts = {}
            for table, fields, make in layers:
                records, ok, columns = make()
                counts[table] = records.size
                rtree = f"rtree_{table}_{geom_cols[table]}"
                # OGR's insert triggers (R-tree, feature count) run per row and call OGR's SQL functions: set
                # aside, replaced by the bulk R-tree load and the count, then restored as OGR wrote them.
                triggers = conn.execute("SELECT name, sql FROM sqlite_master WHERE type = 'trigger' AND "
                                        "tbl_name = ? AND name IN (?, ?)",
                                        (table, rtree + "_insert", f"trigger_insert_feature_count_{table}")).fetchall()
                for name, _ in triggers:
                    conn.execute(f'DROP TRIGGER "{name}"')
                _insert_rows(conn, table, geom_cols[table], records, ok, fields, columns, cancelled)
                boxes = _boxes(records, ok)
                del records, columns
                if conn.execute("SELECT 1 FROM sqlite_master WHERE name = ?", (rtree,)).fetchone():
                    _rtree_bulk_load(conn, rtree, np.flatnonzero(ok) + 1, boxes)  # fids 1..n
                for _, sql in triggers:
                    conn.execute(sql)
                extent = _extent(boxes)
                if extent is not None:
                    conn.execute("UPDATE gpkg_contents SET min_x = ?, min_y = ?, max_x = ?, max_y = ? "
                                 "WHERE table_name = ?", (*extent, table))
                del boxes, ok
            conn.execute("COMMIT")
        finally:
            conn.close()
    except sqlite3.Error as exc:
        raise Gf4calError(f"cannot write the GeoPackage ({exc}): check the disk is not full; nothing was kept") \
            from None
    with gdal_exceptions():
        try:
            ds = gdal.OpenEx(str(path), gdal.OF_VECTOR)
            for table, expected in counts.items():
                got = ds.GetLayerByName(table).GetFeatureCount()
                if got != expected:
                    raise Gf4calError(f"the GeoPackage layer {table!r} holds {got} features instead of "
                                      f"{expected}; nothing was kept")
            ds = None
        except RuntimeError as exc:
            raise Gf4calError(f"cannot write the GeoPackage: {first_line(exc)}; check the disk is not full") \
                from None


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


@with_quiet_errors
def write_residuals_gpkg(gcps, path: PathLike, *, footprint=None, exaggeration: Optional[float] = None,
                         before: Optional[Tuple[str, str]] = STANDARD_BEFORE,
                         after: Optional[Tuple[str, str]] = STANDARD_AFTER,
                         crs: Any = "EPSG:4326", pixel_size=None, overwrite: bool = True,
                         title: str = "GCP residuals", cancelled: Optional[Callable[[], bool]] = None,
                         layer_prefix: str = "", append: bool = False, points_title: Optional[str] = None) -> Path:
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
    cancelled : callable, optional
        Asked between layers and every 20,000 rows; when it returns True the write stops with
        :class:`~gdal_gf4cal.errors.CancelledError` and the temporary file is removed (nothing is written).
    points_title : str, optional
        The points layer's title (its ``IDENTIFIER``, the name QGIS gives the layer) when the points are not GCPs,
        e.g. pan-MS cells; the table keeps its name ``gcps``.
    layer_prefix : str
        Prefix of every layer name and title (``<prefix>gcps``, ...): several images' layers in one GeoPackage.
    append : bool
        Add the layers to the existing GeoPackage ``path`` instead of replacing it (the caller owns atomicity, e.g.
        an :class:`~gdal_gf4cal.outputs.OutputSet` temporary).

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
        if vals.dtype.kind not in "biufO":
            vals = vals.astype(str)     # object columns: text, nulls kept (converted chunk-wise when written)
        columns[col] = vals
        fields.append((col, _ogr_type(vals)))

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
    clip_at = np.inf
    if exaggeration is not None:
        factor = float(exaggeration)
    else:
        factor = _nice(0.1 * extent / longest_all) if longest_all > 0 else 1.0
        clip_at = 3.0 * longest_all * factor  # auto mode: blunders drawn at most 3x the longest regular arrow
    scale = factor * math.sqrt(ps * pl)

    def arrows(epoch):
        """One epoch's arrows: residuals, map offsets, magnitude, drawable mask, blunder shortening."""
        s_, l_ = res[epoch]
        dx, dy = s_ * ps, -l_ * pl  # sample -> east, line -> south (image rows go down)
        if metric[epoch] is not None:
            dx, dy = metric[epoch]   # the RPC ground offsets (res_east_m_/res_north_m_ columns), in map units
        drawn = factor * np.hypot(dx, dy)
        finite = np.isfinite(drawn) & np.isfinite(x) & np.isfinite(y)
        shrink = np.where(drawn > clip_at, clip_at / np.where(drawn > 0, drawn, 1.0), 1.0)
        return s_, l_, dx, dy, np.hypot(s_, l_), finite, shrink, drawn > clip_at

    def arrow_layer(epoch, srs_id):
        """The epoch's line records and fields, built when the layer is written (one epoch in memory at a time)."""
        s_, l_, dx, dy, mag, keep, shrink, clipped = arrows(epoch)
        f = factor * shrink[keep]
        records, ok = _line_records(x[keep], y[keep], x[keep] + f * dx[keep], y[keep] + f * dy[keep], srs_id)
        cols = {"id": ids[keep], "role": role[keep], "epoch": epoch,          # scalars: the same in every row
                "res_sample": s_[keep], "res_line": l_[keep], "res_px": mag[keep], "outlier": outlier[keep],
                "clipped": clipped[keep], "exaggeration": factor, "map_units_per_px": scale}
        return records, ok, cols

    vfields = [("id", (ogr.OFTString, ogr.OFSTNone)), ("role", (ogr.OFTString, ogr.OFSTNone)),
               ("epoch", (ogr.OFTString, ogr.OFSTNone))] + \
              [(c, (ogr.OFTReal, ogr.OFSTNone)) for c in ("res_sample", "res_line", "res_px")] + \
              [("outlier", (ogr.OFTInteger, ogr.OFSTBoolean)), ("clipped", (ogr.OFTInteger, ogr.OFSTBoolean)),
               ("exaggeration", (ogr.OFTReal, ogr.OFSTNone)), ("map_units_per_px", (ogr.OFTReal, ogr.OFSTNone))]
    for k, epoch in enumerate(epochs):
        _, _, _, _, mag, finite, _, clipped = arrows(epoch)
        # Scale and classes follow the ordinary points: one blunder must not shrink every other arrow to nothing.
        regular = finite & ~outlier if (finite & ~outlier).any() else finite
        name = layer_prefix + ("residual_vectors" if k == 0 else "residual_vectors_before")
        desc = (f"{title}: {epoch} residuals (measured - predicted, px) drawn from each GCP's ground position with "
                f"sample -> east and line -> south, exaggerated {factor:g}x (1 px of residual = {scale:.6g} map "
                f"units; pixel size {ps:.6g} x {pl:.6g} map units from {ps_source})")
        if clipped[finite].any():
            desc += (f"; {int(clipped[finite].sum())} blunder arrow(s) shortened to 3x the longest other one "
                     "(clipped = 1)")
        meta = {"EXAGGERATION": f"{factor:g}", "MAP_UNITS_PER_PX": f"{scale:.10g}", "EPOCH": epoch,
                "DIRECTION": "sample->east, line->south", "PIXEL_SIZE_MAP_UNITS": f"{ps:.10g} {pl:.10g}"}
        mag = mag[regular]  # class breaks from the regular points; blunders fall in the open last class
        vector_layers.append((name, vfields, epoch, desc, meta, mag, layer_prefix + residual_layer_title(epoch, factor)))

    if path.exists() and not overwrite and not append:  # pragma: no cover - checked above; re-checked for races
        raise Gf4calError(f"{path} exists")
    appending = append and path.exists()
    tmp = path if appending else _temp_path(path)
    driver = ogr.GetDriverByName("GPKG")
    check_cancel = cancelled if cancelled is not None else (lambda: False)
    try:
        ds = ogr.Open(str(path), update=1) if appending else driver.CreateDataSource(str(tmp))
        if ds is None:
            raise Gf4calError(f"cannot create a GeoPackage in {path.parent}; check the folder is writable")
        styles, bulk = [], []
        if ds.StartTransaction() != 0:
            raise Gf4calError(f"cannot write the GeoPackage {path}; check the folder is writable")
        gname = layer_prefix + "gcps"
        gl = _create_layer(ds, gname, srs, ogr.wkbPoint, fields,
                           f"{title}: ground control / check points with residuals (measured - predicted, px)",
                           None, points_title)
        bulk.append((gname, fields, lambda sid: (*_point_records(x, y, sid), columns)))
        qml, sld = _points_style()
        styles.append((gname, gl.GetGeometryColumn(), qml, _sld(gname, sld), "GCPs by role; outliers as red crosses"))
        for name, vfields, epoch, desc, meta, mag, ident in vector_layers:
            vl = _create_layer(ds, name, srs, ogr.wkbLineString, vfields, desc, meta, ident)
            bulk.append((name, vfields, lambda sid, e=epoch: arrow_layer(e, sid)))
            # The 'before' arrows are drawn half-transparent so the 'after' ones stand out where both are shown.
            qml, sld = _vector_style(_class_breaks(mag), 1.0 if name.endswith("residual_vectors") else 0.5)
            styles.append((name, vl.GetGeometryColumn(), qml, _sld(name, sld),
                           f"residual arrows coloured by magnitude; {desc}"))
        if fp is not None and not fp.is_empty:
            ffields = [("name", (ogr.OFTString, ogr.OFSTNone))]
            fname = layer_prefix + "footprint"
            fl = _create_layer(ds, fname, srs, ogr.wkbMultiPolygon, ffields, f"{title}: scene footprint")
            wkb = ogr.ForceToMultiPolygon(ogr.CreateGeometryFromWkb(fp.wkb)).ExportToWkb(ogr.wkbNDR)
            bulk.append((fname, ffields,
                         lambda sid, w=wkb, bb=fp.bounds: (*_wkb_records(w, bb, sid), {"name": "footprint"})))
            qml, sld = _footprint_style()
            styles.append((fname, fl.GetGeometryColumn(), qml, _sld(fname, sld), "scene footprint"))
        _write_layer_styles(ds, styles)
        if ds.CommitTransaction() != 0:
            raise Gf4calError(f"cannot write the GeoPackage {path} (the commit failed: disk full?); nothing was kept")
        ds = None
        if check_cancel():
            raise CancelledError("cancelled while writing the residual GeoPackage; nothing was kept")
        srs_ids = _srs_ids(tmp, [name for name, *_ in bulk])
        _bulk_write(tmp, [(name, lfields, (lambda m=make, sid=srs_ids[name]: m(sid))) for name, lfields, make in bulk],
                    check_cancel)
        if check_cancel():
            raise CancelledError("cancelled while writing the residual GeoPackage; nothing was kept")
        if not appending:
            os.replace(tmp, path)
    finally:
        ds = None
        if not appending:
            _cleanup(tmp)
    return path


@with_quiet_errors
def write_points_layer(path: PathLike, layer: str, columns: Mapping[str, np.ndarray], lon, lat, *,
                       description: str = "") -> Path:
    """Add a point layer (EPSG:4326, one feature per row of ``columns``) to the GeoPackage ``path`` (created when
    absent), styled as the ``gcps`` layers (e.g. block calibration's ``seams``: one feature per overlap tie point).
    Written as the residual layers are: OGR creates the layer and its style, the rows go in in bulk."""
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
    try:
        if ds.StartTransaction() != 0:
            raise Gf4calError(f"cannot write the GeoPackage {path}; check the folder is writable")
        if layer == "seams":       # seam offsets: graduated arrows, the factor in the title (styles.seams_style)
            qml, sld, title, _ = seams_style(cols, lon, lat)
        else:
            (qml, sld), title = _points_style(), None
        lyr = _create_layer(ds, layer, srs, ogr.wkbPoint, fields, description, identifier=title)
        _write_layer_styles(ds, [(layer, lyr.GetGeometryColumn(), qml, _sld(layer, sld), description)])
        if ds.CommitTransaction() != 0:
            raise Gf4calError(f"cannot write the GeoPackage {path} (the commit failed: disk full?)")
    finally:
        ds = None
    sid = _srs_ids(path, [layer])[layer]
    _bulk_write(path, [(layer, fields, lambda: (*_point_records(lon, lat, sid), cols))], None)
    return path


def residual_layer_title(epoch: str, factor: float) -> str:
    """The title of a residual-arrow layer, stating its exaggeration: ``"residuals after (x37)"``. The GeoPackage
    stores it as the layer's ``IDENTIFIER`` (gpkg_contents), and QGIS shows it as the layer name, so before and
    after arrows drawn with one factor say so in the legend."""
    return f"residuals {epoch} (x{float(factor):g})"


def layer_titles(path: PathLike) -> dict:
    """``{table name: title}`` of a GeoPackage's layers: the ``IDENTIFIER`` when it differs from the table name
    (the residual arrows, see :func:`residual_layer_title`), else the table name."""
    from .._gdal import open_vector
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
