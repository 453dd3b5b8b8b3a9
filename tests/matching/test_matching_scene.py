"""Checks of the rendered test scenes (tests/matchscene.py) against GDAL's RPC transformer (issue 7)."""
from __future__ import annotations

import subprocess

import numpy as np

from matchscene import affine_rpc, build_scene, error_affine, synthetic_rpc


def test_affine_rpc_is_exact():
    rpc = synthetic_rpc((400, 300), 30.0)
    e = error_affine(shift=(50.3, -37.6), rotation_rad=0.003, scale=1.002, center=(200, 150))
    biased = affine_rpc(rpc, e)
    lon, lat = rpc.localize(np.array([10.5, 200.0, 390.2]), np.array([5.5, 150.0, 280.0]), 800.0)
    s, l_ = rpc.project(lon, lat, 800.0)
    s2, l2 = biased.project(lon, lat, 800.0)
    want = e @ np.vstack([np.ones_like(s), s, l_])
    np.testing.assert_allclose(np.vstack([s2, l2]), want, atol=1e-8)


def test_render_agrees_with_gdal_rpc_transformer(tmp_path):
    """gdalwarp -rpc of the rendered raw image (true RPC) reproduces the reference: the renderer and GDAL's
    RPC transformer agree, so scenes are geometrically what they claim (measured by phase correlation)."""
    from osgeo import gdal
    from gdal_gf4cal.matching.correlate import phase_correlate
    sc = build_scene(tmp_path, size=(256, 256), noise=0.0)
    ds = gdal.Open(sc.image, gdal.GA_Update)
    ds.SetMetadata(sc.true_rpc.to_gdal_metadata(), "RPC")
    ds = None
    ref = gdal.Open(sc.reference)
    gt = ref.GetGeoTransform()
    out = str(tmp_path / "ortho.tif")
    subprocess.run(["gdalwarp", "-q", "-rpc", "-to", f"RPC_DEM={sc.dem_path}", "-t_srs", "EPSG:32631",
                    "-te", str(gt[0]), str(gt[3] + gt[5] * ref.RasterYSize), str(gt[0] + gt[1] * ref.RasterXSize),
                    str(gt[3]), "-ts", str(ref.RasterXSize), str(ref.RasterYSize), "-r", "cubic",
                    "-dstnodata", "0", sc.image, out], check=True)
    o = gdal.Open(out).ReadAsArray().astype(float)
    r = ref.ReadAsArray().astype(float)
    cy, cx = np.array(o.shape) // 2
    win = (slice(cy - 64, cy + 64), slice(cx - 64, cx + 64))
    assert np.all(o[win] > 0)
    res = phase_correlate(r[win], o[win])
    assert res.ncc > 0.9
    assert abs(res.dx) < 0.1 and abs(res.dy) < 0.1, (res.dx, res.dy)
