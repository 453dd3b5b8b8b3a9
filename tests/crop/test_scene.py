"""Scene: an opened input the workflows pass around (issue 21): opened once, its RPC read through the crop rules,
the same model and note as image_rpc (the Ventoux crop at (5000, 5000) of its product, tests/data/crop_ventoux)."""
from __future__ import annotations

import pickle

import numpy as np

from gdal_gf4cal.crop import image_rpc
from gdal_gf4cal.scene import Scene

from ventouxcrop import GEOM, ORIGIN, SIZE, grid_nodes, write_crop


def test_scene_opens_once_and_reads_the_crop_rpc_as_image_rpc(tmp_path):
    crop = write_crop(tmp_path / "left_image.tif")
    scene = Scene.open(crop)
    assert scene.is_image and scene.size == tuple(SIZE) and scene.key == "left_image"
    assert scene.dataset is not None and scene.files[0] == str(crop) and scene.rpc is None
    ready = scene.with_rpc(GEOM)
    model, note = image_rpc(crop, GEOM)
    assert ready.note == note and "RPC shifted by the origin" in note and str(GEOM) in ready.files
    col, row, alts, lon, lat = grid_nodes()
    s, l = ready.rpc.project(lon[0], lat[0], np.full(col.size, alts[0]))
    assert np.max(np.abs(s - (col - ORIGIN[0]))) < 2e-3 and np.max(np.abs(l - (row - ORIGIN[1]))) < 2e-3
    back = pickle.loads(pickle.dumps(ready))                # to a Dask worker: the dataset reopened there
    assert back.size == ready.size and back.note == ready.note and back.dataset is not None
    assert np.array_equal(back.rpc.line_num, ready.rpc.line_num)
    standalone = Scene.open(GEOM)                           # an RPC file alone: no pixels
    assert not standalone.is_image and standalone.dataset is None and standalone.files == (str(GEOM),)
