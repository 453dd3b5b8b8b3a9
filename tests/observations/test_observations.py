"""The one observation table (issue 10, Build item 5): long format, GCP view, CSV/GeoPackage files, validation.

Known truth: a simulated ZY-3 three-line scene (seeded); each GCP's ``truth_sample, truth_line`` is the true
model's projection of its ground point, so every table that went through a file must still project to it.
"""
from __future__ import annotations

import os
import re

import numpy as np
import pandas as pd
import pytest

from gdal_gf4cal import DEM, GCPError, InputOverwriteError, read_gcps
from gdal_gf4cal.observations import (OBS_SCHEMA, flag_outliers, from_gcp_views, from_gcps, gcp_view, image_ids,
                                      read_observations, validate_observations, write_observations)
from gdal_gf4cal.simulate import make_scene, simulate_gcps

N_GCPS = 30


@pytest.fixture(scope="module")
def scene():
    return make_scene("zy3", seed=3, size=(2000, 2000))


@pytest.fixture(scope="module")
def views(scene):
    """{image file name: GCP table}: 30 ground points seen by the three images, ids shared."""
    v = simulate_gcps(scene, n_gcps=N_GCPS, gcp_noise_px=0.5, check_fraction=0.3, seed=1)
    return {f"{name}.tif": g for name, g in v.items()}


def _true_models(scene):
    return {f"{im.name}.tif": im.true for im in scene.images}


def _assert_truth(table, scene):
    """Every GCP row's ground point projects, by the true model, to the row's truth_sample/truth_line."""
    for image_id, model in _true_models(scene).items():
        rows = table[(table["image_id"] == image_id) & (table["kind"] == "gcp")]
        s, ln = model.project(rows["lon"].to_numpy(float), rows["lat"].to_numpy(float), rows["h"].to_numpy(float))
        assert np.allclose(s, rows["truth_sample"], atol=1e-6) and np.allclose(ln, rows["truth_line"], atol=1e-6)


def test_gcp_view_is_lossless(views, scene):
    for image_id, g in views.items():
        table = from_gcps(g, image_id)
        assert list(table.columns[:len(OBS_SCHEMA)]) == list(OBS_SCHEMA)
        assert set(table["kind"]) == {"gcp"} and set(table["image_id"]) == {image_id}
        back = gcp_view(table, image_id)
        pd.testing.assert_frame_equal(back, g, check_exact=True)              # every column, same order, same values
        pd.testing.assert_frame_equal(gcp_view(table, f"/elsewhere/{image_id}"), g)   # a path finds it by name
    _assert_truth(from_gcp_views(views), scene)


@pytest.mark.parametrize("ext", [".csv", ".gpkg"])
def test_multi_image_table_round_trip(tmp_path, views, scene, ext):
    table = from_gcp_views(views)
    assert len(table) == 3 * N_GCPS and table["point_id"].nunique() == N_GCPS
    assert image_ids(table) == list(views)
    # One ground point: one set of coordinates on each of its three rows.
    per_point = table.groupby("point_id")[["lon", "lat", "h"]].nunique()
    assert (per_point.to_numpy() == 1).all()
    # Tie points: a third of the points lose their ground coordinates (NaN until estimated).
    tie = table["point_id"].isin(table["point_id"].unique()[::3])
    table.loc[tie, ["lon", "lat", "h"]] = np.nan
    table.loc[tie, "kind"] = "tie"
    path = tmp_path / f"obs{ext}"
    assert write_observations(table, path) == str(path)
    back = read_observations(path)
    pd.testing.assert_frame_equal(back, validate_observations(table), check_exact=True)   # bit-identical
    assert back.loc[tie.to_numpy(), ["lon", "lat", "h"]].isna().all().all()
    _assert_truth(back, scene)
    if ext == ".gpkg":
        import geopandas as gpd
        geom = gpd.read_file(path).geometry
        assert geom.isna().sum() == tie.sum() and geom.notna().sum() == (~tie).sum()
    with pytest.raises(InputOverwriteError, match="exists"):
        write_observations(table, path)
    write_observations(table, path, overwrite=True)
    assert sorted(os.listdir(tmp_path)) == [path.name]                   # no temporary file left


