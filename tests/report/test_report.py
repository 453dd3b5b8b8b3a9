"""gdal_gf4cal.report: styled residual GeoPackages, residual plots and report.json, read back with GDAL/OGR."""
from __future__ import annotations

import json
import math
import os
import xml.etree.ElementTree as ET

import geopandas as gpd
import numpy as np
import pandas as pd
import pytest
from osgeo import gdal, ogr
from shapely.geometry import box

from gdal_gf4cal.errors import GCPError, InputOverwriteError
from gdal_gf4cal.report import plot_residuals, write_report_json, write_residuals_gpkg
from gdal_gf4cal.report.gpkg import layer_titles

ogr.UseExceptions()
gdal.UseExceptions()

PX_DEG = 1e-3  # ground size of a pixel in the synthetic GCP set, degrees


@pytest.fixture
def gcps():
    """60 GCPs on a north-up 1000 x 1000 px grid, 1e-3 deg per pixel, with known residuals before/after."""
    rng = np.random.default_rng(42)
    n = 60
    s, l = rng.uniform(0, 1000, n), rng.uniform(0, 1000, n)
    lon, lat = 100.0 + s * PX_DEG, 30.0 - l * PX_DEG
    df = pd.DataFrame({
        "id": [f"P{i:03d}" for i in range(n)], "lon": lon, "lat": lat, "h": rng.uniform(100, 900, n),
        "sample": s, "line": l, "role": np.where(np.arange(n) % 4 == 0, "check", "control"), "sigma": 0.5,
        "ds0": 3.0 + 0.002 * s, "dl0": -2.0 + 0.001 * l,
        "res_sample_after": rng.normal(0, 0.3, n), "res_line_after": rng.normal(0, 0.3, n),
        "outlier": np.arange(n) == 7, "peak_corr": rng.uniform(0.5, 1, n)})
    return gpd.GeoDataFrame(df, geometry=gpd.points_from_xy(lon, lat), crs="EPSG:4326")


def _layer_rows(path, layer):
    ds = ogr.Open(str(path))
    lyr = ds.GetLayerByName(layer)
    rows = [f.items() | {"_geom": f.GetGeometryRef().Clone() if f.GetGeometryRef() else None} for f in lyr]
    fields = [lyr.GetLayerDefn().GetFieldDefn(i) for i in range(lyr.GetLayerDefn().GetFieldCount())]
    return rows, {f.GetName(): (f.GetType(), f.GetSubType()) for f in fields}, lyr.GetMetadata(), lyr.GetSpatialRef()


def test_gpkg_layers_fields_and_values(tmp_path, gcps):
    out = write_residuals_gpkg(gcps, tmp_path / "res.gpkg", footprint=box(100, 29, 101, 30),
                               before=("ds0", "dl0"))
    assert out == tmp_path / "res.gpkg"
    assert sorted(os.listdir(tmp_path)) == ["res.gpkg"]  # no temporary file left behind
    ds = ogr.Open(str(out))
    names = {ds.GetLayer(i).GetName() for i in range(ds.GetLayerCount())}
    assert names == {"gcps", "residual_vectors", "residual_vectors_before", "footprint", "layer_styles"}
    rows, fields, _, srs = _layer_rows(out, "gcps")
    assert len(rows) == 60 and srs.GetAuthorityCode(None) == "4326"
    for f in ("id", "lon", "lat", "h", "sample", "line", "role", "sigma", "res_sample_before", "res_line_before",
              "res_px_before", "res_sample_after", "res_line_after", "res_px_after", "outlier", "peak_corr"):
        assert f in fields, f
    assert fields["outlier"] == (ogr.OFTInteger, ogr.OFSTBoolean)
    assert "ds0" not in fields  # renamed to the standard residual fields
    by_id = {r["id"]: r for r in rows}
    g = gcps.set_index("id")
    for pid in ("P000", "P007", "P059"):
        r = by_id[pid]
        assert r["res_sample_before"] == pytest.approx(g.loc[pid, "ds0"])
        assert r["res_line_before"] == pytest.approx(g.loc[pid, "dl0"])
        assert r["res_px_after"] == pytest.approx(math.hypot(g.loc[pid, "res_sample_after"],
                                                             g.loc[pid, "res_line_after"]))
        assert r["role"] == g.loc[pid, "role"] and r["peak_corr"] == pytest.approx(g.loc[pid, "peak_corr"])
        assert (r["_geom"].GetX(), r["_geom"].GetY()) == pytest.approx((g.loc[pid, "lon"], g.loc[pid, "lat"]))
    assert [r["id"] for r in rows if r["outlier"]] == ["P007"]
    fp, _, _, _ = _layer_rows(out, "footprint")
    assert len(fp) == 1 and fp[0]["_geom"].GetArea() == pytest.approx(1.0)
    # geopandas reads it back as well
    back = gpd.read_file(out, layer="gcps")
    assert len(back) == 60 and back.crs.to_epsg() == 4326


