"""block-adjust with ``--rpc IMAGE=RPC`` (issue 19 item 8): the seeded simulated Jilin-1 group (tests/blocksim.py) as
crops that state their origin in a product (pixel-unit geotransform without CRS, no RPC of their own), each paired
with its product's RPC, calibrates exactly as the group with its own RPCs: the origins are applied and noted."""
import json
import os

import numpy as np
import pytest
from osgeo import gdal

import blocksim as B  # noqa: E402 (tests/ helper)
from gdal_gf4cal import RPCModel
from gdal_gf4cal.cli import main

pytestmark = pytest.mark.slow
ORIGIN = (3000.0, 12000.0)


def as_crops(d, root):
    """Each image of ``d`` rewritten under ``root`` (same folder names: the observations' image names) as a crop at
    ORIGIN without RPC, and its RPC moved to the product's pixels in ``root/<name>/product.RPB``; the IMAGE=RPC
    pairs."""
    pairs = []
    for name in B.NAMES:
        src = gdal.Open(B.image_path(d, name))
        os.makedirs(os.path.join(root, name))
        path = B.image_path(root, name)
        ds = gdal.GetDriverByName("GTiff").Create(path, src.RasterXSize, src.RasterYSize, 1, gdal.GDT_Float32)
        ds.SetGeoTransform((ORIGIN[0], 1.0, 0.0, ORIGIN[1], 0.0, 1.0))
        ds.GetRasterBand(1).WriteArray(src.GetRasterBand(1).ReadAsArray().astype(np.float32))
        ds = None
        product = RPCModel.from_file(B.image_path(d, name)).with_image_affine(*ORIGIN)
        pairs.append(f"{path}={product.write_rpb(os.path.join(root, name, 'product.RPB'))}")
    return pairs


def test_block_adjust_of_crops_with_their_products_rpcs(tmp_path_factory, tmp_path):
    d = B.block_scene(str(tmp_path_factory.getbasetemp()))
    crops = str(tmp_path / "crops")
    pairs = as_crops(d, crops)
    own = B.cli_args(d)
    args = [a.replace(d + os.sep, crops + os.sep) if a.endswith("scene.tif") else a for a in own]
    assert main(["block-adjust", *own, "--out", str(tmp_path / "own")]) == 0
    assert main(["block-adjust", *args, "--rpc", *pairs, "--out", str(tmp_path / "crop")]) == 0
    notes = json.loads((tmp_path / "crop" / "report.json").read_text())["notes"]
    assert len(notes) == len(B.NAMES)
    assert all(n.startswith(f"{k}: scene.tif is a crop at (3000, 12000)") for n, k in zip(notes, B.NAMES))
    W, H = B.SIZE
    S, L = (a.ravel() for a in np.meshgrid(np.linspace(1, W - 1, 7), np.linspace(1, H - 1, 5)))
    for name in B.NAMES:                   # the recalibrated RPCs, written for the crops' pixels, are the same
        a = RPCModel.from_file(tmp_path / "own" / f"{name}.RPB")
        b = RPCModel.from_file(tmp_path / "crop" / f"{name}.RPB")
        lon, lat = a.localize(S, L, np.full(S.shape, a.height_off))
        ok = np.isfinite(lon)                  # (the refitted RPC's inverse misses an odd point)
        s, l = b.project(lon[ok], lat[ok], a.height_off)
        assert ok.sum() >= 30 and np.max(np.hypot(s - S[ok], l - L[ok])) < 1e-6, name
    # apply-calibration --calibration to the crops, paired as block-adjust was: the same RPCs as to the images
    assert main(["apply-calibration", *own[:len(B.NAMES)], "--calibration", str(tmp_path / "own" / "calibration.json"),
                 "--out", str(tmp_path / "own_applied")]) == 0
    assert main(["apply-calibration", *args[:len(B.NAMES)], "--rpc", *pairs, "--calibration",
                 str(tmp_path / "crop" / "calibration.json"), "--out", str(tmp_path / "crop_applied")]) == 0
    notes = json.loads((tmp_path / "crop_applied" / "report.json").read_text())["notes"]
    assert len(notes) == len(B.NAMES)
    for name in B.NAMES:
        a = RPCModel.from_file(tmp_path / "own_applied" / f"{name}.RPB")
        b = RPCModel.from_file(tmp_path / "crop_applied" / f"{name}.RPB")
        lon, lat = a.localize(S, L, np.full(S.shape, a.height_off))
        ok = np.isfinite(lon)
        s, l = b.project(lon[ok], lat[ok], a.height_off)
        assert ok.sum() >= 30 and np.max(np.hypot(s - S[ok], l - L[ok])) < 1e-6, name


def test_rpc_pairs_that_are_not_pairs_are_refused(tmp_path_factory, tmp_path, capsys):
    d = B.block_scene(str(tmp_path_factory.getbasetemp()))
    assert main(["block-adjust", *B.cli_args(d), "--rpc", "nothing_here", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "RPC pairs (--rpc): 'nothing_here' is not IMAGE=RPC" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()