def test_obs_file_of_block_calibration(tmp_path, views, scene):
    """The block-calibration OBS layout: point_id, image, sample, line (+ lon, lat, h for GCPs), role optional."""
    table = from_gcp_views(views)
    gcp_ids = set(table["point_id"].unique()[:10])
    obs = table[["point_id", "image_id", "sample", "line", "lon", "lat", "h"]].rename(columns={"image_id": "image"})
    obs.loc[~obs["point_id"].isin(gcp_ids), ["lon", "lat", "h"]] = np.nan
    path = tmp_path / "OBS.csv"
    obs.to_csv(path, index=False)
    t = read_observations(path)
    assert (t["kind"] == "gcp").sum() == 30 and (t["kind"] == "tie").sum() == 60
    assert set(t.loc[t["kind"] == "gcp", "point_id"]) == gcp_ids
    assert set(t["role"]) == {"control"} and (t["sigma"] == 1.0).all()
    assert np.array_equal(t["sample"].to_numpy(), obs["sample"].to_numpy())
    # A subset of images, named by path or stem: ties seen by only one of them would be dropped.
    two = read_observations(path, images=["/data/nadir.tif", "fwd"])
    assert image_ids(two) == ["nadir.tif", "fwd.tif"] and len(two) == 60
    one = read_observations(path, images=["bwd.tif"])
    assert len(one) == 10 and set(one["kind"]) == {"gcp"}                # its ties have no partner left
    with pytest.raises(GCPError, match="no observations in image 'pan.tif'"):
        read_observations(path, images=["pan.tif"])
    # The GCP reader gives one image's view of such a file.
    g = read_gcps(path, image="fwd.tif")
    truth = views["fwd.tif"]
    keep = truth["id"].isin(gcp_ids).to_numpy()
    assert list(g["id"]) == list(truth["id"][keep])
    assert np.array_equal(g["sample"].to_numpy(), truth["sample"].to_numpy()[keep])
    with pytest.raises(GCPError, match="3 images"):
        read_gcps(path)


def _obs(**changes):
    base = pd.DataFrame({"point_id": ["1", "1", "2", "2"], "image": ["a.tif", "b.tif", "a.tif", "b.tif"],
                         "sample": [10.5, 12.5, 100.5, 98.0], "line": [20.5, 21.0, 200.0, 199.5],
                         "lon": [5.2, 5.2, np.nan, np.nan], "lat": [44.2, 44.2, np.nan, np.nan],
                         "h": [900.0, 900.0, np.nan, np.nan]})
    for k, v in changes.items():
        base[k] = v
    return base


@pytest.mark.parametrize("table, message", [
    (_obs().drop(columns="line"), "missing column.*line"),
    (_obs(sample=[10.5, np.nan, 1.0, 2.0]), "column sample has a missing"),
    (_obs(point_id=["1", "1", "2", "3"]), "tie point '2' is seen by only one image"),
    (_obs(image=["a.tif", "a.tif", "a.tif", "b.tif"]), "point '1' is measured twice in image 'a.tif'"),
    (_obs(lon=[5.2, 5.3, np.nan, np.nan]), "GCP '1' has different lon/lat/h"),
    (_obs(kind=["gcp", "gcp", "gcp", "tie"]), "both a GCP and a tie point|has no lon/lat"),
    (_obs(kind=["gcp", "gcp", "pass", "pass"]), "kind 'pass'"),
    (_obs(role=["control", "check", "control", "witness"]), "role 'witness'"),
    (_obs(sigma=[1.0, 0.0, 1.0, 1.0]), "sigma must be positive"),
    (_obs(h=[np.nan, np.nan, np.nan, np.nan]), "1 GCP\\(s\\) without height"),
    (_obs(point_id=["1", "1", None, "2"]), "column point_id is empty on row 3"),
])
def test_validation_errors_are_one_line(table, message):
    with pytest.raises(GCPError, match=message) as err:
        validate_observations(table)
    assert "\n" not in str(err.value)


