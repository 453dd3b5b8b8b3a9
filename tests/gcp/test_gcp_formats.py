"""GCP sources beyond CSV (QGIS .points, raster GCPs, layers in any CRS), DEM heights, role assignment."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pyproj
import pytest
from osgeo import gdal

from gdal_gf4cal import DEM, GCPError, read_gcps
from gdal_gf4cal.gcp_formats import (assign_roles, leave_one_out_splits, read_gcp_layer, read_gcps_any,
                                     read_points_file, read_raster_gcps)

gdal.UseExceptions()
UTM31 = "EPSG:32631"


@pytest.fixture(scope="module")
def truth():
    """Twelve ground points around Mont Ventoux (inside the real SRTM tile) with image positions."""
    rng = np.random.default_rng(0)
    lon = rng.uniform(5.15, 5.35, 12)
    lat = rng.uniform(44.12, 44.25, 12)
    return pd.DataFrame({"id": [f"T{i}" for i in range(12)], "lon": lon, "lat": lat,
                         "sample": rng.uniform(0, 5000, 12), "line": rng.uniform(0, 5000, 12)})


def _utm(lon, lat):
    return pyproj.Transformer.from_crs("EPSG:4326", UTM31, always_xy=True).transform(lon, lat)


def test_points_file_with_crs_and_heights_from_dem_geoid(tmp_path, truth, srtm_path):
    x, y = _utm(truth.lon.to_numpy(), truth.lat.to_numpy())
    wkt = pyproj.CRS(UTM31).to_wkt()
    rows = [f"{a!r},{b!r},{s!r},{-l!r},{1 if i != 3 else 0},0,0,0"
            for i, (a, b, s, l) in enumerate(zip(x, y, truth["sample"], truth["line"]))]
    path = tmp_path / "scene.tif.points"
    path.write_text(f"#CRS: {wkt}\nmapX,mapY,sourceX,sourceY,enable,dX,dY,residual\n" + "\n".join(rows) + "\n")
    with pytest.raises(GCPError, match="without height"):
        read_points_file(path)
    dem = DEM.from_file(srtm_path, geoid="egm96")
    g = read_gcps_any(path, dem=dem)
    assert len(g) == 11                                      # the disabled point is dropped
    keep = np.arange(12) != 3
    assert np.allclose(g["lon"], truth.lon[keep], atol=1e-9) and np.allclose(g["lat"], truth.lat[keep], atol=1e-9)
    assert np.allclose(g["sample"], truth["sample"][keep]) and np.allclose(g["line"], truth["line"][keep])
    ortho = DEM.from_file(srtm_path).height(g["lon"].to_numpy(), g["lat"].to_numpy())
    assert np.allclose(g["h"], dem.height(g["lon"].to_numpy(), g["lat"].to_numpy()))
    assert np.all((g["h"] - ortho > 45) & (g["h"] - ortho < 55))   # EGM96 undulation applied, not ignored
    assert set(g["role"]) == {"control"} and "geometry" not in g.columns   # plain table, geometry at export
    # Disabled rows can become check points instead; read_gcps dispatches .points here.
    g2 = read_points_file(path, dem=dem, disabled="check")
    assert (g2["role"] == "check").sum() == 1 and len(g2) == 12
    assert len(read_gcps(path, dem=dem)) == 11


def test_points_file_without_crs(tmp_path, truth):
    body = "\n".join(f"{a},{b},{s},{-l},1" for a, b, s, l in
                     zip(truth.lon, truth.lat, truth["sample"], truth["line"]))
    p = tmp_path / "geo.points"
    p.write_text("mapX,mapY,sourceX,sourceY,enable\n" + body + "\n")
    g = read_points_file(p, dem=DEM.constant(100.0))
    assert np.allclose(g["lon"], truth.lon) and np.allclose(g["h"], 100.0)
    x, y = _utm(truth.lon.to_numpy(), truth.lat.to_numpy())
    p2 = tmp_path / "utm.points"
    p2.write_text("mapX,mapY,sourceX,sourceY,enable\n" + "\n".join(f"{a},{b},1,-1,1" for a, b in zip(x, y)))
    with pytest.raises(GCPError, match="CRS is unknown"):
        read_points_file(p2, dem=DEM.constant(0.0))
    g = read_points_file(p2, dem=DEM.constant(0.0), crs=UTM31)
    assert np.allclose(g["lat"], truth.lat, atol=1e-9)
    bad = tmp_path / "bad.points"
    bad.write_text("a,b,c\n1,2,3\n")
    with pytest.raises(GCPError, match="not a QGIS .points"):
        read_points_file(bad)
    with pytest.raises(GCPError, match="cannot open the image"):            # one line, not a GDAL traceback
        read_points_file(p, dem=DEM.constant(0.0), image=str(tmp_path / "missing.tif"))


def test_raster_gcps(tmp_path, truth):
    x, y = _utm(truth.lon.to_numpy(), truth.lat.to_numpy())
    src = tmp_path / "plain.tif"
    gdal.GetDriverByName("GTiff").Create(str(src), 50, 50, 1)
    gcps = [gdal.GCP(float(a), float(b), float(z), float(s), float(l), "", f"G{i}")
            for i, (a, b, z, s, l) in enumerate(zip(x, y, np.linspace(200, 800, 12), truth["sample"], truth["line"]))]
    out = tmp_path / "with_gcps.tif"
    gdal.Translate(str(out), str(src), GCPs=gcps, outputSRS=UTM31)
    g = read_gcps_any(out)
    assert list(g["id"]) == [str(i) for i in range(1, 13)]     # GeoTIFF tie points carry no ids
    vrt = tmp_path / "with_gcps.vrt"                            # a VRT GCPList keeps them
    vds = gdal.GetDriverByName("VRT").CreateCopy(str(vrt), gdal.Open(str(src)))
    vds.SetGCPs(gcps, pyproj.CRS(UTM31).to_wkt())
    vds = None
    assert list(read_gcps_any(vrt)["id"]) == [f"G{i}" for i in range(12)]
    assert np.allclose(g["lon"], truth.lon, atol=1e-9) and np.allclose(g["h"], np.linspace(200, 800, 12))
    assert np.allclose(g["sample"], truth["sample"]) and np.allclose(g["line"], truth["line"])
    # Z = 0 everywhere means "no height": taken from the DEM.
    gcps0 = [gdal.GCP(g_.GCPX, g_.GCPY, 0.0, g_.GCPPixel, g_.GCPLine, "", g_.Id) for g_ in gcps]
    out0 = tmp_path / "no_z.tif"
    gdal.Translate(str(out0), str(src), GCPs=gcps0, outputSRS=UTM31)
    with pytest.raises(GCPError, match="without height"):
        read_raster_gcps(out0)
    assert np.allclose(read_raster_gcps(out0, dem=DEM.constant(42.0))["h"], 42.0)
    with pytest.raises(GCPError, match="no embedded GCPs"):
        read_raster_gcps(src)


def test_layer_in_projected_crs_with_z_and_aliases(tmp_path, truth):
    import geopandas as gpd
    from shapely.geometry import Point
    x, y = _utm(truth.lon.to_numpy(), truth.lat.to_numpy())
    gdf = gpd.GeoDataFrame({"name": truth["id"], "col": truth["sample"], "row": truth["line"]},
                           geometry=[Point(a, b, 300.0 + i) for i, (a, b) in enumerate(zip(x, y))], crs=UTM31)
    p = tmp_path / "gcps_utm.gpkg"
    gdf.to_file(p, driver="GPKG")
    g = read_gcps_any(p)
    assert list(g["id"]) == list(truth["id"])
    assert np.allclose(g["lon"], truth.lon, atol=1e-9) and np.allclose(g["h"], 300.0 + np.arange(12))
    assert np.allclose(g["sample"], truth["sample"])
    gj = tmp_path / "gcps.geojson"
    gpd.GeoDataFrame({"sample": truth["sample"], "line": truth["line"], "height": 5.0},
                     geometry=gpd.points_from_xy(x, y), crs=UTM31).to_file(gj, driver="GeoJSON")
    g = read_gcp_layer(gj)
    assert np.allclose(g["h"], 5.0) and np.allclose(g["lat"], truth.lat, atol=1e-9)
    nofields = tmp_path / "nofields.gpkg"
    gpd.GeoDataFrame({"a": np.arange(12)}, geometry=gpd.points_from_xy(x, y), crs=UTM31).to_file(nofields)
    with pytest.raises(GCPError, match="'sample' and 'line'"):
        read_gcp_layer(nofields)


def test_roles_check_fraction_seeded_spread_and_leave_one_out(truth):
    base = truth.assign(h=0.0)
    a = assign_roles(base, 0.25, seed=3)
    b = assign_roles(base, 0.25, seed=3)
    c = assign_roles(base, 0.25, seed=4)
    assert (a["role"] == "check").sum() == 3
    assert list(a["role"]) == list(b["role"])
    assert any(list(assign_roles(base, 0.25, seed=k)["role"]) != list(a["role"]) for k in range(4, 10))
    assert list(assign_roles(base, None)["role"]) == ["control"] * 12
    big = pd.DataFrame({"sample": np.repeat(np.arange(10) * 100.0, 10), "line": np.tile(np.arange(10) * 100.0, 10)})
    r = assign_roles(big, 0.2, seed=0)
    chk = r[r.role == "check"]
    assert len(chk) == 20
    # Spread: check points in every quadrant of the image.
    quad = (chk["sample"] >= 500).astype(int) * 2 + (chk["line"] >= 500).astype(int)
    assert set(quad) == {0, 1, 2, 3}
    with pytest.raises(GCPError):
        assign_roles(base, 1.0)
    splits = list(leave_one_out_splits(base.assign(role="control")))
    assert [s[0] for s in splits] == list(truth["id"])
    assert all((t["role"] == "check").sum() == 1 for _, t in splits)
