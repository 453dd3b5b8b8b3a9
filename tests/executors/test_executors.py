"""Issue 14: one unit of work, three executors (gdal_gf4cal.executors)."""
from __future__ import annotations

import time

import numpy as np
import pytest

from gdal_gf4cal.executors import ExecutorError, get_executor, map_ordered
from gdal_gf4cal.workflows.collect import collect_gcps_file

from matchscene import build_scene, error_affine

SIZE = (320, 320)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("exec")
    sc = build_scene(folder, texture="pleiades", size=SIZE, seed=3,
                     error=error_affine(shift=(12.2, -9.4), rotation_rad=0.001, scale=0.999, center=(160, 160)))
    sc.rpc.write_rpb(str(folder / "raw.RPB"))
    return sc


def _collect(scene, out, spec):
    with get_executor(spec) as ex:
        return collect_gcps_file(scene.image, scene.reference, scene.dem_path, out, executor=ex,
                                 spacing_px=40, window_px=64, tile_windows=4, keep_outliers=True)


def test_same_gcp_table_bit_for_bit_serial_threads_localcluster(scene, tmp_path):
    """The SAME GCP table (every column, every bit; the CSV byte for byte) serially, on threads and on a
    LocalCluster with 2 worker processes; and it is right (truth from the simulation)."""
    reps = {}
    for spec in ("serial", "threads:2", "local:2"):
        reps[spec] = _collect(scene, tmp_path / f"{spec.replace(':', '_')}.csv", spec)
    base = reps["serial"]["gcps"]
    assert len(base) >= 20 and reps["serial"]["windows"]["total"] >= 25
    ts, tl = scene.truth(base["lon"].to_numpy(), base["lat"].to_numpy(), base["h"].to_numpy())
    inl = ~base["outlier"].to_numpy(bool)
    assert np.sqrt(np.mean((base["sample"][inl] - ts[inl]) ** 2 + (base["line"][inl] - tl[inl]) ** 2)) <= 0.1
    data = {k: (tmp_path / f"{k.replace(':', '_')}.csv").read_bytes() for k in reps}
    for spec in ("threads:2", "local:2"):
        g = reps[spec]["gcps"]
        assert list(g.columns) == list(base.columns) and len(g) == len(base)
        for c in base.columns:
            if c == "geometry":
                continue
            a, b = base[c].to_numpy(), g[c].to_numpy()
            if a.dtype.kind == "f":
                assert np.array_equal(a.view(np.uint64), b.view(np.uint64)), (spec, c)
            else:
                assert np.array_equal(a, b), (spec, c)
        assert data[spec] == data["serial"], spec
        assert reps[spec]["windows"] == reps["serial"]["windows"]


def _square(x):
    time.sleep(0.01 * ((7 * x) % 3))  # completes out of order
    return x * x


def test_map_ordered_gathers_in_submission_order_and_reports_progress():
    seen = []
    with get_executor("threads:3") as ex:
        out = map_ordered(_square, list(range(12)), ex, progress=lambda f, m: seen.append(f))
    assert out == [x * x for x in range(12)]
    # one report per wait round (tasks finishing together under load share one): counts of finished tasks,
    # never decreasing, ending at all of them
    assert seen[-1] == 1.0 and 1 <= len(seen) <= 12 and seen == sorted(seen)
    assert all(abs(f * 12 - round(f * 12)) < 1e-9 for f in seen)


def test_unreachable_scheduler_is_one_line_error():
    t0 = time.monotonic()
    with pytest.raises(ExecutorError) as e:
        with get_executor("tcp://127.0.0.1:9", connect_timeout_s=2):
            pass
    assert time.monotonic() - t0 < 30
    assert "cannot reach the Dask scheduler at tcp://127.0.0.1:9" in str(e.value) and "\n" not in str(e.value)


def test_unknown_executor_spec():
    with pytest.raises(ExecutorError, match="unknown executor"):
        with get_executor("spark://x"):
            pass


def _malloc_env(_):
    import os
    return {k: os.environ.get(k) for k in ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_", "OMP_NUM_THREADS")}


def test_local_cluster_workers_keep_tile_sized_arrays_on_the_heap():
    """Dask's default MALLOC_TRIM_THRESHOLD_=65536 turns every array > 128 KB into a fresh mmap (page faults:
    matching ~1.5x slower than on threads); our local workers get glibc's adaptive maxima instead."""
    from gdal_gf4cal.executors import WORKER_ENV
    with get_executor("local:1") as ex:
        env = ex.submit(_malloc_env, 0).result()
    assert env == {"MALLOC_TRIM_THRESHOLD_": str(64 * 2 ** 20), "MALLOC_MMAP_THRESHOLD_": str(32 * 2 ** 20),
                   "OMP_NUM_THREADS": "1"}
    assert int(WORKER_ENV["MALLOC_MMAP_THRESHOLD_"]) >= 16 * 2 ** 20
