"""Issue 24: the residual GeoPackage's footprint lies on the DEM (lines of sight intersected with it, as the ortho is
warped), not at the RPC's HEIGHT_OFF: on the real Pleiades Ventoux crop (500 x 500 px at product pixel (5000, 5000)
with the product's .geom; SRTM above EGM96, relief 30-70 m off the ortho at HEIGHT_OFF), `gf4cal refine --ortho
--residuals` writes a footprint within a pixel of the ortho's valid area (its internal mask)."""
from __future__ import annotations

import numpy as np
import pytest
from osgeo import gdal, ogr, osr

from gdal_gf4cal.cli import main
from ventouxcrop import GEOM, grid_gcps, write_crop

RES = 1.0


def _valid_area(ortho):
    """The ortho's valid area (its mask band > 0) as a shapely polygon in the ortho's CRS."""
    from shapely import wkt
    from shapely.affinity import affine_transform
    ds = gdal.Open(str(ortho))
    mask = ds.GetRasterBand(1).GetMaskBand()
    mem = ogr.GetDriverByName("Memory").CreateDataSource("m")
    lyr = mem.CreateLayer("v", ds.GetSpatialRef(), ogr.wkbPolygon)
    lyr.CreateField(ogr.FieldDefn("v", ogr.OFTInteger))
    gdal.Polygonize(mask, mask, lyr, 0)
    polys = [wkt.loads(f.GetGeometryRef().ExportToWkt()) for f in lyr]   # in pixels (the mask has no georef)
    x0, dx, _, y0, _, dy = ds.GetGeoTransform()
    best = max(polys, key=lambda p: p.area)
    return affine_transform(best, [dx, 0.0, 0.0, dy, x0, y0]), ds.GetSpatialRef()


def _footprint(gpkg, srs):
    from shapely import wkt
    ds = ogr.Open(str(gpkg))
    lyr = ds.GetLayerByName("footprint")
    feature = lyr.GetNextFeature()
    g = feature.GetGeometryRef().Clone()
    src = lyr.GetSpatialRef()
    src.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    srs.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    g.Transform(osr.CoordinateTransformation(src, srs))
    return wkt.loads(g.ExportToWkt())


def test_refine_footprint_lies_on_the_dem_within_a_pixel_of_the_ortho(tmp_path, srtm_path):
    crop = write_crop(tmp_path / "left_image.tif")
    grid_gcps().to_csv(tmp_path / "gcps.csv", index=False)
    assert main(["refine", str(crop), "--rpc", str(GEOM), "--gcps", str(tmp_path / "gcps.csv"), "--model",
                 "translation", "--dem", str(srtm_path), "--geoid", "egm96", "--ortho", str(tmp_path / "o.tif"),
                 "--res", str(RES), "--crs", "EPSG:32631", "--residuals", str(tmp_path / "r.gpkg"),
                 "--out", str(tmp_path / "refined.RPB")]) == 0
    valid, srs = _valid_area(tmp_path / "o.tif")
    fp = _footprint(tmp_path / "r.gpkg", srs)
    gap = fp.hausdorff_distance(valid)
    assert gap <= 1.5 * RES, gap                   # a pixel of the ortho (and half a pixel of its own edge)
    assert fp.symmetric_difference(valid).area / valid.area < 0.01
