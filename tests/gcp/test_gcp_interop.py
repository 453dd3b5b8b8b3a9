"""GCP files of other tools (issue 15 "GCP interoperability"): every format reads to the same coordinates as the
CSV it was written from, in both pixel conventions.

Truth: a seeded simulated ZY-3 nadir image's GCPs (``simulate_gcps``), written once as our CSV (the reference).
Pixel conventions: ``corner`` = GDAL's (centre of the first pixel at 0.5); ``center`` = centres at integers
(orthority's ``ji``, ASP, OTB's raw indices): the same point has ``center`` coordinates 0.5 px smaller.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from osgeo import gdal, osr

from gdal_gf4cal import DEM, GCPError, read_gcps, write_gcps
from gdal_gf4cal.gcp_formats import (read_asp_gcp, read_orthority_geojson, read_points_file, write_asp_gcp,
                                     write_orthority_geojson)
from gdal_gf4cal.observations import from_gcp_views
from gdal_gf4cal.simulate import make_scene, simulate_gcps

OFFSET = {"corner": 0.0, "center": 0.5}


@pytest.fixture(scope="module")
def scene_views():
    scene = make_scene("zy3", seed=5, size=(1500, 1500))
    v = simulate_gcps(scene, n_gcps=12, gcp_noise_px=0.4, check_fraction=0.3, seed=2)
    return {f"{k}.tif": g.drop(columns="truth_outlier") for k, g in v.items()}


@pytest.fixture(scope="module")
def reference(tmp_path_factory, scene_views):
    """The nadir GCPs as our CSV, read back: what every other format must reproduce."""
    path = tmp_path_factory.mktemp("ref") / "gcps.csv"
    write_gcps(scene_views["nadir.tif"], path)
    ref = read_gcps(path)
    assert (ref["role"] == "check").any() and (ref["role"] == "control").any()
    return ref


def _same(g, ref, *, heights=True, atol_px=1e-9, ids=True):
    assert len(g) == len(ref)
    if ids:
        assert list(g["id"]) == list(ref["id"])
    assert np.allclose(g["lon"], ref["lon"], rtol=0, atol=1e-12)
    assert np.allclose(g["lat"], ref["lat"], rtol=0, atol=1e-12)
    if heights:
        assert np.allclose(g["h"], ref["h"], rtol=0, atol=1e-9)
    assert np.allclose(g["sample"], ref["sample"], rtol=0, atol=atol_px)
    assert np.allclose(g["line"], ref["line"], rtol=0, atol=atol_px)


def test_reference_is_the_truth(reference, scene_views):
    scene = make_scene("zy3", seed=5, size=(1500, 1500))
    s, ln = scene.images[0].true.project(reference["lon"].to_numpy(), reference["lat"].to_numpy(),
                                         reference["h"].to_numpy())
    assert np.allclose(s, reference["truth_sample"], atol=1e-6) and np.allclose(ln, reference["truth_line"], atol=1e-6)
    # noise 0.4 px per axis: the measured positions differ from the truth, the files must keep them exactly
    assert 0.1 < np.hypot(reference["sample"] - s, reference["line"] - ln).mean() < 1.5


# ---------------------------------------------------------------------------------------------------------------
# writers -> readers
# ---------------------------------------------------------------------------------------------------------------
def test_orthority_geojson_round_trip(tmp_path, reference):
    path = tmp_path / "gcps.geojson"
    write_gcps(reference, path, format="orthority", image="/data/nadir.tif")
    doc = json.loads(path.read_text())
    f0 = doc["features"][0]
    assert f0["properties"]["filename"] == "nadir.tif"
    assert f0["properties"]["ji"] == pytest.approx([reference["sample"][0] - 0.5, reference["line"][0] - 0.5],
                                                   abs=1e-12)          # pixel centres at integers
    assert f0["geometry"]["coordinates"] == [reference["lon"][0], reference["lat"][0], reference["h"][0]]
    g = read_gcps(path)
    _same(g, reference)
    assert list(g["role"]) == list(reference["role"]) and np.array_equal(g["sigma"], reference["sigma"])
    # Told the other convention, the same file reads 0.5 px off: the option is honoured, not ignored.
    corner = read_gcps(path, pixel_convention="corner")
    assert np.allclose(corner["sample"], reference["sample"] - 0.5, atol=1e-9)


def test_orthority_multi_image_file(tmp_path, scene_views):
    """One orthority file for several images: the image is chosen by file name."""
    path = tmp_path / "all.geojson"
    feats = []
    for name, g in scene_views.items():
        write_orthority_geojson(g, tmp_path / f"{name}.geojson", image=name)
        feats += json.loads((tmp_path / f"{name}.geojson").read_text())["features"]
    path.write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    table = read_orthority_geojson(path)
    assert len(table) == sum(len(g) for g in scene_views.values())
    assert table["point_id"].nunique() == len(scene_views["nadir.tif"])       # shared ids: one ground point each
    fwd = read_gcps(path, image="fwd.tif")
    truth = scene_views["fwd.tif"]
    assert np.allclose(fwd["sample"], truth["sample"], atol=1e-9) and list(fwd["id"]) == list(truth["id"])
    with pytest.raises(GCPError, match="3 images"):
        read_gcps(path)


@pytest.mark.parametrize("numeric_ids", [False, True])
def test_asp_gcp_round_trip(tmp_path, reference, numeric_ids):
    ref = reference.copy()
    if numeric_ids:
        ref["id"] = [str(100 + i) for i in range(len(ref))]
    path = tmp_path / "gcps.gcp"
    write_gcps(ref, path, image="nadir.tif")
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
    tok = lines[0].split()
    assert len(tok) == 12 and tok[7] == "nadir.tif"
    assert float(tok[1]) == ref["lat"][0] and float(tok[2]) == ref["lon"][0]          # lat before lon
    assert float(tok[8]) == pytest.approx(ref["sample"][0] - 0.5, abs=1e-12)         # centres at integers
    assert tok[0] == (ref["id"][0] if numeric_ids else "1")                           # ASP wants integer ids
    g = read_gcps(path)
    _same(g, ref)
    assert np.array_equal(g["sigma"], ref["sigma"])


def test_asp_multi_image_lines(tmp_path, scene_views):
    """ASP puts every image a GCP is seen in on its line: an observation table, one row per image."""
    table = from_gcp_views(scene_views)
    path = tmp_path / "block.gcp"
    write_asp_gcp(table, path)
    body = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
    assert len(body) == len(scene_views["nadir.tif"]) and all(len(ln.split()) == 7 + 5 * 3 for ln in body)
    back = read_asp_gcp(path)
    assert len(back) == len(table) and set(back["image_id"]) == set(scene_views)
    for name, g in scene_views.items():
        v = read_gcps(path, image=name)
        assert list(v["id"]) == list(g["id"])
        assert np.allclose(v["sample"], g["sample"], atol=1e-9) and np.allclose(v["line"], g["line"], atol=1e-9)


def test_points_round_trip(tmp_path, reference):
    path = tmp_path / "nadir.tif.points"
    write_gcps(reference, path)
    text = path.read_text().splitlines()
    assert text[0].startswith("#CRS: ") and text[1] == "mapX,mapY,sourceX,sourceY,enable,dX,dY,residual"
    # .points has no height: it comes back from a DEM. Check points are written disabled.
    g = read_points_file(path, disabled="check", dem=DEM.constant(0.0))
    _same(g, reference, heights=False, ids=False)
    assert list(g["role"]) == list(reference["role"])
    control = read_gcps(path, need_height=False)
    assert len(control) == (reference["role"] == "control").sum()


# ---------------------------------------------------------------------------------------------------------------
# readers of files written elsewhere, both pixel conventions
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("convention", ["corner", "center"])
@pytest.mark.parametrize("layout, columns, sep", [
    ("id sample line lon lat h", "id,sample,line,lon,lat,h", " "),              # IKONOS-style, blank-separated
    ("id lon lat h sample line", "id,lon,lat,h,sample,line", ","),               # SPOT-style order
    ("id line sample lat lon h flag", "name,row,col,latitude,longitude,height,-", ";"),
])
def test_headerless_csv(tmp_path, reference, convention, layout, columns, sep):
    off = OFFSET[convention]
    val = {"id": reference["id"], "sample": reference["sample"] - off, "line": reference["line"] - off,
           "lon": reference["lon"], "lat": reference["lat"], "h": reference["h"], "flag": ["ok"] * len(reference)}
    rows = [sep.join(f"{v!r}" if not isinstance(v, str) else v for v in r)
            for r in zip(*(val[k] for k in layout.split()))]
    path = tmp_path / "gcps.txt"
    path.write_text("\n".join(rows) + "\n")
    g = read_gcps(path, columns=columns, pixel_convention=convention)
    _same(g, reference)
    with pytest.raises(GCPError, match="no header; give its column map"):
        read_gcps(path)
    with pytest.raises(GCPError, match="names 5"):
        read_gcps(path, columns="id,sample,line,lon,lat")


@pytest.mark.parametrize("convention", ["corner", "center"])
def test_geotiff_gcps_both_conventions(tmp_path, reference, convention):
    off = OFFSET[convention]
    path = str(tmp_path / "scene.tif")
    ds = gdal.GetDriverByName("GTiff").Create(path, 1500, 1500, 1, gdal.GDT_Byte)
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(4326)
    srs.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    ds.SetGCPs([gdal.GCP(x, y, z, s - off, ln - off, "", i) for i, x, y, z, s, ln in
                zip(reference["id"], reference["lon"], reference["lat"], reference["h"], reference["sample"],
                    reference["line"])], srs)
    ds = None
    g = read_gcps(path, pixel_convention=convention)
    _same(g, reference, ids=False)                   # GeoTIFF tie points carry no ids
    if convention == "center":     # read with GDAL's default, the half-pixel bias the issue reports
        biased = read_gcps(path)
        assert np.allclose(reference["sample"] - biased["sample"], 0.5, atol=1e-9)


@pytest.mark.parametrize("convention", ["corner", "center"])
@pytest.mark.parametrize("with_height", [True, False])
def test_otb_tie_points(tmp_path, reference, convention, with_height):
    off = OFFSET[convention]
    rows = [f"{s - off!r}\t{ln - off!r}\t{x!r}\t{y!r}" + (f"\t{z!r}" if with_height else "")
            for s, ln, x, y, z in zip(reference["sample"], reference["line"], reference["lon"], reference["lat"],
                                      reference["h"])]
    path = tmp_path / "tiepoints.txt"
    path.write_text("# col row lon lat\n" + "\n".join(rows) + "\n")
    dem = None if with_height else DEM.constant(321.0)
    g = read_gcps(path, pixel_convention=convention, dem=dem)
    _same(g, reference, heights=with_height, ids=False)
    if not with_height:
        assert (g["h"] == 321.0).all()


@pytest.mark.parametrize("convention", ["corner", "center"])
def test_points_and_csv_conventions(tmp_path, reference, convention):
    """A convention given for our own CSV and a .points file shifts both the same way."""
    off = OFFSET[convention]
    shifted = reference.assign(sample=reference["sample"] - off, line=reference["line"] - off)
    write_gcps(shifted, tmp_path / "g.csv")
    _same(read_gcps(tmp_path / "g.csv", pixel_convention=convention), reference)
    write_gcps(shifted[shifted["role"] == "control"], tmp_path / "g.points")
    ctrl = reference[reference["role"] == "control"].reset_index(drop=True)
    _same(read_gcps(tmp_path / "g.points", pixel_convention=convention, dem=DEM.constant(0.0)), ctrl,
          heights=False, ids=False)


# ---------------------------------------------------------------------------------------------------------------
# files that must be refused, with one line saying what to do (rpcm's "unsupported files" list)
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name, text, kwargs, message", [
    ("bad.gcp", "1 44.1 5.2 900 1 1 1 img.tif 10.0\n", {}, "not an ASP GCP"),
    ("bad2.gcp", "1 44.1 5.2 abc 1 1 1 img.tif 10 20 1 1\n", {}, "non-numeric"),
    ("odd.geojson", json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"ji": [1.0]}, "geometry": {"type": "Point", "coordinates": [5, 44, 1]}}]}),
     {}, "not an orthority GCP"),
    ("otb.txt", "10 20 5.2\n11 21 5.3\n", {}, "no header; give its column map"),
    ("cols.txt", "1 10 20 5.2 44.1 900\n", {"columns": "id,sample,line,lon,lat,hh"}, "unknown column 'hh'"),
    ("cols2.txt", "1 10 20 5.2 44.1 900\n", {"columns": "id,sample,line,h,-,-"}, "must name sample, line and lon"),
    ("conv.csv", "id,lon,lat,h,sample,line\n1,5.2,44.1,900,10,20\n", {"pixel_convention": "middle"},
     "pixel convention must be 'center' or 'corner'"),
    ("xy.txt", "1 10 20 650000 4890000 900\n", {"columns": "id,sample,line,x,y,h"}, "need their CRS"),
])
def test_unsupported_or_malformed(tmp_path, name, text, kwargs, message):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(GCPError, match=message) as err:
        read_gcps(path, **kwargs)
    assert "\n" not in str(err.value)


def test_projected_columns_with_crs(tmp_path, reference):
    import pyproj
    tf = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:32651", always_xy=True)
    x, y = tf.transform(reference["lon"].to_numpy(), reference["lat"].to_numpy())
    path = tmp_path / "utm.dat"          # a column map reads any delimited text, whatever its extension
    path.write_text("\n".join(f"{i},{s!r},{ln!r},{a!r},{b!r},{z!r}" for i, s, ln, a, b, z in
                              zip(reference["id"], reference["sample"], reference["line"], x, y, reference["h"])))
    g = read_gcps(path, columns="id,sample,line,x,y,h", crs="EPSG:32651")
    assert np.allclose(g["lon"], reference["lon"], atol=1e-9) and np.allclose(g["lat"], reference["lat"], atol=1e-9)
    assert np.array_equal(g["sample"], reference["sample"])


def test_single_image_file_is_that_images(tmp_path, reference):
    """refine passes the scene path as ``image``: a one-image ASP file named otherwise is still its GCPs."""
    path = tmp_path / "field.gcp"
    write_gcps(reference, path, image="QB02_P001.TIF")
    g = read_gcps(path, image=str(tmp_path / "scene_rpc.vrt"))
    _same(g, reference)
