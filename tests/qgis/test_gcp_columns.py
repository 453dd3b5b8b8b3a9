"""The advanced GCP parameters in headless QGIS (issue 15): a header-less CSV read with a column map
(GCP_COLUMNS) gives the same GCPs as the GeoPackage it was written from, and the pixel convention
(GCP_PIXEL_CONVENTION) moves every image coordinate by exactly half a pixel between centre and corner, for a
layer and for GCPs embedded in a GeoTIFF (GCP_RASTER)."""
from __future__ import annotations

import pytest


def _assess(run_alg, files, gcps, **kw):
    res, _ = run_alg("gf4cal:assessaccuracy", {"INPUT": files["image"], "GCPS": str(gcps) if gcps else None, **kw})
    return res


@pytest.fixture
def headerless(scene, tmp_path):
    """The scene's GCPs (from the UTM GeoPackage, as the engine reads them) as a CSV without a header line, columns
    in an unusual order with one column to skip."""
    from gdal_gf4cal.gcp import read_gcps
    files, _ = scene
    g = read_gcps(files["gcps"])
    g["junk"] = "x"
    path = tmp_path / "gcps_nohdr.csv"
    g[["lat", "lon", "junk", "line", "sample", "h", "id"]].to_csv(path, index=False, header=False,
                                                                   float_format="%.12f")
    return path


def test_header_less_csv_with_column_map_reads_the_same_gcps(run_alg, scene, headerless):
    files, truth = scene
    ref = _assess(run_alg, files, files["gcps"])
    got = _assess(run_alg, files, headerless, GCP_COLUMNS="lat,lon,-,line,sample,h,id")
    assert got["N"] == ref["N"] == len(truth["ids"])
    for key in ("MEAN_SAMPLE", "MEAN_LINE", "RMS_SAMPLE", "RMS_LINE", "RMS_PLANAR"):
        assert got[key] == pytest.approx(ref[key], abs=1e-6), key


def test_header_less_csv_without_column_map_is_refused_naming_the_parameter(run_alg, scene, headerless):
    from qgis.core import QgsProcessingException
    files, _ = scene
    with pytest.raises(QgsProcessingException, match="GCP_COLUMNS"):
        _assess(run_alg, files, headerless)


@pytest.mark.parametrize("source", ["csv", "gpkg"])
def test_pixel_convention_centre_vs_corner_is_half_a_pixel(run_alg, scene, headerless, source):
    """Centres at integers (orthority, ASP) are GDAL's coordinates minus 0.5: read as centres, every GCP moves by
    +0.5 px on both axes, so the mean residual (measured - predicted) grows by exactly 0.5 px; the spread stays."""
    files, _ = scene
    kw = {"GCP_COLUMNS": "lat,lon,-,line,sample,h,id"} if source == "csv" else {}
    path = headerless if source == "csv" else files["gcps"]
    corner = _assess(run_alg, files, path, GCP_PIXEL_CONVENTION=1, **kw)
    centre = _assess(run_alg, files, path, GCP_PIXEL_CONVENTION=2, **kw)
    default = _assess(run_alg, files, path, **kw)
    assert centre["MEAN_SAMPLE"] - corner["MEAN_SAMPLE"] == pytest.approx(0.5, abs=1e-9)
    assert centre["MEAN_LINE"] - corner["MEAN_LINE"] == pytest.approx(0.5, abs=1e-9)
    assert default["MEAN_SAMPLE"] == pytest.approx(corner["MEAN_SAMPLE"], abs=1e-12)   # CSV/GPKG: GDAL's corners


def test_geotiff_gcps_centre_vs_corner_is_half_a_pixel(run_alg, scene, tmp_path):
    """GCPs embedded in a GeoTIFF (GCP_RASTER, no GCP layer): read as corners they equal the GeoPackage's; read as
    centres every GCP moves by +0.5 px on both axes (the mean residual grows by exactly 0.5 px)."""
    from osgeo import gdal
    from gdal_gf4cal.gcp import read_gcps
    files, truth = scene
    g = read_gcps(files["gcps"])
    tif = tmp_path / "with_gcps.tif"
    gdal.Translate(str(tif), files["norpc"], outputSRS="EPSG:4326", GCPs=[
        gdal.GCP(float(r.lon), float(r.lat), float(r.h), float(r.sample), float(r.line), "", str(r.id))
        for r in g.itertuples()])
    ref = _assess(run_alg, files, files["gcps"])
    corner = _assess(run_alg, files, "", GCP_RASTER=str(tif), GCP_PIXEL_CONVENTION=1)
    centre = _assess(run_alg, files, "", GCP_RASTER=str(tif), GCP_PIXEL_CONVENTION=2)
    default = _assess(run_alg, files, "", GCP_RASTER=str(tif))
    assert corner["N"] == len(truth["ids"])
    for key in ("MEAN_SAMPLE", "MEAN_LINE", "RMS_PLANAR"):
        assert corner[key] == pytest.approx(ref[key], abs=1e-6) and default[key] == corner[key], key
    assert centre["MEAN_SAMPLE"] - corner["MEAN_SAMPLE"] == pytest.approx(0.5, abs=1e-9)
    assert centre["MEAN_LINE"] - corner["MEAN_LINE"] == pytest.approx(0.5, abs=1e-9)


def test_gcp_layer_and_raster_together_or_neither_is_refused(run_alg, scene, tmp_path):
    from qgis.core import QgsProcessingException
    files, _ = scene
    with pytest.raises(QgsProcessingException, match="GCP_RASTER"):
        _assess(run_alg, files, "")
    with pytest.raises(QgsProcessingException, match="not both"):
        _assess(run_alg, files, files["gcps"], GCP_RASTER=files["image"])
