"""``gf4cal ortho`` / ``refine --ortho`` on a simulated, rendered GF-4 scene whose DEM is in a compound CRS (EGM96).

Truth: the simulator's noise-free image position of every GCP (``truth_sample``, ``truth_line``). The error of the
ortho is measured ON the ortho: a coordinate image (band 1 = sample, band 2 = line of each pixel centre, GDAL
convention) carrying the refined RPC is orthorectified on the same grid, and each check point's true image position
is located in it (Newton on the bilinear ortho); its distance to the GCP's ground position, in ortho pixels, is the
error. The ortho must also equal ``gdalwarp -rpc -to RPC_DEM=<ellipsoidal DEM>`` (the simulator's own DEM).
"""
from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pyproj
import pytest
from osgeo import gdal
from scipy.ndimage import binary_erosion, map_coordinates

from rasters import write_geoid_dem
from gdal_gf4cal.cli import main
from gdal_gf4cal.geoid import GeoidGridMissing, find_grid, resolve_geoid
from gdal_gf4cal.rpc import RPCModel
from gdal_gf4cal.simulate import write_scene
from gdal_gf4cal.workflows import orthorectify

gdal.UseExceptions()
RES_M = 50.0


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("ortho")
    write_scene("gf4", d / "s", seed=3, size=(256, 256), n_gcps=24, gcp_noise_px=0.2, check_fraction=0.4,
                render=True, tile=256, reference_ortho=False)
    write_geoid_dem(d / "s" / "dem.tif", d / "dem_egm96.tif", 5773)
    write_geoid_dem(d / "s" / "dem.tif", d / "dem_egm2008.tif", 3855)   # mislabelled on purpose: only the label matters
    return d


@pytest.fixture(scope="module")
def refined(scene):
    s = scene / "s"
    out = scene / "run"
    out.mkdir()
    rc = main(["refine", str(s / "scene.tif"), "--gcps", str(s / "gcps.csv"), "--model", "affine", "--dem",
               str(scene / "dem_egm96.tif"), "--out", str(out / "refined.vrt"), "--ortho", str(out / "ortho.tif"),
               "--res", str(RES_M), "--report", str(out / "report.json"), "--residuals", str(out / "res.gpkg")])
    assert rc == 0
    return out


def _coordinate_image(scene: Path, rpc: RPCModel, path: Path) -> Path:
    """A 2-band float raster of the scene's size: the GDAL image coordinates of each pixel centre, with ``rpc``."""
    src = gdal.Open(str(scene / "s" / "scene.tif"))
    W, H = src.RasterXSize, src.RasterYSize
    ds = gdal.GetDriverByName("GTiff").Create(str(path), W, H, 2, gdal.GDT_Float64)
    ds.GetRasterBand(1).WriteArray(np.tile(np.arange(W) + 0.5, (H, 1)))
    ds.GetRasterBand(2).WriteArray(np.tile((np.arange(H) + 0.5)[:, None], (1, W)))
    ds.SetMetadata(rpc.to_gdal_metadata(), "RPC")
    ds = None
    return path


def _read(path):
    ds = gdal.Open(str(path))
    return ds.ReadAsArray().astype(float), ds.GetGeoTransform(), ds.GetSpatialRef().GetAuthorityCode(None)