def test_residual_vectors_direction_length_and_factor(tmp_path, gcps):
    out = write_residuals_gpkg(gcps, tmp_path / "res.gpkg", before=("ds0", "dl0"))
    extent = max(np.ptp(gcps.lon), np.ptp(gcps.lat))
    g = gcps.set_index("id")
    factors, longest = [], []
    for layer, cols, epoch in (("residual_vectors", ("res_sample_after", "res_line_after"), "after"),
                               ("residual_vectors_before", ("ds0", "dl0"), "before")):
        rows, fields, meta, _ = _layer_rows(out, layer)
        assert len(rows) == 60
        assert {"id", "role", "epoch", "res_sample", "res_line", "res_px", "outlier", "exaggeration",
                "map_units_per_px"} <= set(fields)
        factor = rows[0]["exaggeration"]
        assert all(r["exaggeration"] == factor and r["epoch"] == epoch for r in rows)
        assert meta["EXAGGERATION"] == f"{factor:g}"
        assert meta["IDENTIFIER"] == f"residuals {epoch} (x{factor:g})"   # the title QGIS shows states the factor
        ds = ogr.Open(str(out))
        desc = ds.ExecuteSQL(f"SELECT description FROM gpkg_contents WHERE table_name = '{layer}'")
        assert f"exaggerated {factor:g}x" in desc.GetNextFeature()["description"]
        ds.ReleaseResultSet(desc)
        lengths = []
        for r in rows:
            geom = r["_geom"]
            (x0, y0), (x1, y1) = geom.GetPoint_2D(0), geom.GetPoint_2D(1)
            ds_px, dl_px = g.loc[r["id"], cols[0]], g.loc[r["id"], cols[1]]
            assert (x0, y0) == pytest.approx((g.loc[r["id"], "lon"], g.loc[r["id"], "lat"]))
            # sample -> east, line -> south; one pixel is PX_DEG on the ground (estimated from the GCPs)
            assert x1 - x0 == pytest.approx(factor * ds_px * PX_DEG, rel=1e-6, abs=1e-12)
            assert y1 - y0 == pytest.approx(-factor * dl_px * PX_DEG, rel=1e-6, abs=1e-12)
            assert r["map_units_per_px"] == pytest.approx(factor * PX_DEG, rel=1e-6)
            lengths.append(math.hypot(x1 - x0, y1 - y0))
        factors.append(factor)
        longest.append(max(lengths))
    # one automatic factor for before and after: the longest arrow of either is ~10 % of the extent (two
    # significant digits of rounding), so the gain of the refinement shows as shorter 'after' arrows
    assert factors[0] == factors[1]
    assert max(longest) / extent == pytest.approx(0.10, rel=0.06)


def test_explicit_factor_projected_crs_and_before_only(tmp_path, gcps):
    out = write_residuals_gpkg(gcps.drop(columns=["res_sample_after", "res_line_after"]), tmp_path / "b.gpkg",
                               before=("ds0", "dl0"), exaggeration=500, crs="EPSG:32647")
    ds = ogr.Open(str(out))
    assert {ds.GetLayer(i).GetName() for i in range(ds.GetLayerCount())} == {"gcps", "residual_vectors",
                                                                             "layer_styles"}
    rows, _, meta, srs = _layer_rows(out, "residual_vectors")
    assert srs.GetAuthorityCode(None) == "32647" and meta["EPOCH"] == "before"
    assert all(r["epoch"] == "before" and r["exaggeration"] == 500 for r in rows)
    assert layer_titles(out) == {"gcps": "gcps", "residual_vectors": "residuals before (x500)",
                                 "layer_styles": "layer_styles"}
    # the pixel is ~96 m x 111 m at 30 N in UTM: lengths follow residual x pixel size x 500
    ps = rows[0]["map_units_per_px"] / 500
    assert 90 < ps < 115
    g = gcps.set_index("id")
    for r in rows[:5]:
        (x0, y0), (x1, y1) = r["_geom"].GetPoint_2D(0), r["_geom"].GetPoint_2D(1)
        assert x1 > x0 and y1 > y0  # ds0 > 0 -> east; dl0 < 0 (up the image) -> north
        assert math.hypot(x1 - x0, y1 - y0) == pytest.approx(
            500 * math.hypot(g.loc[r["id"], "ds0"], g.loc[r["id"], "dl0"]) * 100, rel=0.15)
    gl, _, _, _ = _layer_rows(out, "gcps")
    assert all(r["res_sample_after"] is None for r in gl)  # absent residuals are NULL, not 0


