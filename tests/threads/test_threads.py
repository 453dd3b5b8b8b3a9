"""GF4CAL_NUM_THREADS (issue 23): the point kernels give bit-identical results with 1, 2 and 3 threads.

2e5 points (several blocks of :data:`gdal_gf4cal.threads.BLOCK` and :data:`~gdal_gf4cal.threads.DEM_BLOCK`) on the
real Pleiades Ventoux RPC, with NaN inputs and points that have no solution, on the real SRTM tile and on a 0.5 m
urban DSM with holes; the sensor-model mixin paths on every model kind of the engine; the thread pool itself (limits,
nesting, errors); a tiled DEM sampled from several threads at once; blocks that leave project/localize unchanged.
"""
from __future__ import annotations

import threading

import numpy as np
import pytest

from gdal_gf4cal import DEM, RPCModel, threads
from gdal_gf4cal.errors import Gf4calError
from gdal_gf4cal.localization import localize_dem
from gdal_gf4cal.simulate.dsm import urban_dsm

N = 200_000
THREADS = ("1", "2", "3")


def _per_thread_count(monkeypatch, fn):
    """``fn()`` under GF4CAL_NUM_THREADS = 1, 2, 3: the three results (tuples of arrays)."""
    out = []
    for k in THREADS:
        monkeypatch.setenv(threads.ENV, k)
        assert threads.num_threads() == int(k)
        out.append(tuple(np.asarray(a) for a in fn()))
    return out


def _assert_bit_identical(results):
    first = results[0]
    for other in results[1:]:
        for a, b in zip(first, other):
            assert a.shape == b.shape
            assert np.array_equal(a, b, equal_nan=True), "results differ between thread counts"


@pytest.fixture(scope="module")
def ventoux(ventoux_rpc_path):
    return RPCModel.from_file(ventoux_rpc_path)


def _image_points(rpc, n, seed):
    """Points over the image and 20 % beyond it, with NaN coordinates sprinkled in."""
    w, h = rpc.image_size
    rng = np.random.default_rng(seed)
    s = rng.uniform(-0.2 * w, 1.2 * w, n)
    l = rng.uniform(-0.2 * h, 1.2 * h, n)
    s[rng.choice(n, 300, replace=False)] = np.nan
    l[rng.choice(n, 300, replace=False)] = np.nan
    return s, l


def test_rpc_project_and_localize_bit_identical(ventoux, monkeypatch):
    s, l = _image_points(ventoux, N, seed=1)
    rng = np.random.default_rng(2)
    h = rng.uniform(*ventoux.height_range, N)
    h[:50] = 1e7                                             # far outside the RPC's cube: no solution (NaN)
    res = _per_thread_count(monkeypatch, lambda: ventoux.localize(s, l, h, full_output=True)[:2])
    _assert_bit_identical(res)
    lon, lat = res[0]
    assert np.isnan(lon[:50]).all() and np.isnan(lon[np.isnan(s)]).all()
    assert np.isfinite(lon).mean() > 0.9
    ok = np.isfinite(lon)
    proj = _per_thread_count(monkeypatch, lambda: ventoux.project(lon.reshape(400, 500), lat.reshape(400, 500),
                                                                  h.reshape(400, 500), pixel_convention="rpc"))
    _assert_bit_identical(proj)
    ps, pl = (a.ravel() + 0.5 for a in proj[0])
    assert proj[0][0].shape == (400, 500)
    assert np.max(np.hypot(ps[ok] - s[ok], pl[ok] - l[ok])) < 1e-6     # the round trip, whatever the blocks


def test_localize_dem_bit_identical_on_srtm(ventoux, srtm_path, monkeypatch):
    dem = DEM.from_file(srtm_path, geoid="egm96", nodata="nan")
    s, l = _image_points(ventoux, N, seed=4)
    res = _per_thread_count(monkeypatch, lambda: ventoux.localize_dem(s, l, dem))
    _assert_bit_identical(res)
    lon, lat, h = res[0]
    assert np.isfinite(h).mean() > 0.6 and np.isnan(h[np.isnan(s)]).all()
    ok = np.isfinite(h)
    assert np.max(np.abs(dem.sample(lon[ok], lat[ok]) - h[ok])) <= 1e-4