def test_refine_ortho_check_points_on_the_ortho(scene, refined):
    rpc = RPCModel.from_file(refined / "refined.vrt")
    ortho, gt, epsg = _read(refined / "ortho.tif")
    assert gt[1] == RES_M and -gt[5] == RES_M and ortho.std() > 10       # a rendered scene, on a 50 m grid
    coords = _coordinate_image(scene, rpc, scene / "coords.tif")
    orthorectify(coords, dem=scene / "dem_egm96.tif", out=scene / "coords_ortho.tif", res_m=RES_M)
    xy, gt_c, epsg_c = _read(scene / "coords_ortho.tif")
    assert gt_c == gt and epsg_c == epsg and xy.shape[1:] == ortho.shape
    gcps = pd.read_csv(scene / "s" / "gcps.csv")
    chk = gcps[gcps["role"] == "check"]
    assert len(chk) >= 6
    x, y = pyproj.Transformer.from_crs("EPSG:4326", f"EPSG:{epsg}", always_xy=True).transform(
        chk["lon"].to_numpy(), chk["lat"].to_numpy())
    c0 = (np.asarray(x) - gt[0]) / gt[1]                  # ortho pixel coordinates (GDAL convention)
    r0 = (np.asarray(y) - gt[3]) / gt[5]
    target = np.vstack([chk["truth_sample"].to_numpy(), chk["truth_line"].to_numpy()])

    def sample(c, r):     # bilinear, pixel centres at integer + 0.5
        return np.vstack([map_coordinates(xy[b], [r - 0.5, c - 0.5], order=1) for b in (0, 1)])

    c, r = c0.copy(), r0.copy()
    for _ in range(6):                                    # Newton: where the ortho shows the true image point
        f = sample(c, r) - target
        dc = (sample(c + 0.5, r) - sample(c - 0.5, r))
        dr = (sample(c, r + 0.5) - sample(c, r - 0.5))
        det = dc[0] * dr[1] - dc[1] * dr[0]
        c -= (dr[1] * f[0] - dr[0] * f[1]) / det
        r -= (-dc[1] * f[0] + dc[0] * f[1]) / det
    err_px = np.hypot(c - c0, r - r0)
    assert np.all(np.abs(sample(c, r) - target) < 1e-3)
    rms = float(np.sqrt(np.mean(err_px ** 2)))
    assert rms <= 0.5, (rms, err_px)


def test_ortho_equals_gdalwarp_with_the_ellipsoidal_dem(scene, refined):
    rpc = RPCModel.from_file(refined / "refined.vrt")
    ortho, gt, epsg = _read(refined / "ortho.tif")
    ny, nx = ortho.shape
    te = [str(v) for v in (gt[0], gt[3] + gt[5] * ny, gt[0] + gt[1] * nx, gt[3])]
    common = ["gdalwarp", "-q", "-rpc", "-to", f"RPC_DEM={scene / 's' / 'dem.tif'}", "-to",
              "RPC_DEMINTERPOLATION=bilinear", "-t_srs", f"EPSG:{epsg}", "-te", *te, "-tr", str(RES_M), str(RES_M),
              "-r", "bilinear"]
    subprocess.run(common + [str(refined / "refined.vrt"), str(scene / "gdalwarp_scene.tif")], check=True)
    ref, gt_r, _ = _read(scene / "gdalwarp_scene.tif")
    assert gt_r == gt
    assert np.mean(np.abs(ref - ortho)) < 0.05 and np.abs(ref - ortho).max() <= 1     # Byte rounding at most
    # Geometric agreement: the coordinate image through both warps, to 0.01 px.
    coords = _coordinate_image(scene, rpc, scene / "coords2.tif")
    subprocess.run(common + [str(coords), str(scene / "gdalwarp_coords.tif")], check=True)
    orthorectify(coords, dem=scene / "dem_egm96.tif", out=scene / "coords2_ortho.tif", res_m=RES_M)
    a, _, _ = _read(scene / "gdalwarp_coords.tif")
    b, gt_b, _ = _read(scene / "coords2_ortho.tif")
    assert gt_b == gt
    valid = binary_erosion((a[0] > 0) & (b[0] > 0), iterations=2)
    assert valid.sum() > 0.5 * valid.size
    diff = np.abs(a - b)[:, valid]
    assert diff.max() < 0.01, diff.max()


