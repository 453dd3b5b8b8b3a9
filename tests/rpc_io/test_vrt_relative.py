"""A refined VRT references its image relative to the VRT when the image path was given relative (issue 15)."""
from __future__ import annotations

import os
import shutil
from pathlib import Path

from osgeo import gdal

from gdal_gf4cal import RPCModel
from gdal_gf4cal.rpc_io import write_rpc_vrt

DATA = Path(__file__).parents[1] / "data" / "compensation"


def _image(folder: Path) -> Path:
    img = folder / "img.tif"
    ds = gdal.GetDriverByName("GTiff").Create(str(img), 8, 8, 1, gdal.GDT_Byte)
    ds = None
    return img


def test_relative_image_path_stays_relative(tmp_path, monkeypatch):
    _image(tmp_path)
    (tmp_path / "sub").mkdir()
    rpc = RPCModel.from_file(DATA / "md_dg.RPB")
    monkeypatch.chdir(tmp_path)
    write_rpc_vrt("img.tif", rpc, "sub/r.vrt")
    text = (tmp_path / "sub" / "r.vrt").read_text()
    assert '<SourceFilename relativeToVRT="1">../img.tif</SourceFilename>' in text
    moved = tmp_path.parent / (tmp_path.name + "_moved")       # the pair moves together
    shutil.copytree(tmp_path, moved)
    monkeypatch.chdir(moved.parent)
    ds = gdal.Open(str(moved / "sub" / "r.vrt"))
    assert ds.GetFileList()[1] == os.path.join(str(moved / "sub"), "../img.tif")
    assert ds.GetMetadata("RPC")["LINE_OFF"]


def test_absolute_image_path_stays_absolute(tmp_path):
    img = _image(tmp_path)
    (tmp_path / "sub").mkdir()
    write_rpc_vrt(img, RPCModel.from_file(DATA / "md_dg.RPB"), tmp_path / "sub" / "r.vrt")
    assert f'relativeToVRT="0">{img}<' in (tmp_path / "sub" / "r.vrt").read_text()