@pytest.fixture(scope="module")
def dsm(srtm_path, tmp_path_factory):
    """The 0.5 m urban DSM with holes of tests/localization/test_localize_dsm.py (seed 0)."""
    path = tmp_path_factory.mktemp("dsm") / "dsm.tif"
    urban_dsm(path, DEM.from_file(srtm_path, geoid="egm96"), (5.2872, 44.1357), seed=0)
    return DEM.from_file(path, nodata="nan")


def _dsm_points(rpc, dsm, n, seed):
    """Image points over the DSM's footprint and 20 px beyond it (those rays miss it: NaN)."""
    b = dsm.bounds_lonlat()
    lo, hi = dsm.height_range()
    cs, cl = rpc.project(np.array([b[0], b[2], b[0], b[2]]), np.array([b[1], b[1], b[3], b[3]]),
                         np.full(4, 0.5 * (lo + hi)))
    rng = np.random.default_rng(seed)
    return rng.uniform(cs.min() - 20, cs.max() + 20, n), rng.uniform(cl.min() - 20, cl.max() + 20, n)


def test_localize_dem_bit_identical_on_a_dsm_with_holes(ventoux, dsm, monkeypatch):
    s, l = _dsm_points(ventoux, dsm, N, seed=5)
    res = _per_thread_count(monkeypatch, lambda: localize_dem(ventoux, s, l, dsm))
    _assert_bit_identical(res)
    assert 0.5 < np.isfinite(res[0][2]).mean() < 0.99


def test_generic_dsm_intersection_bit_identical(ventoux, dsm, monkeypatch):
    """The generic path (any model: march, Illinois, bridged holes) in smaller blocks (fixed by the number of points
    whatever the block size; a smaller one keeps the test short)."""
    monkeypatch.setattr(threads, "BLOCK", 4096)
    monkeypatch.setattr(threads, "DEM_BLOCK", 4096)
    s, l = _dsm_points(ventoux, dsm, 3 * 4096 + 77, seed=8)
    res = _per_thread_count(monkeypatch, lambda: localize_dem(ventoux, s, l, dsm, fast_path=False))
    _assert_bit_identical(res)
    assert 0.5 < np.isfinite(res[0][2]).mean() < 0.99


def test_sensor_model_mixin_paths_bit_identical(sensor_model, monkeypatch):
    """project, localize and localize_dem of every model kind, in blocks of 4096 points (a smaller block keeps the
    simulator's models quick; the blocks are fixed by the number of points whatever the block size)."""
    name, model, dem, (w, h) = sensor_model
    monkeypatch.setattr(threads, "BLOCK", 4096)
    monkeypatch.setattr(threads, "DEM_BLOCK", 4096)
    n = 3 * 4096 + 123                                   # four blocks
    rng = np.random.default_rng(6)
    s, l = rng.uniform(0, w, n), rng.uniform(0, h, n)
    s[:7] = np.nan
    hh = rng.uniform(*model.height_range, n)
    loc = _per_thread_count(monkeypatch, lambda: model.localize(s, l, hh))
    _assert_bit_identical(loc)
    lon, lat = loc[0]
    assert np.isnan(lon[:7]).all() and np.isfinite(lon[7:]).all()
    _assert_bit_identical(_per_thread_count(monkeypatch, lambda: model.project(lon, lat, hh)))
    k = np.r_[0:40, n - 40:n]                            # DEM intersections: a few points of two blocks
    sd, ld = np.full(n, np.nan), np.full(n, np.nan)
    sd[k], ld[k] = s[k], l[k]
    res = _per_thread_count(monkeypatch, lambda: model.localize_dem(sd, ld, dem))
    _assert_bit_identical(res)
    assert np.isfinite(res[0][2][k[7:]]).all()