def test_egm2008_without_grid_refused_nothing_written(scene, capsys):
    if find_grid("egm2008")[0] is not None:
        pytest.skip("an EGM2008 grid is installed here")
    out = scene / "refused"
    out.mkdir()
    rc = main(["refine", str(scene / "s" / "scene.tif"), "--gcps", str(scene / "s" / "gcps.csv"), "--model",
               "translation", "--dem", str(scene / "dem_egm2008.tif"), "--out", str(out / "r.vrt"), "--ortho",
               str(out / "o.tif")])
    err = capsys.readouterr().err
    assert rc == 2
    assert "us_nga_egm08_25.tif" in err and "--geoid PATH" in err and err.count("\n") == 1
    assert list(out.iterdir()) == []
    rc = main(["ortho", str(scene / "s" / "scene.tif"), "--dem", str(scene / "dem_egm2008.tif"), "--out",
               str(out / "o.tif")])
    err = capsys.readouterr().err
    assert rc == 2 and "us_nga_egm08_25.tif" in err and list(out.iterdir()) == []
    with pytest.raises(GeoidGridMissing) as info:           # the library's neutral wording
        orthorectify(scene / "s" / "scene.tif", dem=scene / "dem_egm2008.tif", out=out / "o.tif")
    assert "geoid=<grid path>" in str(info.value) and info.value.grids[0] == "us_nga_egm08_25.tif"
    # --geoid none: the heights are used as they are (the user's choice), and the ortho is written
    assert main(["ortho", str(scene / "s" / "scene.tif"), "--dem", str(scene / "dem_egm2008.tif"), "--geoid",
                 "none", "--out", str(out / "o.tif"), "--res", "100"]) == 0
    assert gdal.Open(str(out / "o.tif")).GetGeoTransform()[1] == 100.0


def test_geoid_grid_found_under_proj_current_name(tmp_path, monkeypatch):
    grid = tmp_path / "us_nga_egm08_25.tif"
    grid.write_bytes(b"x")                     # only its name is looked up here
    monkeypatch.setenv("PROJ_DATA", str(tmp_path))
    path, names, dirs = find_grid("egm2008")
    assert path == str(grid) and names[0] == "us_nga_egm08_25.tif" and str(tmp_path) in dirs
    assert resolve_geoid("egm2008") == str(grid)
    assert resolve_geoid("none") is None and resolve_geoid("auto") is None
    assert resolve_geoid(str(grid)) == str(grid)


def test_ortho_geoid_changes_the_ortho(scene):
    """Heights above EGM96 (N about -34 m) used as ellipsoidal move the ortho: the geoid is applied."""
    a = scene / "o_auto.tif"
    b = scene / "o_none.tif"
    ra = orthorectify(scene / "s" / "scene.tif", dem=scene / "dem_egm96.tif", out=a, res_m=RES_M)
    rb = orthorectify(scene / "s" / "scene.tif", dem=scene / "dem_egm96.tif", out=b, res_m=RES_M, geoid="none")
    assert ra["geoid"]["name"] == "egm96_15.gtx" and "geoid" not in rb
    e = scene / "o_ell.tif"
    orthorectify(scene / "s" / "scene.tif", dem=scene / "s" / "dem.tif", out=e, res_m=RES_M)
    va, vb, ve = (gdal.Open(str(p)).ReadAsArray().astype(float) for p in (a, b, e))
    assert va.shape == ve.shape and np.mean(np.abs(va - ve)) < 0.05
    if va.shape == vb.shape:
        assert np.mean(np.abs(va - vb)) > 1.0