def test_layer_styles_table_follows_qgis_schema(tmp_path, gcps):
    out = write_residuals_gpkg(gcps, tmp_path / "res.gpkg", before=("ds0", "dl0"), footprint=box(100, 29, 101, 30))
    rows, fields, _, _ = _layer_rows(out, "layer_styles")
    assert list(fields) == ["f_table_catalog", "f_table_schema", "f_table_name", "f_geometry_column", "styleName",
                            "styleQML", "styleSLD", "useAsDefault", "description", "owner", "ui", "update_time"]
    assert fields["useAsDefault"] == (ogr.OFTInteger, ogr.OFSTBoolean)
    assert fields["update_time"][0] == ogr.OFTDateTime
    by_table = {r["f_table_name"]: r for r in rows}
    assert set(by_table) == {"gcps", "residual_vectors", "residual_vectors_before", "footprint"}
    for table, r in by_table.items():
        assert r["useAsDefault"] == 1 and r["f_geometry_column"] == "geom" and r["styleName"] == table
        qml = ET.fromstring(r["styleQML"].split("\n", 1)[1])  # skip the DOCTYPE line
        sld = ET.fromstring(r["styleSLD"].encode())
        assert sld.tag.endswith("StyledLayerDescriptor")
        renderer = qml.find("renderer-v2")
        if table.startswith("residual_vectors"):
            assert renderer.get("type") == "graduatedSymbol" and renderer.get("attr") == "res_px"
            assert len(renderer.findall("ranges/range")) == 6
            assert {lyr.get("class") for lyr in renderer.iter("layer")} == {"ArrowLine", "SimpleFill"}
            # every residual falls in a class
            vals, _, _, _ = _layer_rows(out, table)
            ranges = [(float(x.get("lower")), float(x.get("upper"))) for x in renderer.findall("ranges/range")]
            assert all(any(lo <= v["res_px"] <= hi for lo, hi in ranges) for v in vals)
        elif table == "gcps":
            assert renderer.get("type") == "RuleRenderer"
            assert [x.get("label") for x in renderer.findall("rules/rule")] == ["control", "check", "other",
                                                                               "outlier"]
        else:
            assert renderer.get("type") == "singleSymbol"


def test_gpkg_bad_input_writes_nothing(tmp_path, gcps):
    with pytest.raises(GCPError, match="GeoPackage"):
        write_residuals_gpkg(gcps, tmp_path / "res.shp")
    with pytest.raises(GCPError, match="'sample'"):
        write_residuals_gpkg(gcps.drop(columns=["sample"]), tmp_path / "res.gpkg")
    assert os.listdir(tmp_path) == []
    (tmp_path / "keep.gpkg").write_bytes(b"old")
    with pytest.raises(InputOverwriteError):
        write_residuals_gpkg(gcps, tmp_path / "keep.gpkg", overwrite=False)
    assert (tmp_path / "keep.gpkg").read_bytes() == b"old"
    # ground positions from the geometry when lon/lat columns are absent (any CRS)
    utm = gcps.drop(columns=["lon", "lat"]).to_crs("EPSG:32647")
    out = write_residuals_gpkg(utm, tmp_path / "geom.gpkg")
    rows, _, _, _ = _layer_rows(out, "gcps")
    assert rows[0]["lon"] == pytest.approx(gcps.lon.iloc[0], abs=1e-9)


