"""A tile's shared work (issue 23): the coarse level's windows resampled and read once per tile, and the raster
blocks a row of tiles shares decompressed once per thread, the same GCPs as window by window and tile by tile.

Scene (tests/matchscene.py): the real SRTM relief (Mont Ventoux) under a 384 x 384 raw image rendered through a true
RPC, a biased RPC ~63 px off (the coarse level finds it), the builtin texture as the reference ortho in UTM 31N.
"""
from __future__ import annotations

import concurrent.futures as cf
import gc

import numpy as np
import pytest
from osgeo import gdal

from gdal_gf4cal.matching import ReferenceImage, collect_gcps, match_tile, plan_tiles, reference_on_grids
from gdal_gf4cal.matching import collect, resample
from gdal_gf4cal import threads
from gdal_gf4cal.matching.correlate import phase_correlate

from matchscene import build_scene, error_affine

SIZE = (384, 384)
ERROR = error_affine(shift=(-50.3, 37.6), rotation_rad=0.002, scale=1.001, center=(192, 192))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return build_scene(tmp_path_factory.mktemp("tiles"), texture="builtin", size=SIZE, error=ERROR)


def _reads(monkeypatch):
    """Counter of :func:`resample.read_block` calls (one GDAL read each)."""
    calls = []
    real = resample.read_block

    def counted(*a, **k):
        calls.append(a[4:8])
        return real(*a, **k)
    monkeypatch.setattr(resample, "read_block", counted)
    return calls


@pytest.mark.parametrize("overviews", [False, True])
def test_decimated_dense_boxes_are_one_read_of_the_same_values(scene, tmp_path, monkeypatch, overviews):
    """Coarse windows on one lattice of the decimation (some past the raster's edges) come out of one averaged read
    of their union with the bits of one read per window, with or without overviews; off the lattice, one read each
    (GDAL averages other cells)."""
    path = scene.image
    if overviews:
        path = str(tmp_path / "ovr.tif")
        gdal.Translate(path, scene.image)
        ds = gdal.Open(path, gdal.GA_Update)
        ds.BuildOverviews("AVERAGE", [2, 4])
        ds = None
    ds = gdal.Open(path)
    band, W, H = ds.GetRasterBand(1), ds.RasterXSize, ds.RasterYSize
    calls = _reads(monkeypatch)
    for d, size in ((4, 256), (2, 100), (8, 256)):
        x0 = -37 + d * np.array([0, 8, 16, 24, 8, 40, 60, 90])
        y0 = 250 + d * np.array([0, 0, 8, 8, 16, 20, 10, 0])
        calls.clear()
        got = resample.read_boxes(band, W, H, None, x0, y0, size, d)
        assert len(calls) == 1
        one = np.array([resample.read_block(band, W, H, None, int(x), int(y), size, size, d) for x, y in zip(x0, y0)])
        assert got.shape == one.shape and np.isnan(got).any() and np.isfinite(got).any()
        np.testing.assert_array_equal(got, one)
        calls.clear()
        resample.read_boxes(band, W, H, None, x0 + np.arange(x0.size) % 2, y0, size, d)
        assert len(calls) == x0.size


def test_coarse_grid_of_a_tile_is_its_windows_resampled_one_by_one(scene, monkeypatch):
    """The coarse windows of a tile (grid spacing 4, corners on its lattice) resampled once on their union's grid:
    the reference values of every window as resampled alone, up to the geometry interpolated between other nodes
    (a median 2e-4 of the texture's range over rugged relief, no window moved), from one spline interpolation
    instead of one per window."""
    ref = ReferenceImage(scene.reference)
    x0 = np.repeat(np.arange(4) * 32.0, 3) + 16
    y0 = np.tile(np.arange(3) * 32.0, 4) + 16
    sampled = []
    real = resample._sample_reference

    def counted(reference, fx, *a):
        sampled.append(fx.size)
        return real(reference, fx, *a)
    monkeypatch.setattr(resample, "_sample_reference", counted)
    one = reference_on_grids(scene.rpc, scene.dem, ref, x0, y0, 64, spacing=4, oversample=1.0)
    assert sampled == [x0.size * 64 * 64]
    sampled.clear()
    shared = reference_on_grids(scene.rpc, scene.dem, ref, x0, y0, 64, spacing=4, oversample=1.0, shared=True)
    assert sampled == [(64 + 24) * (64 + 16)]
    assert np.isfinite(one).all() and np.isfinite(shared).all()
    diff = np.abs(shared - one)
    assert 0 < np.median(diff) < 1e-3 * np.ptp(one)   # geometry nodes elsewhere: not the same computation
    # ... but the same ground: no window moved by 0.01 of a coarse pixel.
    r = phase_correlate(one, shared)
    assert np.abs(r.dx).max() < 0.01 and np.abs(r.dy).max() < 0.01


