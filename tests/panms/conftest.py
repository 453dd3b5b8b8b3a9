"""Shared fixture of the pan-MS tests: the real Pleiades-1B Ventoux pan/MS crops as delivered."""
from __future__ import annotations

import os
import shutil

import pytest

DATA = os.path.join(os.path.dirname(__file__), "..", "data")


@pytest.fixture(scope="module")
def ventoux_pair(tmp_path_factory):
    """The crops under their shareloc names in a fresh folder, each .geom beside its image (a folder per test
    module: the outputs written beside them stay apart)."""
    d = tmp_path_factory.mktemp("ventoux")
    shutil.copy(os.path.join(DATA, "matching", "pleiades_ventoux_left.tif"), d / "left_image.tif")
    shutil.copy(os.path.join(DATA, "rpc", "ventoux_left_image.geom"), d / "left_image.geom")
    for name in ("lowres_color_image.tif", "lowres_color_image.geom"):
        shutil.copy(os.path.join(DATA, "panms_ventoux", name), d / name)
    return d