def test_plot_residuals_png(tmp_path, gcps):
    out = plot_residuals(gcps, tmp_path / "res.png", before=("ds0", "dl0"), image_size=(1000, 1000),
                         title="synthetic")
    assert sorted(os.listdir(tmp_path)) == ["res.png"]
    ds = gdal.Open(str(out))
    assert ds.GetDriver().ShortName == "PNG" and ds.RasterXSize > 2 * ds.RasterYSize * 0.8
    rgb = np.stack([ds.GetRasterBand(b).ReadAsArray() for b in (1, 2, 3)], -1).astype(int)
    blue = (abs(rgb[..., 0] - 0x1f) < 30) & (abs(rgb[..., 1] - 0x4f) < 30) & (rgb[..., 2] > 180)
    green = (rgb[..., 0] < 60) & (abs(rgb[..., 1] - 0xa0) < 30) & (rgb[..., 2] < 80)
    assert blue.sum() > 200 and green.sum() > 50  # control and check arrows drawn in both panels
    with pytest.raises(GCPError, match="no residual"):
        plot_residuals(gcps, tmp_path / "none.png", before=("x", "y"), after=None)
    assert not (tmp_path / "none.png").exists()


def test_report_json_numpy_safe(tmp_path):
    rep = {"n": np.int64(3), "rms_px": np.float32(0.25), "arr": np.arange(3, dtype=np.int16), "flag": np.bool_(True),
           "nan": float("nan"), "inf": np.inf, "nested": {"t": (1, np.float64(2.5))}, "path": tmp_path / "x"}
    out = write_report_json(rep, tmp_path / "report.json")

    def no_constants(name):
        raise AssertionError(f"non-standard JSON constant {name}")

    back = json.loads(out.read_text(), parse_constant=no_constants)
    assert back == {"n": 3, "rms_px": 0.25, "arr": [0, 1, 2], "flag": True,
                    "nested": {"t": [1, 2.5]}, "path": str(tmp_path / "x")}
    assert sorted(os.listdir(tmp_path)) == ["report.json"]
    with pytest.raises(TypeError):
        write_report_json({"x": object()}, tmp_path / "bad.json")
    assert not (tmp_path / "bad.json").exists()


def test_report_json_leaves_out_what_was_not_measured(tmp_path):
    """Absent sections instead of nulls (issue 15): a value that could not be computed is left out, a section of
    no points (n = 0), an empty one or one of zero counts only is left out; inside arrays NaN stays a positional
    null; the top level is always an object."""
    rep = {"model": {"name": "affine", "order": None, "along": None},
           "control": {"n_outliers": 1, "before": {"n": 5, "line": {"rms": 1.5, "std": float("nan")}, "ce90_m": None}},
           "check": {"n_outliers": 0, "before": {"n": 0, "line": {"rms": float("nan")}},
                     "after": {"n": 0, "line": {"rms": None}}},
           "empty": {}, "zeros": {"n_failed": 0, "n_points": 0}, "counts": {"ok": 0, "n_failed": 0},
           "series": np.array([1.0, np.nan, 2.0]), "outliers": []}
    back = json.loads(write_report_json(rep, tmp_path / "r.json").read_text())
    assert back == {"model": {"name": "affine"},
                    "control": {"n_outliers": 1, "before": {"n": 5, "line": {"rms": 1.5}}},
                    "counts": {"ok": 0, "n_failed": 0}, "series": [1.0, None, 2.0], "outliers": []}
    assert json.loads(write_report_json({"x": None}, tmp_path / "e.json").read_text()) == {}