def test_residual_arrows_are_rpc_ground_offsets_in_metres(refined):
    """One exaggeration for before/after; arrow length = factor x the RPC ground offset (m) in res_m_*."""
    from osgeo import ogr
    geod = pyproj.Geod(ellps="WGS84")
    ds = ogr.Open(str(refined / "res.gpkg"))
    gcps = {f["id"]: f for f in ds.GetLayerByName("gcps")}
    factors = set()
    for layer, epoch in (("residual_vectors", "after"), ("residual_vectors_before", "before")):
        for f in ds.GetLayerByName(layer):
            g = f.GetGeometryRef()
            (x0, y0), (x1, y1) = g.GetPoint_2D(0), g.GetPoint_2D(1)
            length_m = geod.inv(x0, y0, x1, y1)[2]
            factors.add(f["exaggeration"])
            assert length_m == pytest.approx(f["exaggeration"] * gcps[f["id"]][f"res_m_{epoch}"], rel=0.01)
    assert len(factors) == 1
    before = np.array([f["res_m_before"] for f in gcps.values()])
    after = np.array([f["res_m_after"] for f in gcps.values()])
    assert np.sqrt(np.mean(after ** 2)) < 0.3 * np.sqrt(np.mean(before ** 2))     # the gain, in metres


def test_valid_pixels_equal_to_nodata_are_lifted_not_hidden(scene, tmp_path):
    """An image without a no-data value gets 0 as the ortho's; its own dark 0 pixels inside the footprint are
    written as 1 (the next value), as GDAL's warper does from 3.11, and the run says so: QGIS would draw a pixel
    equal to the no-data value transparent even where the mask says valid. The collar stays 0 and masked."""
    src = gdal.Open(str(scene / "s" / "scene.tif"))
    image = tmp_path / "dark.tif"
    ds = gdal.GetDriverByName("GTiff").CreateCopy(str(image), src)
    ds.GetRasterBand(1).DeleteNoDataValue()                     # the simulator declares 0; a product may not
    data = ds.GetRasterBand(1).ReadAsArray()
    assert data.min() > 0
    data[100:140, 100:140] = 0                                   # a dark patch inside the scene
    ds.GetRasterBand(1).WriteArray(data)
    ds = None
    rep = orthorectify(image, dem=scene / "dem_egm96.tif", out=tmp_path / "o.tif", res_m=RES_M, resampling="near")
    o = gdal.Open(str(tmp_path / "o.tif"))
    band = o.GetRasterBand(1)
    values, valid = band.ReadAsArray(), band.GetMaskBand().ReadAsArray() > 0
    assert band.GetNoDataValue() == 0.0 and rep["nodata"] == 0.0
    assert not np.any(values[valid] == 0)                        # no valid pixel reads as no-data
    assert np.all(values[~valid] == 0) and (~valid).any()        # the collar: 0 and masked
    lifted = int(np.sum(values[valid] == 1))
    assert any(f"{lifted} valid pixel(s) of the ortho equal to its no-data value 0 were written as 1" in w
               for w in rep["warnings"]), rep["warnings"]
    # the rest of the ortho is the ortho of the image without the patch
    ds = gdal.GetDriverByName("GTiff").CreateCopy(str(tmp_path / "plain.tif"), src)
    ds.GetRasterBand(1).DeleteNoDataValue()
    ds = None
    plain = orthorectify(tmp_path / "plain.tif", dem=scene / "dem_egm96.tif", out=tmp_path / "p.tif", res_m=RES_M,
                         resampling="near")
    assert not any("no-data value" in w for w in plain["warnings"])
    p = gdal.Open(str(tmp_path / "p.tif")).ReadAsArray()
    changed = values != p                                       # the patch, now 1 instead of 0
    assert np.all(values[changed] == 1) and int(changed.sum()) == lifted > 100


@pytest.mark.parametrize("gdal_type, nodata, expected", [
    (gdal.GDT_Byte, 255, 254),
    (gdal.GDT_UInt16, 0, 1),
    (gdal.GDT_Float32, 0.0, float(np.nextafter(np.float32(0), np.float32(1)))),   # 1.4e-45
    (gdal.GDT_Int16, 1e10, None),
    (gdal.GDT_Float32, 1e40, None)])                 # inf in float32: an infinite pixel is not no-data
