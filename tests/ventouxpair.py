"""The real Pleiades Ventoux stereo crops for the bundle-adjust tests (issue 22; tests/data/bundle_ventoux/PROVENANCE):
each crop copied beside its product's OSSIM .geom (left.tif + left.geom, right.tif + right.geom), as shareloc ships
them, so the views' RPCs are found beside the images and moved to the crops by their origins."""
from __future__ import annotations

import shutil
from pathlib import Path

DATA = Path(__file__).parent / "data"
LEFT_TIF = DATA / "matching" / "pleiades_ventoux_left.tif"
LEFT_GEOM = DATA / "rpc" / "ventoux_left_image.geom"
RIGHT_TIF = DATA / "bundle_ventoux" / "right_image.tif"
RIGHT_GEOM = DATA / "crop_ventoux" / "right_image.geom"
#: The right product's RPC with LINE_OFF moved by +60 px (shareloc's deliberately biased copy).
RIGHT_BIAS_GEOM = DATA / "bundle_ventoux" / "right_image_bias.geom"
BIAS_LINE_PX = 60.0
SRTM = DATA / "dem" / "N44E005.hgt"


def pair(folder, *, biased: bool = False):
    """``(left.tif, right.tif)`` in ``folder``, each with its .geom beside it; ``biased``: the right one's is the
    biased RPC."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    left, right = folder / "left.tif", folder / "right.tif"
    shutil.copyfile(LEFT_TIF, left)
    shutil.copyfile(LEFT_GEOM, folder / "left.geom")
    shutil.copyfile(RIGHT_TIF, right)
    shutil.copyfile(RIGHT_BIAS_GEOM if biased else RIGHT_GEOM, folder / "right.geom")
    return left, right


def dem_args():
    """The CLI's DEM options: real SRTM3 above EGM96."""
    return ["--dem", str(SRTM), "--geoid", "egm96"]