def test_num_threads_setting(monkeypatch):
    monkeypatch.delenv(threads.ENV, raising=False)
    assert threads.num_threads() == threads.machine_cores() >= 1
    monkeypatch.setenv(threads.ENV, " 3 ")
    assert threads.num_threads() == 3
    with threads.limit(2):
        assert threads.num_threads() == 2
        with threads.limit(None):                      # None: unchanged
            assert threads.num_threads() == 2
    assert threads.num_threads() == 3
    for bad in ("0", "-2", "two", "1.5"):
        monkeypatch.setenv(threads.ENV, bad)
        with pytest.raises(threads.ThreadSettingError, match="GF4CAL_NUM_THREADS"):
            threads.num_threads()


def test_a_bad_setting_is_refused_in_one_line(monkeypatch, ventoux):
    """A kernel that would split refuses a bad GF4CAL_NUM_THREADS with a Gf4calError (one line; exit 2 at the CLI);
    one that would not split never reads it."""
    monkeypatch.setenv(threads.ENV, "many")
    n = threads.BLOCK + 1
    with pytest.raises(Gf4calError) as err:
        ventoux.localize(np.zeros(n), np.zeros(n), 0.0)
    assert "\n" not in str(err.value) and "'many'" in str(err.value)
    assert np.isfinite(ventoux.localize(100.0, 100.0, 0.0)[0])


def test_blocks_are_fixed_and_nested_kernels_stay_serial(monkeypatch):
    assert threads.block_slices(10) == [slice(0, 10)]
    assert threads.block_slices(2 * threads.BLOCK + 1)[-1] == slice(2 * threads.BLOCK, 2 * threads.BLOCK + 1)
    monkeypatch.setenv(threads.ENV, "3")
    seen = []

    def fn(sl):
        seen.append((sl.start, threads.num_threads(), threading.current_thread().name))
        return sl.stop - sl.start

    assert threads.map_blocks(fn, 10 * 1000, block=1000) == [1000] * 10
    assert sorted(s for s, _, _ in seen) == list(range(0, 10000, 1000))
    assert all(k == 1 for _, k, _ in seen)              # inside a block: serial, never a nested split
    assert threads.num_threads() == 3                   # the caller's setting is back


def test_rounds_give_every_thread_an_item_in_order():
    items = list(range(7))
    for k, sizes in ((1, [1] * 7), (2, [2, 2, 2, 1]), (3, [3, 3, 1])):
        with threads.limit(k):
            rounds = list(threads.rounds(items))
        assert [len(r) for r in rounds] == sizes and [i for r in rounds for i in r] == items
    with threads.limit(2):
        assert list(threads.rounds([])) == []


def test_the_first_failing_block_is_raised(monkeypatch):
    monkeypatch.setenv(threads.ENV, "2")

    def fn(sl):
        if sl.start >= 3000:
            raise ValueError(f"block at {sl.start}")
        return sl.start

    with pytest.raises(ValueError, match="block at 3000$"):
        threads.map_blocks(fn, 8000, block=1000)
    monkeypatch.setenv(threads.ENV, "1")
    with pytest.raises(ValueError, match="block at 3000$"):
        threads.map_blocks(fn, 8000, block=1000)


def test_a_tiled_dem_sampled_from_threads_at_once(tmp_path):
    """A DEM too large to hold in memory is read tile by tile through one GDAL dataset (GDAL releases the GIL while it
    reads and decompresses): several threads sampling it at once, tiles evicted from a small cache all along, get
    what one thread gets."""
    from osgeo import gdal, osr
    n = 4100                                             # > 16 Mpx: windowed reads
    x = np.linspace(0.0, 60.0, n)
    Z = (500.0 + 200.0 * np.sin(x)[None, :] * np.cos(x)[:, None]).astype(np.uint16)
    ds = gdal.GetDriverByName("GTiff").Create(str(tmp_path / "big.tif"), n, n, 1, gdal.GDT_UInt16,
                                              ["TILED=YES", "BLOCKXSIZE=128", "BLOCKYSIZE=128", "COMPRESS=DEFLATE"])
    ds.SetGeoTransform((5.0, 1e-4, 0.0, 44.5, 0.0, -1e-4))
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(4326)
    ds.SetProjection(srs.ExportToWkt())
    ds.GetRasterBand(1).WriteArray(Z)
    ds = None
    dem = DEM(path=str(tmp_path / "big.tif"), nodata="nan", tile_size=192, cache_tiles=2)
    assert not dem.height_range_is_exact
    rng = np.random.default_rng(7)
    lon = rng.uniform(5.0, 5.41, (8, 20000))
    lat = rng.uniform(44.09, 44.5, (8, 20000))
    want = [dem.sample(lon[i], lat[i]) for i in range(8)]
    got = [[] for _ in range(8)]

    def run(i):
        for _ in range(2):
            got[i].append(dem.sample(lon[i], lat[i]))

    workers = [threading.Thread(target=run, args=(i,)) for i in range(8)]
    cache = gdal.GetCacheMax()
    gdal.SetCacheMax(1 << 20)                            # GDAL's own block cache small too: every read decompresses
    try:
        for t in workers:
            t.start()
        for t in workers:
            t.join()
    finally:
        gdal.SetCacheMax(cache)
    for i in range(8):
        assert len(got[i]) == 2
        for g in got[i]:
            assert np.array_equal(g, want[i], equal_nan=True)
    assert np.isfinite(want[0]).all()