def test_lift_valid_nodata_next_value_of_the_type(tmp_path, gdal_type, nodata, expected):
    """The next value of the band's type (the one below at its maximum; the smallest step for floats); a no-data
    value no pixel of the type can hold changes nothing. Masked pixels keep the no-data value."""
    from gdal_gf4cal.workflows.ortho import lift_valid_nodata
    ds = gdal.GetDriverByName("GTiff").Create(str(tmp_path / "b.tif"), 600, 5, 2, gdal_type,
                                              ["TILED=YES", "BLOCKXSIZE=256", "BLOCKYSIZE=256"])
    ds.CreateMaskBand(gdal.GMF_PER_DATASET)
    fill = nodata if expected is not None else (np.inf if gdal_type == gdal.GDT_Float32 else 0)
    a = np.full((5, 600), fill)
    a[:, ::2] = 7
    mask = np.full((5, 600), 255, np.uint8)
    mask[0] = 0
    for i in (1, 2):
        ds.GetRasterBand(i).WriteArray(a)
    ds.GetRasterBand(1).GetMaskBand().WriteArray(mask)
    n, value = lift_valid_nodata(ds, nodata)
    if expected is None:
        assert n == 0
        return
    assert n == 2 * 4 * 300 and value == expected
    for i in (1, 2):
        b = ds.GetRasterBand(i).ReadAsArray()
        assert np.all(b[1:, 1::2] == np.asarray(expected, b.dtype)) and np.all(b[0, 1::2] == nodata)
        assert np.all(b[:, ::2] == 7)


def test_ortho_deflate_predictor_by_type(refined):
    """The ortho's DEFLATE has the predictor of its type: horizontal differencing for integers (the rendered scene),
    the floating-point one for floats, none for complex (GDAL has none)."""
    from gdal_gf4cal.workflows.ortho import creation_options
    structure = gdal.Open(str(refined / "ortho.tif")).GetMetadata("IMAGE_STRUCTURE")
    assert structure["COMPRESSION"] == "DEFLATE" and structure["PREDICTOR"] == "2"
    assert "PREDICTOR=3" in creation_options(gdal.GDT_Float64) and "PREDICTOR=2" in creation_options(gdal.GDT_UInt16)
    assert not any(o.startswith("PREDICTOR=") for o in creation_options(gdal.GDT_CFloat32))


# With overviews not at 2x: which level gdalwarp takes there flips with the last digit of the resolution.
@pytest.mark.parametrize("res_factor, resampling, overviews", [
    (1.0, "bilinear", False), (2.0, "bilinear", False), (3.3, "bilinear", False), (1.0, "cubic", False),
    (2.0, "lanczos", False), (2.4, "bilinear", True), (3.3, "cubic", True)])
