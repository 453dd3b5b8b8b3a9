"""GCP table schema, CSV/GeoPackage/GeoJSON round trips and input validation."""
from __future__ import annotations

import numpy as np
import pytest

from gdal_gf4cal import DEM, GCPError, make_gcps, read_gcps, write_gcps
from gdal_gf4cal.gcp import split_roles, to_geodataframe


@pytest.fixture
def gcps():
    rng = np.random.default_rng(0)
    return make_gcps(rng.uniform(5, 6, 12), rng.uniform(44, 45, 12), rng.uniform(0, 900, 12),
                     rng.uniform(0, 1000, 12), rng.uniform(0, 1000, 12), role="control", sigma=0.5)


@pytest.mark.parametrize("ext", [".csv", ".gpkg", ".geojson"])
def test_round_trip(gcps, tmp_path, ext):
    path = write_gcps(gcps, tmp_path / f"gcps{ext}")
    back = read_gcps(path)
    assert list(back.columns[:8]) == ["id", "lon", "lat", "h", "sample", "line", "role", "sigma"]
    assert to_geodataframe(back).crs.to_epsg() == 4326
    for c in ("lon", "lat", "h", "sample", "line", "sigma"):
        np.testing.assert_allclose(back[c], gcps[c], rtol=1e-9)
    assert list(back["id"]) == list(gcps["id"])
    np.testing.assert_allclose(to_geodataframe(back).geometry.x, gcps["lon"], rtol=1e-12)


def test_missing_height_taken_from_dem(tmp_path, srtm_path):
    (tmp_path / "g.csv").write_text("id,lon,lat,sample,line\nA,5.2,44.2,10,20\nB,5.3,44.3,30,40\n")
    with pytest.raises(GCPError, match="without height"):
        read_gcps(tmp_path / "g.csv")
    dem = DEM.from_file(srtm_path, geoid="egm96")
    g = read_gcps(tmp_path / "g.csv", dem=dem)
    np.testing.assert_allclose(g["h"], dem.height(g["lon"].to_numpy(), g["lat"].to_numpy()))


@pytest.mark.parametrize("text, message", [
    ("id,lon,lat,h,sample\n1,5,44,0,3\n", "missing column"),
    ("id,lon,lat,h,sample,line\n1,5,44,0,x,2\n", "non-numeric"),
    ("id,lon,lat,h,sample,line\n1,5,44,0,1,2\n1,5,44,0,1,2\n", "duplicate"),
    ("id,lon,lat,h,sample,line,role\n1,5,44,0,1,2,ctrl\n", "role"),
    ("id,lon,lat,h,sample,line\n1,500000,4900000,0,1,2\n", "WGS84"),
    ("id,lon,lat,h,sample,line\n", "no GCPs"),
])
def test_bad_tables_are_clear_errors(tmp_path, text, message):
    (tmp_path / "bad.csv").write_text(text)
    with pytest.raises(GCPError, match=message):
        read_gcps(tmp_path / "bad.csv")


def test_missing_file():
    with pytest.raises(GCPError, match="not found"):
        read_gcps("/nonexistent/gcps.csv")


def test_split_roles_is_seeded(gcps):
    a = split_roles(gcps, 0.25, seed=3)
    b = split_roles(gcps, 0.25, seed=3)
    assert (a["role"] == "check").sum() == 3
    assert list(a["role"]) == list(b["role"])


def test_heights_missing_under_a_nan_policy_dem_are_an_error_not_nan(tmp_path, srtm_path):
    """A DEM opened with nodata="nan" must not hand a GCP a NaN height silently."""
    (tmp_path / "g.csv").write_text("id,lon,lat,sample,line\nA,5.2,44.2,10,20\nB,9.5,44.3,30,40\n")
    with pytest.raises(GCPError, match="no height under 1 GCP"):
        read_gcps(tmp_path / "g.csv", dem=DEM.from_file(srtm_path, nodata="nan"))


def test_infinite_image_coordinates_are_rejected(tmp_path):
    (tmp_path / "g.csv").write_text("id,lon,lat,h,sample,line\nA,5.2,44.2,0,inf,20\n")
    with pytest.raises(GCPError, match="column sample"):
        read_gcps(tmp_path / "g.csv")


def test_write_refuses_an_existing_file_with_a_project_error(gcps, tmp_path):
    from gdal_gf4cal import Gf4calError
    path = write_gcps(gcps, tmp_path / "g.csv")
    with pytest.raises(Gf4calError, match="exists"):
        write_gcps(gcps, path, overwrite=False)