def test_assess_accuracy_against_known_offsets(tmp_path):
    """A real RPC (GDAL autotest's DigitalGlobe sample) and GCPs displaced by a known shift + rotation + noise."""
    from gdal_gf4cal.gcp import make_gcps
    from gdal_gf4cal.workflows import assess_accuracy
    from gdal_gf4cal.rpc import RPCModel

    rpc_path = os.path.join(os.path.dirname(os.path.dirname(__file__)), "data", "rpc", "md_dg.RPB")
    rpc = RPCModel.from_file(rpc_path)
    W, H = rpc.image_size
    rng = np.random.default_rng(3)
    n = 80
    s0, l0 = rng.uniform(0, W, n), rng.uniform(0, H, n)
    h = rng.uniform(50, 300, n)
    lon, lat = rpc.localize(s0, l0, h)
    theta, cs, cl = 2e-4, W / 2, H / 2  # a small rotation about the centre (~0.2 px at the edges)
    s = cs + np.cos(theta) * (s0 - cs) - np.sin(theta) * (l0 - cl) + 1.5 + rng.normal(0, 0.1, n)
    l = cl + np.sin(theta) * (s0 - cs) + np.cos(theta) * (l0 - cl) - 0.7 + rng.normal(0, 0.1, n)
    gcps = make_gcps(lon, lat, h, s, l, role=np.where(np.arange(n) % 3 == 0, "check", "control"))
    rep = assess_accuracy(rpc_path, gcps, residuals=tmp_path / "acc.gpkg", plot=tmp_path / "acc.png",
                          report=tmp_path / "acc.json", image_size=(W, H))
    assert rep["n"] == n and rep["check"]["n"] == (np.arange(n) % 3 == 0).sum()
    assert rep["all"]["sample"]["mean"] == pytest.approx(1.5, abs=0.05)
    assert rep["all"]["line"]["mean"] == pytest.approx(-0.7, abs=0.05)
    assert rep["all"]["sample"]["std"] < 0.3 and rep["all"]["line"]["std"] < 0.3
    # ~1.65 px planar at ~1.6 m per pixel
    assert rep["all"]["ce90_m"] == pytest.approx(1.65 * 1.6, rel=0.15)
    # internal accuracy removes the shift and rotation: what is left is the noise
    internal = rep["all"]["internal"]
    assert internal["theta_rad"] == pytest.approx(theta, abs=5e-5)
    assert internal["sample"]["rms"] < 0.13 and internal["line"]["rms"] < 0.13
    assert sorted(os.listdir(tmp_path)) == ["acc.gpkg", "acc.json", "acc.png"]
    rows, fields, _, _ = _layer_rows(tmp_path / "acc.gpkg", "gcps")
    assert len(rows) == n and "res_sample_before" in fields and "pred_sample" in fields
    assert all(r["res_sample_after"] is None for r in rows)
    ds = ogr.Open(str(tmp_path / "acc.gpkg"))
    assert ds.GetLayerByName("footprint").GetFeatureCount() == 1
    assert ds.GetLayerByName("residual_vectors").GetMetadata()["EPOCH"] == "before"


@pytest.mark.parametrize("n", [2, 40, 3000])
def test_bulk_written_gpkg_is_valid_with_spatial_index_styles_and_nulls(tmp_path, n):
    """The residual GeoPackage is written in bulk (SQLite executemany + an STR-packed R-tree, issue 11): SQLite's own
    integrity and R-tree checks pass, OGR re-opens it with the right counts, extents and a spatial index that answers
    like a brute-force search (R-trees of depth 0, 1 and 2 for 2, 40 and 3000 points), a point without ground
    position is kept with a NULL geometry and no index entry, NaN fields are NULL, and the styles are intact."""
    import sqlite3
    rng = np.random.default_rng(n)
    s, l = rng.integers(0, 1000, n).astype(float), rng.integers(0, 1000, n).astype(float)
    df = pd.DataFrame({"id": [f"P{i}" for i in range(n)], "lon": 100.0 + s / 1024, "lat": 30.0 - l / 1024,
                       "h": 50.0, "sample": s, "line": l, "role": "control",
                       "res_sample_before": rng.normal(2, 1, n), "res_line_before": rng.normal(-1, 1, n),
                       "res_sample_after": rng.normal(0, .2, n), "res_line_after": rng.normal(0, .2, n),
                       "note": [None if i % 7 == 0 else f"n{i}" for i in range(n)]})
    df.loc[n - 1, "lon"] = np.nan                  # no ground position: kept, without geometry
    df.loc[0, "res_sample_after"] = np.nan
    out = write_residuals_gpkg(df, tmp_path / "bulk.gpkg", footprint=box(100, 29, 101, 30))
    conn = sqlite3.connect(str(out))
    try:
        assert conn.execute("PRAGMA integrity_check").fetchone() == ("ok",)
        for table in ("gcps", "residual_vectors", "residual_vectors_before", "footprint"):
            assert conn.execute(f"SELECT rtreecheck('rtree_{table}_geom')").fetchone() == ("ok",), table
            n_geom = conn.execute(f'SELECT COUNT(*) FROM "{table}" WHERE geom IS NOT NULL').fetchone()[0]
            assert conn.execute(f"SELECT COUNT(*) FROM rtree_{table}_geom").fetchone()[0] == n_geom
        triggers = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'trigger'")}
        assert {"rtree_gcps_geom_insert", "trigger_insert_feature_count_gcps"} <= triggers   # restored
        assert conn.execute("SELECT COUNT(*) FROM layer_styles").fetchone()[0] == 4
    finally:
        conn.close()
    ds = ogr.Open(str(out))
    gl = ds.GetLayerByName("gcps")
    assert gl.GetFeatureCount() == n and gl.TestCapability(ogr.OLCFastSpatialFilter)
    ok = df["lon"].notna()
    assert gl.GetExtent() == pytest.approx((df.lon[ok].min(), df.lon[ok].max(), df.lat[ok].min(), df.lat[ok].max()))
    for rect in ((100.2, 29.3, 100.6, 29.9), (99.0, 29.0, 101.0, 31.0)):   # edges between the 1/1024 grid points
        gl.SetSpatialFilterRect(*rect)
        inside = ok & df.lon.between(rect[0], rect[2]) & df.lat.between(rect[1], rect[3])
        assert sorted(f["id"] for f in gl) == sorted(df.id[inside])
    gl.SetSpatialFilter(None)
    feats = {f["id"]: f for f in gl}
    assert feats[f"P{n - 1}"].GetGeometryRef() is None
    assert feats["P0"]["res_sample_after"] is None and feats["P0"]["note"] is None
    assert feats["P1"]["note"] == "n1" and feats["P1"]["res_sample_before"] == pytest.approx(df.res_sample_before[1])
    assert feats["P0"].GetGeometryRef().GetPoint_2D() == (df.lon[0], df.lat[0])   # exact: float64 WKB
    assert ds.GetLayerByName("residual_vectors").GetFeatureCount() == n - 2          # P0: no after residual
    assert ds.GetLayerByName("residual_vectors_before").GetFeatureCount() == n - 1
    assert ds.GetLayerByName("footprint").GetFeatureCount() == 1


