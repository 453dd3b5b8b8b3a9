"""register-pan-ms gives the same outputs, to the bit, with 1 and 2 threads (issue 23): its bands, outputs and plots
run over the thread pool (``GF4CAL_NUM_THREADS``), never changing a number.

The real Pleiades-1B pair over Mont Ventoux as delivered (tests/data: a 500 x 500 pan crop and a 145 x 145 x 4 MS
crop, each with its product's .geom; the real SRTM tile above EGM96), registered by the ``gf4cal`` command with no
option but the DEM, once with ``GF4CAL_NUM_THREADS=1`` and once with 2: every raster, the model, the refitted RPC,
the cells and the plots are the same bytes or values; the report differs only in its timings.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from osgeo import gdal, ogr

from gdal_gf4cal import threads

DATA = os.path.join(os.path.dirname(__file__), "..", "data")
ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))


@pytest.fixture(scope="module")
def runs(ventoux_pair):
    d = ventoux_pair
    dem = os.path.join(DATA, "dem", "N44E005.hgt")
    out = {}
    for k in ("1", "2"):
        env = dict(os.environ, PYTHONPATH=ROOT, **{threads.ENV: k})
        proc = subprocess.run([sys.executable, "-m", "gdal_gf4cal.cli", "register-pan-ms", "left_image.tif",
                               "lowres_color_image.tif", "--dem", dem, "--geoid", "egm96", "--out", f"out{k}"],
                              capture_output=True, text=True, cwd=d, env=env)
        assert proc.returncode == 0, proc.stderr
        out[k] = d / f"out{k}"
    return out


def _raster(path):
    ds = gdal.Open(str(path))
    return ds.ReadAsArray(), ds.GetMetadata("RPC"), [ds.GetRasterBand(b + 1).GetDescription()
                                                     for b in range(ds.RasterCount)]


def _features(path):
    ds = ogr.Open(str(path))
    layers = {}
    for i in range(ds.GetLayerCount()):
        lyr = ds.GetLayerByIndex(i)
        layers[lyr.GetName()] = [({k: v for k, v in f.items().items() if k != "update_time"},    # the styles'
                                  f.GetGeometryRef().ExportToWkb() if f.GetGeometryRef() else None) for f in lyr]
    return layers


def test_outputs_are_the_same_with_1_and_2_threads(runs):
    one, two = runs["1"], runs["2"]
    for name in ("correction.tif", "ms_on_pan.tif"):
        a1, rpc1, d1 = _raster(one / name)
        a2, rpc2, d2 = _raster(two / name)
        assert np.array_equal(a1, a2, equal_nan=True), name
        assert (rpc1, d1) == (rpc2, d2), name
    for name in ("model.json", "ms_approx.RPB", "residual_maps.png", "residual_along_line.png", "spectrum.png"):
        assert (one / name).read_bytes() == (two / name).read_bytes(), name
    f1, f2 = _features(one / "cells.gpkg"), _features(two / "cells.gpkg")
    assert f1.keys() == f2.keys() and len(f1["gcps"]) > 300      # one point per cell
    for layer in f1:
        assert f1[layer] == f2[layer], layer
    r1, r2 = (json.loads((o / "report.json").read_text()) for o in (one, two))
    for r in (r1, r2):
        assert set(r.pop("timings_s")) >= {"matching", "estimate", "correction_and_ms_on_pan", "rpc_cells_plots"}
        r.pop("outputs")
    assert r1 == r2
    # and the registration is the one the accuracy test pins (tests/panms/test_panms_ventoux.py)
    assert r1["steps"][-1]["rms_sample_px"] < 0.1 and r1["steps"][-1]["rms_line_px"] < 0.1



@pytest.mark.skipif(threads.blas_threads() is None, reason="NumPy's BLAS is not OpenBLAS")
def test_the_python_api_computes_blas_on_the_calling_thread(ventoux_pair, tmp_path):
    """``register_pan_ms`` called from Python (no ``gf4cal`` command, no ``threads.limit`` around it) holds BLAS on
    the calling thread from start to end, as the command does: a product computed on OpenBLAS's own threads wakes
    them, and they then spin ~0.1 s on another core (0.4 s of CPU per run on the GF7 bench crop), beside the pool's
    threads. Every progress report comes from inside that scope, and the scope is closed afterwards."""
    from gdal_gf4cal.workflows.panms import register_pan_ms
    d = ventoux_pair
    assert not threads.blas_is_serial()
    seen = []
    register_pan_ms(str(d / "left_image.tif"), str(d / "lowres_color_image.tif"),
                    dem=os.path.join(DATA, "dem", "N44E005.hgt"), geoid="egm96", out=str(tmp_path / "out"),
                    progress=lambda f, m="": seen.append(threads.blas_is_serial()))
    assert len(seen) > 3 and all(seen)
    assert not threads.blas_is_serial()


@pytest.fixture(scope="module")
def tiled_writes(runs, ventoux_pair):
    """correction.tif and ms_on_pan.tif of the registered Ventoux pair written again by the appliers in 32-px tiles
    (25 and 16 tiles: rounds of 1, 2 or 3 tiles) under 1, 2 and 3 threads, and each in one tile; with the progress
    of correction.tif."""
    from gdal_gf4cal import DEM
    from gdal_gf4cal.crop import image_rpc
    from gdal_gf4cal.panms import PanMSModel, resample_ms_on_pan, write_correction
    d = ventoux_pair
    model = PanMSModel.from_json(runs["1"] / "model.json")
    pan_rpc, ms_rpc = image_rpc(d / "left_image.tif")[0], image_rpc(d / "lowres_color_image.tif")[0]
    dem = DEM.from_user_input(os.path.join(DATA, "dem", "N44E005.hgt"), geoid="egm96")
    out, seen = {}, {}
    for k in (1, 2, 3):
        with threads.limit(k):
            seen[k] = []
            write_correction(model, d / f"corr{k}.tif", tile=32, rpc=ms_rpc,
                             progress=lambda f, m="", k=k: seen[k].append(f))
            resample_ms_on_pan(model, d / "left_image.tif", d / "lowres_color_image.tif", d / f"mop{k}.tif",
                               pan_rpc=pan_rpc, ms_rpc=ms_rpc, dem=dem, ratio=4, tile=32)
            out[k] = [gdal.Open(str(d / f"{name}{k}.tif")).ReadAsArray() for name in ("corr", "mop")]
    write_correction(model, d / "corr_whole.tif", rpc=ms_rpc)
    resample_ms_on_pan(model, d / "left_image.tif", d / "lowres_color_image.tif", d / "mop_whole.tif",
                       pan_rpc=pan_rpc, ms_rpc=ms_rpc, dem=dem, ratio=4)
    return out, seen, [gdal.Open(str(d / f"{name}_whole.tif")).ReadAsArray() for name in ("corr", "mop")]


def test_tiled_appliers_give_the_same_bits_with_any_thread_count(tiled_writes):
    """The appliers compute a round of tiles over the pool and write them in order (issue 23): every tile is the
    one thread's, with 1, 2 or 3 threads; correction.tif's pixels do not depend on the tiles at all (one tile or
    sixteen), and ms_on_pan.tif's in 32-px tiles are those of one tile within its node grid's interpolation."""
    out, seen, whole = tiled_writes
    (corr1, mop1) = out[1]
    assert corr1.shape == (2, 145, 145) and mop1.shape == (4, 125, 125)
    for k in (2, 3):
        assert np.array_equal(out[k][0], corr1, equal_nan=True) and np.array_equal(out[k][1], mop1), k
    assert np.array_equal(corr1, whole[0], equal_nan=True)
    diff = np.abs(mop1.astype(float) - whole[1])
    shifted = np.abs(np.diff(whole[1].astype(float), axis=-1))     # what a tile one pixel off would give
    assert np.median(diff) <= 1e-3 * np.median(shifted) and diff.max() <= 0.01 * shifted.max()
    for k in (1, 2, 3):                      # one report per tile, in order, whatever the rounds
        assert seen[k] == [i / 25 for i in range(1, 26)], k


@pytest.mark.parametrize("first", [True, False])
def test_ms_on_pan_before_or_beside_the_plots_gives_the_same_outputs(ventoux_pair, runs, tmp_path, monkeypatch,
                                                                     first):
    """register-pan-ms writes ms_on_pan.tif before the plots begin when it has more tiles than a round of the pool,
    else beside them (workflows.panms._ms_on_pan_first): either order gives the command's outputs, to the byte."""
    from gdal_gf4cal.workflows import panms as wp
    monkeypatch.setattr(wp, "_ms_on_pan_first", lambda pair: first)
    monkeypatch.chdir(ventoux_pair)                     # the inputs named as the command run names them
    with threads.limit(2):
        wp.register_pan_ms("left_image.tif", "lowres_color_image.tif", dem=os.path.join(DATA, "dem", "N44E005.hgt"),
                           geoid="egm96", out=str(tmp_path / "out"))
    for name in ("correction.tif", "ms_on_pan.tif"):
        assert np.array_equal(_raster(tmp_path / "out" / name)[0], _raster(runs["2"] / name)[0], equal_nan=True)
    for name in ("model.json", "ms_approx.RPB", "residual_maps.png", "residual_along_line.png", "spectrum.png"):
        assert (tmp_path / "out" / name).read_bytes() == (runs["2"] / name).read_bytes(), name
    assert _features(tmp_path / "out" / "cells.gpkg") == _features(runs["2"] / "cells.gpkg")


def test_ms_on_pan_goes_first_when_it_has_more_tiles_than_a_round():
    from types import SimpleNamespace
    from gdal_gf4cal.workflows.panms import _ms_on_pan_first
    bench_crop, crop_4096 = SimpleNamespace(pan_size=(1024, 1024), ratio=4), SimpleNamespace(pan_size=(4096, 4096),
                                                                                           ratio=4)
    with threads.limit(2):
        assert not _ms_on_pan_first(bench_crop) and _ms_on_pan_first(crop_4096)       # 1 and 4 tiles of 512 px
    with threads.limit(4):
        assert not _ms_on_pan_first(crop_4096)