def test_real_crop_ortho_equals_gdalwarp_whatever_the_chunks(tmp_path, res_factor, resampling, overviews):
    """The real Pleiades crops as delivered (each beside its .geom, SRTM heights as they are): ``gf4cal ortho``
    equals ``gdalwarp -rpc`` of the same image and RPC on its grid pixel for pixel, at GDAL's resolution and coarser,
    bilinear, cubic and lanczos, from the image's overviews as gdalwarp does when it has some (the resampling
    kernel's scale is the whole ortho's, not each warped block's: 512 x 128 blocks had widened the kernel along y,
    51-82 % of the pixels off, up to 50 DN; the full image's size where GDAL warps from an overview, 98 %)."""
    from ventouxpair import SRTM, pair
    from gdal_gf4cal.crop import image_rpc
    from gdal_gf4cal.threads import limit
    for image in pair(tmp_path / "in"):
        model, _ = image_rpc(str(image), None)                 # the product's RPC moved to the crop
        if overviews:                                          # gdalwarp warps a coarser ortho from one of them
            ds = gdal.Open(str(image), gdal.GA_Update)
            ds.BuildOverviews("AVERAGE", [2, 4])
            ds = None
        out = tmp_path / f"{image.stem}.tif"
        orthorectify(image, dem=SRTM, out=out, geoid="none", resampling=resampling)
        if res_factor != 1.0:                                  # coarser than GDAL's choice: the kernel widens
            res = round(res_factor * _read(out)[1][1], 3)
            out = tmp_path / f"{image.stem}_{res_factor}.tif"
            orthorectify(image, dem=SRTM, out=out, geoid="none", res_m=res, resampling=resampling)
        ortho, gt, epsg = _read(out)
        ny, nx = ortho.shape
        src = tmp_path / f"{image.stem}_rpc.vrt"
        gdal.Translate(str(src), str(image), format="VRT")
        vrt = gdal.Open(str(src), gdal.GA_Update)
        vrt.SetMetadata(model.to_gdal_metadata(), "RPC")
        vrt = None
        ref_path = tmp_path / f"{image.stem}_{res_factor}_gdalwarp.tif"
        gdal.Warp(str(ref_path), str(src), rpc=True, dstSRS=f"EPSG:{epsg}", resampleAlg=resampling,
                  outputBounds=(gt[0], gt[3] + gt[5] * ny, gt[0] + gt[1] * nx, gt[3]), xRes=gt[1], yRes=-gt[5],
                  transformerOptions=[f"RPC_DEM={SRTM}", "RPC_DEMINTERPOLATION=bilinear",
                                      "RPC_DEM_APPLY_VDATUM_SHIFT=FALSE"])
        ref, gt_r, _ = _read(ref_path)
        assert gt_r == gt and ny > 128                                       # more than one warped block of rows
        ds = gdal.Open(str(out))
        valid = ds.GetRasterBand(1).GetMaskBand().ReadAsArray() > 0
        ds = None
        assert valid.mean() > 0.3
        bad = ortho[valid] != ref[valid]
        assert not bad.any(), (image.stem, res_factor, ny, bad.mean(), np.abs(ortho - ref)[valid].max())
        if res_factor == 1.0:                                  # GDAL's warp on two threads: the same pixels
            with limit(2):
                orthorectify(image, dem=SRTM, out=tmp_path / f"{image.stem}_2t.tif", geoid="none",
                             resampling=resampling)
            np.testing.assert_array_equal(_read(tmp_path / f"{image.stem}_2t.tif")[0], ortho)


@pytest.mark.parametrize("dst", [(49, 71), (48, 50), (50, 33), (120, 97), (26, 100)])
def test_kernel_scales_are_gdals_for_one_chunk(dst):
    """``kernel_scales`` gives the scales GDAL's warp kernel computes for a one-chunk warp (a textured 100 x 100
    image downsampled or upsampled onto ``dst`` px): passing them as XSCALE / YSCALE changes no pixel, and the
    unsnapped ratio does where GDAL snaps it (1 / r within 0.05 of an integer) below 0.95."""
    from gdal_gf4cal.workflows.ortho import kernel_scales
    rng = np.random.default_rng(5)
    src = gdal.GetDriverByName("MEM").Create("", 100, 100, 1, gdal.GDT_Float32)
    src.SetGeoTransform((0.0, 1.0, 0.0, 100.0, 0.0, -1.0))
    src.GetRasterBand(1).WriteArray(rng.normal(size=(100, 100)).astype(np.float32))

    def warp(options):
        return gdal.Warp("", src, format="MEM", outputBounds=(0, 0, 100, 100), width=dst[0], height=dst[1],
                         resampleAlg="bilinear", warpOptions=options).ReadAsArray()

    scales = kernel_scales(dst, (100, 100))
    np.testing.assert_array_equal(warp([f"XSCALE={scales[0]!r}", f"YSCALE={scales[1]!r}"]), warp([]))
    raw = (dst[0] / 100, dst[1] / 100)
    if scales != raw and min(raw) < 0.95:          # from 0.95 up bilinear takes 4 samples whatever the scale
        assert not np.array_equal(warp([f"XSCALE={raw[0]!r}", f"YSCALE={raw[1]!r}"]), warp([]))