def _worker_threads(_):
    return threads.num_threads()


def test_dask_workers_keep_one_thread_each():
    """The workers of a local Dask cluster run the point kernels on one thread (the cluster parallelises)."""
    from gdal_gf4cal.executors import get_executor
    with get_executor("local:1") as ex:
        assert ex.submit(_worker_threads, 0).result() == 1


def test_ortho_ellipsoidal_dem_bit_identical(srtm_path, tmp_path, monkeypatch):
    """The ortho's own per-pixel step (DEM heights above EGM96 -> ellipsoidal, h = H + N) in blocks over the pool."""
    from osgeo import gdal
    from gdal_gf4cal.geoid import resolve_geoid
    from gdal_gf4cal.workflows.ortho import write_ellipsoidal_dem
    grid = resolve_geoid("egm96")
    bounds = (5.05, 44.05, 5.45, 44.45)                  # ~ 480 x 480 SRTM pixels: four blocks
    out = []
    for k in THREADS:
        monkeypatch.setenv(threads.ENV, k)
        path = write_ellipsoidal_dem(str(srtm_path), grid, bounds, str(tmp_path / f"ell{k}.tif"))
        out.append(gdal.Open(path).ReadAsArray())
    assert out[0].size > 3 * threads.BLOCK
    assert np.array_equal(out[0], out[1]) and np.array_equal(out[0], out[2])
    src = gdal.Open(str(srtm_path))
    ds = gdal.Open(str(tmp_path / "ell1.tif"))
    x0 = int(round((ds.GetGeoTransform()[0] - src.GetGeoTransform()[0]) / src.GetGeoTransform()[1]))
    y0 = int(round((ds.GetGeoTransform()[3] - src.GetGeoTransform()[3]) / src.GetGeoTransform()[5]))
    H = src.GetRasterBand(1).ReadAsArray(x0, y0, ds.RasterXSize, ds.RasterYSize).astype(float)
    valid = out[0] != -9999.0                           # SRTM voids stay no-data
    assert valid.mean() > 0.99
    undulation = out[0][valid] - H[valid]
    assert 49.0 < undulation.min() and undulation.max() < 53.0      # EGM96 over Mont Ventoux: N ~ 50-52 m


def test_block_size_does_not_change_project_and_localize(ventoux, monkeypatch):
    """project and localize compute every point on its own: 1.5 BLOCK points split into blocks (any thread count) give
    the bits of one unsplit call, the serial path as it was before blocks existed."""
    n = threads.BLOCK * 3 // 2 + 5
    s, l = _image_points(ventoux, n, seed=11)
    h = np.random.default_rng(12).uniform(*ventoux.height_range, n)
    monkeypatch.setenv(threads.ENV, "2")
    split = ventoux.localize(s, l, h) + ventoux.project(s * 1e-5 + 5.2, l * 1e-5 + 44.1, h)
    monkeypatch.setattr(threads, "BLOCK", 10 ** 9)
    whole = ventoux.localize(s, l, h) + ventoux.project(s * 1e-5 + 5.2, l * 1e-5 + 44.1, h)
    _assert_bit_identical([tuple(split), tuple(whole)])
    assert np.isfinite(whole[0]).mean() > 0.9


