"""Rendering through the true model (METHODS §10): built-in texture, reference rasters in any CRS, clouds."""
from __future__ import annotations

import numpy as np
import pytest
from osgeo import gdal

from gdal_gf4cal.errors import CancelledError
from gdal_gf4cal.simulate import make_scene, write_scene
from gdal_gf4cal.simulate.render import ground_of_pixels, model_bounds, render_image, write_reference_ortho, _DemGrid

gdal.UseExceptions()


@pytest.fixture(scope="module")
def gf4_crop():
    return make_scene("gf4", seed=0, size=(256, 256))


def _read(path):
    return gdal.Open(str(path)).ReadAsArray().astype(float)


def test_ground_of_pixels_matches_rigorous_dem_intersection(gf4_crop):
    m = gf4_crop.images[0].true
    lon, lat, h = ground_of_pixels(m, _DemGrid(gf4_crop.dem, model_bounds(m)), 0, 0, 256, 256)
    s, l = np.meshgrid(np.arange(256) + 0.5, np.arange(256) + 0.5)
    ps, pl = m.project(lon[::9, ::9], lat[::9, ::9], h[::9, ::9])
    assert np.max(np.hypot(ps - s[::9, ::9], pl - l[::9, ::9])) < 0.05        # ray interpolation error only
    assert np.max(np.abs(gf4_crop.dem.height(lon[::9, ::9], lat[::9, ::9]) - h[::9, ::9])) < 0.05


def test_render_texture_equals_render_from_reference_in_another_crs(gf4_crop, tmp_path):
    im = gf4_crop.images[0]
    a = render_image(im.true, gf4_crop.dem, tmp_path / "a.tif", seed=3, gsd_m=im.gsd_m, tile=128)
    # The same texture as a reference DOM (EPSG:4326, ~1/3 of the image GSD), then warped to UTM.
    b0, b1, b2, b3 = model_bounds(im.true, margin=0.1)
    ref = write_reference_ortho(tmp_path / "ref.tif", (b0, b1, b2, b3), 20.0 / 111320.0, seed=3,
                                scale_m=3.0 * im.gsd_m)
    utm = str(tmp_path / "ref_utm.tif")
    gdal.Warp(utm, ref, dstSRS="EPSG:32645", xRes=20.0, yRes=20.0, resampleAlg="bilinear")
    b = render_image(im.true, gf4_crop.dem, tmp_path / "b.tif", reference=utm, gsd_m=im.gsd_m, tile=128)
    A, B = _read(a), _read(b)
    assert A.shape == B.shape == (256, 256)
    assert np.corrcoef(A.ravel(), B.ravel())[0, 1] > 0.85
    assert A.std() > 15                                   # real texture, not a flat image


def test_render_paints_clouds_and_mask(gf4_crop, tmp_path):
    im = gf4_crop.images[0]
    render_image(im.true, gf4_crop.dem, tmp_path / "c.tif", seed=1, gsd_m=im.gsd_m, paint_clouds=0.25,
                 cloud_mask_path=str(tmp_path / "mask.tif"), tile=128)
    mask = _read(tmp_path / "mask.tif") > 0
    img = _read(tmp_path / "c.tif")
    assert 0.1 < mask.mean() < 0.4
    assert img[mask].mean() > 240 > img[~mask].mean()


def test_render_cancel_leaves_nothing(gf4_crop, tmp_path):
    def cancel(fraction, message):
        if fraction > 0.2:
            raise CancelledError("stop")
    with pytest.raises(CancelledError):
        render_image(gf4_crop.images[0].true, gf4_crop.dem, tmp_path / "x.tif", tile=64, progress=cancel)
    assert not any(p.suffix == ".tif" for p in tmp_path.iterdir())


def test_write_scene_render_pushbroom(tmp_path):
    res = write_scene("gf7", tmp_path / "gf7", seed=2, size=(256, 256), n_gcps=20, render=True, tile=128)
    for name, bands in (("pan", ()), ("ms", (4,))):           # gf7: pan 1 band, MS 4 bands (issue 20)
        arr = _read(tmp_path / "gf7" / name / "scene.tif")
        W, H = res.scene.image(name).size
        assert arr.shape == bands + (H, W)
        assert arr.min() >= 1 and arr.std() > 10