def test_kind_inferred_and_heights_from_dem():
    t = validate_observations(_obs(h=[np.nan, np.nan, np.nan, np.nan]), dem=DEM.constant(123.5))
    assert list(t["kind"]) == ["gcp", "gcp", "tie", "tie"]
    assert list(t["h"][:2]) == [123.5, 123.5] and t["h"][2:].isna().all()   # ties stay unknown
    assert list(t["image_id"]) == ["a.tif", "b.tif", "a.tif", "b.tif"]
    blank = validate_observations(_obs(kind=["", "gcp", None, "TIE"]))      # blank kinds inferred, case folded
    assert list(blank["kind"]) == ["gcp", "gcp", "tie", "tie"]


def test_outlier_levels_cumulative(tmp_path):
    t = validate_observations(_obs())
    t = flag_outliers(t, [False, True, False, False], "reject")
    t = flag_outliers(t, [False, True, True, False], "match")       # an earlier level, run later
    t = flag_outliers(t, [False, False, False, False], "reject")    # flags are never cleared
    assert list(t["outlier"]) == [False, True, True, False]
    assert list(t["outlier_level"]) == ["", "match", "match", ""]
    assert list(t["outlier_reject"]) == [False, True, False, False]
    for ext in (".csv", ".gpkg"):
        back = read_observations(write_observations(t, tmp_path / f"o{ext}"))
        pd.testing.assert_frame_equal(back, t, check_exact=True)
    with pytest.raises(GCPError, match="4 observations"):
        flag_outliers(t, [True], "snooping")


def test_gcp_points_same_geometries_as_shapely_points():
    """GCP tables are plain DataFrames; their export geometry (``to_geodataframe``) is the one ``Point(x, y)`` makes,
    also for extreme coordinates, none where lon/lat are not finite, and behaves as points (WKB, distance, pickling).
    No ctypes in the engine (no other library's internals) but libc's public ``mallopt`` (executors.keep_heap)."""
    import pathlib
    import pickle
    from shapely.geometry import Point
    from gdal_gf4cal.observations import make_gcps, to_geodataframe
    lon = np.array([0.0, -179.999999999, 1e-300, 123.456789012345678, np.nan, -0.0])
    lat = np.array([0.0, 89.5, -1e300, -33.3, 1.0, 5.0])
    table = make_gcps(lon, lat, 0.0, np.ones(6), np.ones(6))
    assert type(table) is pd.DataFrame and "geometry" not in table.columns
    got = to_geodataframe(table).geometry
    assert got.crs.to_epsg() == 4326 and got.isna().tolist() == [False] * 4 + [True, False]
    for g, x, y in zip(got, lon.tolist(), lat.tolist()):
        if not np.isfinite(x):
            continue
        ref = Point(x, y)
        assert g.geom_type == "Point" and not g.has_z
        assert g.wkb == ref.wkb
        assert (g.x, g.y) == (x, y) and g.distance(ref) == 0.0 and g.equals(ref)
        assert pickle.loads(pickle.dumps(g)).wkb == ref.wkb
    engine = pathlib.Path(__file__).resolve().parents[2] / "gdal_gf4cal"
    users = {str(p.relative_to(engine)): p.read_text(encoding="utf-8") for p in engine.rglob("*.py")
             if "ctypes" in p.read_text(encoding="utf-8")}
    # the one exception: libc's documented mallopt (executors.keep_heap), nothing else through ctypes
    heap = users.pop("executors.py", "")
    assert set(re.findall(r"ctypes\.\w+", heap)) <= {"ctypes.CDLL"} and ".mallopt" in heap or not heap
    assert users == {}, sorted(users)


def test_roles_cleaned_as_pandas_does_value_by_value():
    """The role column (filled, text, stripped, lower-cased) on distinct values is what pandas' string methods
    give value by value, also with missing values, numbers, categories and an index."""
    from gdal_gf4cal.observations import _clean_roles

    def ref(r):
        return r.fillna("control").astype(str).str.strip().str.lower()
    cases = [pd.Series(["control"] * 5), pd.Series([" Check", None, "CONTROL ", np.nan, "x"]),
             pd.Series([1, 1.0, None]), pd.Series([], dtype=object), pd.Series(["a", "b"], index=[5, 7], name="role"),
             pd.Series(pd.Categorical(["check", "control", None]))]
    for r in cases:
        got, want = _clean_roles(r), ref(r)
        assert got.equals(want) and got.dtype == want.dtype and list(got.index) == list(want.index)