def test_a_product_gives_each_column_the_bits_of_any_wider_product():
    """threads.product_into: a (4, 20) x (20, n) product of the point kernels gives every column the bits it has in
    the product of all 4099 columns, for every width and offset: OpenBLAS's AVX-512 dgemm (SkylakeX, Cooperlake)
    computes a tail of 1 to 4 columns with another kernel (1 ulp off), which np.matmul alone shows there."""
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(4, 20)), rng.normal(size=(20, 4099))
    with threads.serial():                              # BLAS on this thread, as in every block
        whole = threads.product_into(a, b, np.empty((4, 4099)))
        for start in (0, 3, 8):
            for n in list(range(1, 41)) + [1001, 4091]:
                part = threads.product_into(a, b[:, start:start + n], np.empty((4, n)))
                assert np.array_equal(part, whole[:, start:start + n]), (start, n)
        assert np.array_equal(threads.matmul(a, b), whole)


@pytest.mark.parametrize("rows, n", [(4, 32768), (12, 16384), (16, 20000), (2, 4101)])
def test_a_product_in_small_matrix_slices_gives_the_bits_of_one_product(rows, n):
    """threads.product_into splits a product wider than the small-matrix kernel's reach (SkylakeX, Cooperlake:
    M x N x K <= SMALL_GEMM_MNK) into column slices: every column the bits of the one np.matmul of all whole
    column groups (BLAS's packed kernel there), on every kernel the suite runs under."""
    rng = np.random.default_rng(rows)
    a, b = rng.normal(size=(rows, 20)), rng.normal(size=(20, n))
    whole = n - n % threads.COLUMN_GROUP
    with threads.serial():
        sliced = threads.product_into(a, b, np.empty((rows, n)))
        one = np.matmul(a, b[:, :whole])
    assert np.array_equal(sliced[:, :whole], one)
    step = threads._gemm_columns(rows, 20)
    assert step is None or (step % threads.COLUMN_GROUP == 0 and rows * 20 * step <= threads.SMALL_GEMM_MNK)


def test_a_product_never_looks_for_the_blas_libraries(monkeypatch):
    """product_into runs on pool threads while others import modules: it must not walk the loaded libraries
    (threadpoolctl's scan holds the dynamic loader's lock and waits for the GIL; an import holds the GIL and waits
    for that lock: register-pan-ms hung so). It uses what blas_serial found."""
    def scan():
        raise AssertionError("product_into looked for the BLAS libraries")
    rng = np.random.default_rng(5)
    a, b = rng.normal(size=(12, 20)), rng.normal(size=(20, 20000))
    with threads.serial():                   # the scope is open: only a new look would call the scan below
        expected = np.matmul(a, b)
        monkeypatch.setattr(threads, "_blas_controller", scan)
        got = threads.product_into(a, b, np.empty((12, 20000)))
    assert np.array_equal(got, expected)


def test_kernels_give_the_same_bits_whatever_the_allocator_did(sensor_model):
    """project, localize and localize_dem of every model kind give the same bits call after call while other
    arrays come and go between the calls: on AVX-512 CPUs NumPy computes transcendental ufuncs (arctan2, sin, exp ...)
    with SIMD code unless a strided input's span touches the output's memory, where libm's result, 1 ulp away, was
    taken: the bits then depended on where the allocator put a temporary (the simulator's ecef_to_geodetic did)."""
    name, model, dem, (w, h) = sensor_model
    rng = np.random.default_rng(9)
    n = 123
    s, l = rng.uniform(0, w, n), rng.uniform(0, h, n)
    s[:40] = np.nan
    hh = rng.uniform(*model.height_range, n)
    runs, keep = [], []
    with threads.limit(1):
        for i in range(12):
            keep.append(np.empty(int(rng.integers(1, 4000))))      # the allocator's state moves between the calls
            if i % 3 == 2:
                keep.pop(int(rng.integers(0, len(keep))))
            lon, lat = model.localize(s, l, hh)
            runs.append((lon, lat) + tuple(model.project(lon, lat, hh)) + tuple(model.localize_dem(s, l, dem)))
    _assert_bit_identical(runs)