def test_coarse_level_keeps_accuracy_with_offsets_beyond_the_fine_search(scene):
    """With the coarse level from one grid per tile, the ~63 px bias is found and every GCP lies on the truth (the
    same bounds as tests/matching/test_matching_collect.py), windows spread over two thread counts alike."""
    g1 = collect_gcps(scene.image, scene.rpc, scene.reference, scene.dem, spacing_px=32, window_px=64, workers=1)
    g2 = collect_gcps(scene.image, scene.rpc, scene.reference, scene.dem, spacing_px=32, window_px=64, workers=2)
    for c in ("sample", "line", "precision_px", "texture"):
        np.testing.assert_array_equal(g1[c].to_numpy(), g2[c].to_numpy())
    ts, tl = scene.truth(g1["lon"].to_numpy(), g1["lat"].to_numpy(), g1["h"].to_numpy())
    ok = ~g1["outlier"].to_numpy()
    err = np.hypot(g1["sample"].to_numpy() - ts, g1["line"].to_numpy() - tl)[ok]
    assert ok.sum() >= 60 and np.sqrt(np.mean(err ** 2)) <= 0.1


@pytest.fixture
def room_in_the_cache():
    """GDAL's block cache emptied of the blocks earlier tests left in it (datasets still open: a pool thread's own,
    a module fixture's; above KEEP_BLOCKS_BYTES no thread keeps its blocks, as after tests/panms/test_panms_crops.py)
    and at least 4 x KEEP_BLOCKS_BYTES large (the kept blocks are not evicted by GDAL); its size restored after."""
    size = gdal.GetCacheMax()
    gdal.SetCacheMax(0)                        # evicts every block no one is reading
    gdal.SetCacheMax(max(size, 4 * collect.KEEP_BLOCKS_BYTES))
    assert gdal.GetCacheUsed() <= collect.KEEP_BLOCKS_BYTES // 4
    yield
    gdal.SetCacheMax(size)


def _cache_by_tile(scene, **kw):
    """GDAL's block cache (beyond what it held before) after every tile of a collect run (progress runs between
    tiles) and after the run. A first run opens the threads' datasets and DEM (the DEM's own blocks are not the
    tiles')."""
    def run(progress=None):
        return collect_gcps(scene.image, scene.rpc, scene.reference, scene.dem, spacing_px=48, window_px=64,
                            tile_windows=4, progress=progress, **kw)
    run()
    gc.collect()
    used = []
    base = gdal.GetCacheUsed()
    g = run(lambda f, m="": used.append(gdal.GetCacheUsed() - base))
    return g, used[1:-1], gdal.GetCacheUsed() - base


def test_threads_keep_the_blocks_a_row_of_tiles_shares_and_release_them(scene, monkeypatch, room_in_the_cache):
    """run_tiles' threads keep their raster blocks from one tile to the next (a row of tiles reads the same strips:
    decompressed once instead of once per tile) while GDAL's cache holds at most KEEP_BLOCKS_BYTES, and flush them
    when the run ends; a tile run on its own (another executor's worker, Dask) flushes them at once, as every tile
    with KEEP_BLOCKS_BYTES = 0. The GCPs are the same bits."""
    g, during, after = _cache_by_tile(scene, workers=1)
    assert max(during) > 0 and after == 0
    specs, _ = plan_tiles(scene.image, scene.rpc, scene.reference, scene.dem, 48, 64, tile_windows=4)
    base = gdal.GetCacheUsed()
    match_tile(specs[0])
    assert gdal.GetCacheUsed() == base
    monkeypatch.setattr(collect, "KEEP_BLOCKS_BYTES", 0)
    g2, during2, after2 = _cache_by_tile(scene, workers=1)
    assert max(during2) == 0 and after2 == 0
    monkeypatch.undo()
    with cf.ThreadPoolExecutor(2) as ex:
        g3 = collect_gcps(scene.image, scene.rpc, scene.reference, scene.dem, spacing_px=48, window_px=64,
                          tile_windows=4, executor=ex)
    g4 = collect_gcps(scene.image, scene.rpc, scene.reference, scene.dem, spacing_px=48, window_px=64,
                      tile_windows=4, workers=2)
    for other in (g2, g3, g4):
        np.testing.assert_array_equal(g["sample"].to_numpy(), other["sample"].to_numpy())
        np.testing.assert_array_equal(g["line"].to_numpy(), other["line"].to_numpy())


