"""The GeoPackage bulk writer, for residual layers above ~1e5 rows (:func:`gdal_gf4cal.report.gpkg.writes_in_bulk`
chooses): OGR has created the layers, fields, metadata and styles; the rows go in through SQLite ``executemany`` of
GeoPackage geometry blobs built with NumPy (many rows per statement), with OGR's insert triggers set aside and
restored, the R-tree is STR-packed straight into SQLite's node tables, then OGR re-opens the file and counts.
1e6 GCPs: seconds, where one OGR feature at a time takes tens of seconds. The geometry records built here
(:func:`point_records`, :func:`line_records`, :func:`wkb_records`) are also what the OGR path reads its WKB from."""
from __future__ import annotations

import sqlite3
import struct
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd
from osgeo import gdal, ogr

from .._gdal import first_line, gdal_exceptions
from ..errors import CancelledError, Gf4calError

# ----------------------------------------------------------------------------------------------------------------
# bulk writing: OGR creates the layers (fields, SRS, metadata, styles), the rows go in through SQLite in chunks
# (executemany of GeoPackage geometry blobs built with NumPy), then OGR builds the spatial indexes and the file is
# re-opened and counted. 1e6 GCPs: seconds, where one OGR feature at a time took minutes.
# ----------------------------------------------------------------------------------------------------------------
CHUNK_ROWS = 20_000     # rows per executemany: bounds the Python objects alive at once and the cancel latency


def point_records(x, y, srs_id: int):
    """GeoPackage point blobs as one NumPy record array (header without envelope, as GDAL writes points, + WKB
    little endian)."""
    dt = np.dtype([("magic", "S2"), ("version", "u1"), ("flags", "u1"), ("srs", "<i4"), ("bo", "u1"),
                   ("type", "<u4"), ("x", "<f8"), ("y", "<f8")])
    rec = np.zeros(x.size, dt)
    rec["magic"], rec["flags"], rec["srs"], rec["bo"], rec["type"] = b"GP", 0x01, srs_id, 1, 1
    rec["x"], rec["y"] = x, y
    return rec, np.isfinite(x) & np.isfinite(y)


def line_records(x0, y0, x1, y1, srs_id: int):
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


def wkb_records(wkb: bytes, bounds, srs_id: int):
    """One geometry (any type, its WKB) as a GeoPackage blob record with its envelope."""
    blob = struct.pack("<2sBBi4d", b"GP", 0, 0x03, srs_id, bounds[0], bounds[2], bounds[1], bounds[3]) + wkb
    rec = np.frombuffer(blob, dtype=np.dtype((np.void, len(blob))))
    return rec, np.ones(1, bool)


def sql_values(values, ftype) -> list:
    """A column chunk as Python values SQLite binds, ``None`` where null (NaN, inf, None)."""
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
    ser = pd.Series(a, dtype=object)
    out = ser.astype(str).to_numpy(dtype=object)
    out[ser.isna().to_numpy()] = None
    return out.tolist()


def column_chunk(values, ftype, start: int, stop: int) -> list:
    """Rows ``start:stop`` of one column (an array, or a scalar the same in every row) as :func:`sql_values`."""
    if np.ndim(values) == 0:
        return [sql_values(np.asarray([values]), ftype)[0]] * (stop - start)
    return sql_values(np.asarray(values)[start:stop], ftype)


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
    for start in range(0, n, CHUNK_ROWS):
        stop = min(n, start + CHUNK_ROWS)
        # bytearray, not bytes: sqlite3 binds bytearray directly where bytes go through its adapter lookup
        # (~0.7 us a row); void keeps trailing zeros
        blobs = list(map(bytearray, records[start:stop].view(f"V{size}").tolist()))
        for i in np.flatnonzero(~ok[start:stop]):
            blobs[i] = None
        cols = [blobs] + [column_chunk(columns[f], ftype, start, stop) for f, (ftype, _) in fields]
        _insert_many(conn, head, cols, stop - start)
        if cancelled is not None and cancelled():
            raise CancelledError("cancelled while writing the residual GeoPackage; nothing was kept")
    conn.execute("UPDATE gpkg_ogr_contents SET feature_count = ? WHERE lower(table_name) = lower(?)", (n, table))


def _extent(boxes):
    """(minx, miny, maxx, maxy) of a layer's geometry boxes (:func:`_boxes`), None when it has none."""
    if not len(boxes):
        return None
    return float(boxes[:, 0].min()), float(boxes[:, 2].min()), float(boxes[:, 1].max()), float(boxes[:, 3].max())


def srs_ids(path: Path, tables) -> dict:
    """The ``srs_id`` OGR registered for each layer (gpkg_geometry_columns)."""
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
    for start in range(0, len(fids), 5 * CHUNK_ROWS):     # appended in rowid order (no page splits), chunk by chunk
        stop = min(len(fids), start + 5 * CHUNK_ROWS)
        _insert_many(conn, f'INSERT INTO "{name}_rowid"(rowid, nodeno)',
                     [fids[start:stop].tolist(), leaf_of[start:stop].tolist()], stop - start)


def geometry_boxes(records, ok) -> np.ndarray:
    """(n, 4) [minx, maxx, miny, maxy] of the geometry records ``ok``."""
    names = records.dtype.names
    if names:       # field by field: no copy of the whole records (77 bytes a line) at 1e6 rows
        out = np.empty((int(np.count_nonzero(ok)), 4))
        for j, f in enumerate(("minx", "maxx", "miny", "maxy") if "minx" in names else ("x", "x", "y", "y")):
            out[:, j] = records[f][ok]
        return out
    return np.array([struct.unpack_from("<4d", bytes(rec), 8) for rec in records[ok]], float).reshape(-1, 4)


def bulk_write(path: Path, layers, cancelled) -> None:
    """Fill the layers OGR created in ``path``: ``layers`` = [(table, fields, make)], ``make()`` giving the geometry
    ``(records, ok)`` and the ``columns`` when the layer is written (one layer's data in memory at a time). One
    SQLite transaction (all or nothing): OGR's R-tree insert trigger (it calls OGR's SQL functions) is set aside,
    the rows go in, the R-tree is bulk-loaded and the trigger restored; then OGR re-opens the file and counts."""
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
                boxes = geometry_boxes(records, ok)
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


