"""block-adjust is for the CCDs and bands of one camera's pass (METHODS §8); separate views (issue 22: stereo,
tri-stereo, several dates) are refused with one line pointing to bundle-adjust, decided from the RPCs: images that
share ground see it from directions more than MAX_VIEW_ANGLE_DEG apart. The band-to-CCD pairing comes from the RPCs
by default (issue 24). Real: the Pleiades Ventoux stereo pair's product RPCs (tests/data, from CNES shareloc);
simulated: the seeded Jilin-1 group (tests/blocksim.py)."""
import os

import numpy as np
import pytest
from osgeo import gdal

import blocksim as B
from gdal_gf4cal.block import (MAX_VIEW_ANGLE_DEG, SeparateViewsError, derive_layout, pair_bands, view_angle)
from gdal_gf4cal.cli import main
from gdal_gf4cal.rpc import RPCModel

DATA = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "data")
LEFT_GEOM = os.path.join(DATA, "rpc", "ventoux_left_image.geom")            # left product, 201308051042194
RIGHT_GEOM = os.path.join(DATA, "crop_ventoux", "right_image.geom")         # right product, 201308051042523


def _crop(path, gt, size):
    """An image with the shareloc crop's size and pixel-unit geotransform (its origin in the product)."""
    ds = gdal.GetDriverByName("GTiff").Create(str(path), size[0], size[1], 1, gdal.GDT_Byte)
    ds.SetGeoTransform(gt)
    ds.GetRasterBand(1).Fill(100)
    ds = None
    return str(path)


def test_pleiades_stereo_pair_is_separate_views():
    """The two products' RPCs see the Ventoux ground 19.6 deg apart (their stereo base): the coinciding footprints
    make the right image look like a band of the left's CCD, and the layout refuses it as a separate view."""
    m = {"left": RPCModel.from_file(LEFT_GEOM), "right": RPCModel.from_file(RIGHT_GEOM)}
    sizes = {k: v.image_size for k, v in m.items()}
    assert view_angle(m["left"], sizes["left"], m["right"], sizes["right"], 500.0) == pytest.approx(19.6, abs=0.3)
    order, bands = pair_bands(m, ["left", "right"], sizes=sizes)
    assert order == ["left"] and bands == {"right": "left"}
    with pytest.raises(SeparateViewsError, match="bundle-adjust"):
        derive_layout(m, order, bands_of=bands, sizes=sizes)
    with pytest.raises(SeparateViewsError, match="19.6 deg"):          # given as two CCDs side by side
        derive_layout(m, ["left", "right"], sizes=sizes)


def test_block_adjust_of_the_stereo_crops_points_to_bundle_adjust(tmp_path, capsys):
    """gf4cal block-adjust on the two Ventoux crops (their products' RPCs through --rpc): exit 2, one line naming
    bundle-adjust, nothing written; with and without --bands-of."""
    left = _crop(tmp_path / "left_image.tif", (5000.0, 1.0, 0.0, 5000.0, 0.0, 1.0), (500, 500))
    right = _crop(tmp_path / "right_image.tif", (4915.0, 1.0, 0.0, 5162.0, 0.0, 1.0), (498, 495))
    out = tmp_path / "out"
    base = [left, right, "--rpc", f"{left}={LEFT_GEOM}", f"{right}={RIGHT_GEOM}", "--dem", "500", "--match-ties",
            "--out", str(out)]
    for extra in ([], ["--bands-of", "right_image=left_image"]):
        assert main(["block-adjust", *base, *extra]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("gf4cal: "), err
        assert "separate views" in err[0] and "gf4cal bundle-adjust" in err[0], err[0]
        assert not out.exists()


@pytest.mark.slow
def test_jl1_group_pairing_from_the_rpcs(tmp_path_factory):
    """The simulated group (4 CCDs x pan + 4 MS bands, given blue CCDs first): every band image paired with its
    CCD's blue image from the RPCs alone, as the tests' explicit --bands-of says; lines of sight within 0.5 deg."""
    d = B.block_scene(str(tmp_path_factory.getbasetemp()))
    models = {n: RPCModel.from_file(os.path.join(d, n, "scene.RPB")) for n in B.NAMES}
    sizes = {n: (512, 256) if "_" not in n else (128, 64) for n in B.NAMES}
    order, bands = pair_bands(models, B.NAMES, sizes=sizes)
    assert order == B.REF
    assert bands == {n: n.split("_")[0] + "_blue" for n in B.NAMES if n not in B.REF}
    layout = derive_layout(models, order, bands_of=bands, sizes=sizes)          # accepted: one camera's pass
    angles = [view_angle(models[layout.images[b].reference], sizes[layout.images[b].reference], models[b],
                         sizes[b], 0.0) for b in layout.band_images]
    angles += [view_angle(models[a], sizes[a], models[b], sizes[b], 0.0) for a, b in layout.adjacent_pairs()]
    assert 0.0 < max(angles) < 0.5 < MAX_VIEW_ANGLE_DEG
    assert np.all(np.isfinite(angles))