def test_a_thread_drops_the_blocks_of_rows_its_next_tile_does_not_read(scene, room_in_the_cache):
    """Tiles of rows of tiles far apart: the blocks kept from one tile are dropped before the next tile, which then
    holds its own blocks only, so the cache holds about a row of tiles per thread, never the scene."""
    specs, _ = plan_tiles(scene.image, scene.rpc, scene.reference, scene.dem, 96, 64, tile_windows=1, search_px=8)
    rows = [collect._tile_rows(s, s.centers) for s in specs]
    assert rows[1] == rows[0]
    far = next(k for k in range(1, len(specs)) if rows[k][0] > rows[0][1])
    match_tile(specs[far])        # this thread's datasets and DEM opened (the DEM's blocks are not the tiles')
    gc.collect()
    base = gdal.GetCacheUsed()

    def cache_after(*tiles):
        held, seen = {}, []

        def tile(spec):
            out = collect._match_tile_serial(spec)
            seen.append(gdal.GetCacheUsed() - base)
            return out
        run = collect._keeping_blocks(tile, held)
        for k in tiles:
            run(specs[k])
        for datasets, _ in held.values():
            for d in datasets:
                d.FlushCache()
        assert gdal.GetCacheUsed() <= base
        return seen
    alone = cache_after(far)[0]
    seen = cache_after(0, 1, far)
    assert 0 < seen[0] <= seen[1] and alone > 0
    assert seen[2] == alone                      # the first row's blocks dropped before the far tile read its own


@pytest.mark.skipif(threads.blas_threads() is None, reason="NumPy's BLAS is not OpenBLAS")
def test_collect_gcps_computes_blas_on_the_calling_thread(scene):
    """``collect_gcps`` called from Python (no ``gf4cal`` command, no ``threads.limit``) holds BLAS on the calling
    thread from start to end, as the command does, not only inside each tile: the outlier fit after the tiles woke
    OpenBLAS's own thread, which then spun ~0.1 s on the other core. Every progress report (between tiles too) comes
    from inside that scope, and the scope is closed afterwards."""
    assert not threads.blas_is_serial()
    seen = []
    collect_gcps(scene.image, scene.rpc, scene.reference, scene.dem, spacing_px=48, window_px=64, tile_windows=4,
                 workers=1, progress=lambda f, m="": seen.append(threads.blas_is_serial()))
    assert len(seen) > 3 and all(seen)
    assert not threads.blas_is_serial()


def test_a_tiles_centres_and_corners_are_one_localisation(scene, monkeypatch):
    """A tile localises its windows' centres and corners on the DEM in one call (each call of the DEM intersection is
    ~300 NumPy calls whatever its size, each handing the GIL to a waiting thread): with a coarse level, three calls a
    tile (footprints, coarse grid, fine grid), not four. The GCPs' ground points are those of the centres localised
    alone to within the intersection's own convergence (1e-4 m in height), and on the truth as before."""
    specs, ctx = plan_tiles(scene.image, scene.rpc, scene.reference, scene.dem, 32, 64)
    assert specs[0].factor > 1
    calls = []
    real = type(scene.rpc).localize_dem

    def counted(self, *a, **k):
        calls.append(np.size(a[0]))
        return real(self, *a, **k)
    monkeypatch.setattr(type(scene.rpc), "localize_dem", counted)
    res = [match_tile(sp) for sp in specs]
    assert len(calls) == 3 * len(specs)
    assert calls[0] == 5 * len(specs[0].centers)
    monkeypatch.undo()
    g = collect.assemble_gcps(res, ctx)
    lon, lat, h = scene.rpc.localize_dem(g["sample"].to_numpy() - g["dsample"].to_numpy(),
                                         g["line"].to_numpy() - g["dline"].to_numpy(), scene.dem)
    assert np.abs(g["lon"].to_numpy() - lon).max() < 1e-10 and np.abs(g["lat"].to_numpy() - lat).max() < 1e-10
    assert np.abs(g["h"].to_numpy() - h).max() < 1e-4
    ts, tl = scene.truth(g["lon"].to_numpy(), g["lat"].to_numpy(), g["h"].to_numpy())
    ok = ~g["outlier"].to_numpy()
    assert ok.sum() >= 60 and np.sqrt(np.mean(np.hypot(g["sample"].to_numpy() - ts, g["line"].to_numpy() - tl)[ok]
                                              ** 2)) <= 0.1