@pytest.mark.parametrize("n, bulk", [(60, False), (40_000, True)])
def test_gpkg_through_ogr_or_in_bulk_passes_gdal_validator(tmp_path, n, bulk):
    """One seam chooses the writer (issue 21): OGR features in one transaction up to 1e5 rows in all, the bulk
    writer above (40,000 points + two arrow layers = ~120,000 rows). Both files pass GDAL's GeoPackage validator
    and every check of the bulk test above (spatial index answers, NULLs, extents, restored triggers, styles)."""
    from osgeo_utils.samples.validate_gpkg import check
    from gdal_gf4cal.report.gpkg import OGR_MAX_ROWS, writes_in_bulk
    assert writes_in_bulk(3 * n - 3) is bulk and OGR_MAX_ROWS == 100_000
    test_bulk_written_gpkg_is_valid_with_spatial_index_styles_and_nulls(tmp_path, n)
    check(str(tmp_path / "bulk.gpkg"), abort_at_first_error=True)       # raises on the first violation


def test_concurrent_writer_takes_the_bulk_path_with_the_same_layers(tmp_path, gcps):
    """A caller writing while its other threads compute (register-pan-ms's cells, issue 23) asks for the bulk writer
    at any size: the same layers in the same order, the same features (fields, types, values, geometries),
    metadata, titles and styles as the OGR path, and GDAL's validator passes."""
    from osgeo_utils.samples.validate_gpkg import check
    from gdal_gf4cal.report.gpkg import writes_in_bulk
    assert not writes_in_bulk(3 * len(gcps)) and writes_in_bulk(3 * len(gcps), concurrent=True)
    kw = dict(footprint=box(100, 29, 101, 30), before=("ds0", "dl0"), points_title="cells")
    paths = [write_residuals_gpkg(gcps, tmp_path / f"{c}.gpkg", concurrent=c, **kw) for c in (False, True)]
    names = []
    for p in paths:
        ds = ogr.Open(str(p))
        names.append([ds.GetLayer(i).GetName() for i in range(ds.GetLayerCount())])
    assert names[0] == names[1] and len(names[0]) == 5
    for layer in names[0]:
        (ra, fa, ma, sa), (rb, fb, mb, sb) = (_layer_rows(p, layer) for p in paths)
        assert fa == fb and ma == mb and (sa is None) == (sb is None), layer
        key = lambda r: str(r.get("id", r.get("f_table_name")))     # noqa: E731 - the rows' own order may differ
        for a, b in zip(sorted(ra, key=key), sorted(rb, key=key), strict=True):
            ga, gb = a.pop("_geom"), b.pop("_geom")
            a.pop("update_time", None), b.pop("update_time", None)
            assert a == b and (ga is None and gb is None or ga.Equals(gb)), (layer, a)
    assert layer_titles(paths[0]) == layer_titles(paths[1])
    check(str(paths[1]), abort_at_first_error=True)
