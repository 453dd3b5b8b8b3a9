"""GF4CAL_NUM_THREADS (issue 23) for the matching windows and the batch scenes: GCPs bit-identical with 1, 2 and 3
threads, each tile's point kernels kept serial on its pool thread, and batch scenes on a thread pool sharing the
process's threads instead of each taking them all.

A rendered scene (tests/matchscene.py: the real Pleiades texture as reference ortho, the real SRTM crop, a raw image
rendered through a true RPC, the matcher given a biased RPC) matched with the real GDAL files; the GCPs are checked
against the true RPC.
"""
from __future__ import annotations

import os
import threading

import numpy as np
import pytest
from osgeo import gdal

from gdal_gf4cal import threads
from gdal_gf4cal.batch import run_batch
from gdal_gf4cal.executors import get_executor
from gdal_gf4cal.matching import collect_gcps, match_tile
from gdal_gf4cal.matching.collect import run_tiles

from matchscene import build_scene, error_affine

SIZE = (384, 384)
ERROR = error_affine(shift=(7.3, -5.6), rotation_rad=0.001, center=(192, 192))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return build_scene(tmp_path_factory.mktemp("threads_match"), texture="pleiades", size=SIZE, error=ERROR, seed=2)


def _columns(g):
    return {c: g[c].to_numpy() for c in g.columns if c not in ("geometry", "id", "role")}


def test_collect_gcps_bit_identical_with_1_2_3_threads(scene, monkeypatch):
    """The tiles are fixed by the window grid (tiles of 9 windows here), never by the threads; the default pool
    size is GF4CAL_NUM_THREADS: the same GCP table, to the bit, with 1, 2 and 3 threads, and right against truth."""
    tables = []
    for k in ("1", "2", "3"):
        monkeypatch.setenv(threads.ENV, k)
        tables.append(_columns(collect_gcps(scene.image, scene.rpc, scene.reference, scene.dem, spacing_px=32,
                                            window_px=64, tile_windows=9)))
    first = tables[0]
    for other in tables[1:]:
        assert first.keys() == other.keys()
        for c in first:
            assert np.array_equal(first[c], other[c]), c
    ok = ~first["outlier"]
    assert ok.sum() >= 60
    ts, tl = scene.truth(first["lon"][ok], first["lat"][ok], first["h"][ok])
    assert np.sqrt(np.mean((first["sample"][ok] - ts) ** 2 + (first["line"][ok] - tl) ** 2)) < 0.1
    # the offsets measured are the RPC's error, ~9 px
    assert 7.0 < np.median(np.hypot(first["dsample"][ok], first["dline"][ok])) < 11.0


def test_tiles_run_on_the_pool_with_serial_kernels(scene, monkeypatch):
    """run_tiles takes GF4CAL_NUM_THREADS threads (or the caller's threads.limit) and runs each tile with serial
    point kernels: no threads within threads."""
    from gdal_gf4cal.matching import plan_tiles
    import gdal_gf4cal.matching.collect as collect_mod
    specs, _ = plan_tiles(scene.image, scene.rpc, scene.reference, scene.dem, spacing_px=48, window_px=64,
                          tile_windows=4)
    seen = []

    def spy(spec):
        seen.append((threading.current_thread().name, threads.num_threads()))
        return match_tile(spec)

    monkeypatch.setattr(collect_mod, "match_tile", spy)
    monkeypatch.setenv(threads.ENV, "3")
    with threads.limit(2):
        out = run_tiles(specs)
    assert len(out) == len(specs) > 4
    names = {n for n, _ in seen}
    assert all(n.startswith("gf4cal-tile") for n in names) and 1 <= len(names) <= 2
    assert {k for _, k in seen} == {1}                   # the kernels inside a tile: serial
    seen.clear()
    monkeypatch.setenv(threads.ENV, "1")
    run_tiles(specs[:3])
    assert [n for n, _ in seen] == [threading.current_thread().name] * 3       # 1: in the calling thread


def _scene_threads(scene, outputs, overwrite=False):
    """A scene function that writes a real GeoTIFF and says how many threads its kernels and tiles may use."""
    n = threads.num_threads()
    ds = gdal.GetDriverByName("GTiff").Create(outputs["out"], 4, 4, 1, gdal.GDT_Byte)
    ds.GetRasterBand(1).Fill(n)
    ds = None
    return {"threads": n}


@pytest.mark.parametrize("spec, setting, want", [("threads:2", "4", 2), ("threads:2", "1", 1),
                                                 ("threads:4", "2", 1), ("serial", "3", 3)])
def test_batch_scenes_share_the_threads(tmp_path, monkeypatch, spec, setting, want):
    """Scenes on a thread pool each get GF4CAL_NUM_THREADS over the scenes running at once (1 at least): 2 scenes
    at once of 4 threads -> 2 each; serially a scene has them all."""
    monkeypatch.setenv(threads.ENV, setting)
    scenes = []
    for i in range(3):
        p = tmp_path / f"s{i}.tif"
        gdal.GetDriverByName("GTiff").Create(str(p), 2, 2, 1, gdal.GDT_Byte)
        scenes.append(str(p))
    out = tmp_path / "out"
    with get_executor(spec) as ex:
        rep = run_batch(_scene_threads, scenes, out, lambda s: {"out": os.path.join(out, os.path.basename(s))},
                        executor=ex)
    assert [r["status"] for r in rep["scenes"]] == ["ok"] * 3
    assert [r["threads"] for r in rep["scenes"]] == [want] * 3
    assert gdal.Open(str(out / "s0.tif")).ReadAsArray()[0, 0] == want


def test_default_thread_executor_follows_the_setting(monkeypatch):
    monkeypatch.setenv(threads.ENV, "3")
    with get_executor(None) as ex:
        assert ex._max_workers == 3
    monkeypatch.setenv(threads.ENV, "1")
    with get_executor(None) as ex:
        assert ex.submit(threading.current_thread).result() is threading.current_thread()      # serial
