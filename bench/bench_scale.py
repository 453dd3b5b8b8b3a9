"""Benchmark of issue 14: collect-gcps on full-size scenes, serially, on threads and on a Dask LocalCluster, and
the 50-scene batch apply-calibration.

Prints, in one run:

- windows/s of ``collect_gcps`` on simulated ZY-3 scenes (2.1 m GSD; default sizes 8,192^2 and 24,576^2, built once
  in --workdir by :func:`bench_matching.build`) serially, on 2 threads and on a LocalCluster of 2 worker processes
  (1 thread each), and the Dask overhead against threads (target <= 15 %);
- (each after one untimed warm-up pass: worker start-up and imports are not windows/s)
- the peak RSS of each (the driver's, and for Dask the largest worker's; target <= 2 GB and not growing with the
  scene size: compare the two sizes);
- scenes/minute of the 50-scene batch ``apply-calibration`` on a 2-process LocalCluster.

Each collect run is a child process (``ru_maxrss`` is its own peak). Usage:
    python bench/bench_scale.py [--sizes 8192 24576] [--spacing 256] [--window 64] [--workdir DIR] [--scenes 50]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import bench_matching as bm  # noqa: E402

ZY3_GSD_M = 2.1


def _build(workdir, size):
    bm.GSD = ZY3_GSD_M
    return bm.build(os.path.join(workdir, "zy3"), size)


def child_collect(args):
    """One collect run in this (child) process; prints a JSON line."""
    from gdal_gf4cal.executors import get_executor
    from gdal_gf4cal.matching import collect_gcps
    raw, ref, rpc = _build(args.workdir, args.size)
    biased = bm.biased_rpc(rpc, (args.size, args.size))
    import geopandas  # noqa: F401  (one-off import, not matching time)
    with get_executor(args.mode) as ex:
        # One untimed pass: worker processes import the engine and open their datasets once (steady state).
        collect_gcps(raw, biased, ref, bm.HEIGHT, spacing_px=args.spacing, window_px=args.window, executor=ex,
                     search_px=16)
        t = time.perf_counter()
        g = collect_gcps(raw, biased, ref, bm.HEIGHT, spacing_px=args.spacing, window_px=args.window,
                         executor=ex, search_px=16)
        dt = time.perf_counter() - t
        worker_rss_mb = 0.0
        if hasattr(ex, "_client"):
            rss = ex._client.run(lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
            worker_rss_mb = max(rss.values()) / 1024
    w = g.attrs["windows"]
    err = bm._truth_errors(rpc, g["lon"].to_numpy(), g["lat"].to_numpy(), g["h"].to_numpy(),
                           g["sample"].to_numpy(), g["line"].to_numpy())
    inl = ~g["outlier"].to_numpy(bool)
    print(json.dumps({"mode": args.mode, "size": args.size, "windows": w["total"], "seconds": dt,
                      "windows_per_s": w["total"] / dt, "n_gcps": int(inl.sum()),
                      "rmse_px": float(np.sqrt(np.mean(err[inl] ** 2))) if inl.any() else None,
                      "driver_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "worker_rss_mb": worker_rss_mb}), flush=True)


def batch_scenes_per_minute(workdir, n, mode="local:2"):
    """Scenes/minute of batch apply-calibration over ``n`` GF4-like RPB scenes on ``mode``."""
    import shutil
    from gdal_gf4cal.batch import apply_calibration_batch
    from gdal_gf4cal.camera import LookAngleModel
    from gdal_gf4cal.executors import get_executor
    W, K = 10240, 1.30e-6
    cur = LookAngleModel.from_nominal((W, W), 1.0, K, radial_k1=2.0, name="current")
    S, L = (a.ravel() for a in np.meshgrid(np.linspace(0, W, 21), np.linspace(0, W, 21)))
    tx, ty = cur.tan_angles(S, L)
    new = LookAngleModel.fit(S, L, tx * (1 + 2e-4) + 3 * K, ty * (1 + 2e-4) - 2 * K, size=(W, W), name="new")
    folder = os.path.join(workdir, "batch")
    shutil.rmtree(folder, ignore_errors=True)
    os.makedirs(os.path.join(folder, "in"))
    rpc = bm.synthetic_rpc((W, W), 50.0)
    scenes = [rpc.write_rpb(os.path.join(folder, "in", f"GF4_PMS_{k:03d}.RPB")) for k in range(n)]
    with get_executor(mode) as ex:
        t = time.perf_counter()
        rep = apply_calibration_batch(cur, new, scenes, os.path.join(folder, "out"), executor=ex)
        dt = time.perf_counter() - t
    return rep["counts"], 60.0 * n / dt


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[8192, 24576])
    ap.add_argument("--spacing", type=int, default=256)
    ap.add_argument("--window", type=int, default=64)
    ap.add_argument("--workdir", default=os.path.join(os.environ.get("TMPDIR", "/tmp"), "gf4cal_bench_scale"))
    ap.add_argument("--scenes", type=int, default=50)
    ap.add_argument("--modes", nargs="+", default=["serial", "threads:2", "local:2"])
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--mode", help=argparse.SUPPRESS)
    ap.add_argument("--size", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child_collect(args)
    res = {}
    for size in args.sizes:
        _build(args.workdir, size)       # once, outside the timed children
        for mode in args.modes:
            out = subprocess.run([sys.executable, __file__, "--child", "--mode", mode, "--size", str(size),
                                  "--spacing", str(args.spacing), "--window", str(args.window), "--workdir",
                                  args.workdir], capture_output=True, text=True, check=True)
            r = json.loads(out.stdout.strip().splitlines()[-1])
            res[(size, mode)] = r
            print(f"{size:>6}^2 {mode:>10}: {r['windows_per_s']:8.1f} windows/s ({r['windows']} windows, "
                  f"{r['seconds']:.1f} s, {r['n_gcps']} GCPs, rmse {r['rmse_px']:.3f} px); peak RSS driver "
                  f"{r['driver_rss_mb']:.0f} MB, worker {r['worker_rss_mb']:.0f} MB", flush=True)
    counts, spm = batch_scenes_per_minute(args.workdir, args.scenes)
    print(f"batch apply-calibration, {args.scenes} scenes on local:2: {spm:.1f} scenes/minute ({counts})")
    big = max(args.sizes)
    th, dk = res.get((big, "threads:2")), res.get((big, "local:2"))
    summary = []
    if th and dk:
        over = th["windows_per_s"] / dk["windows_per_s"] - 1
        summary.append(f"Dask overhead vs threads at 2 workers ({big}^2): {100 * over:+.1f} % (target <= 15 %)")
    peak = max(max(r["driver_rss_mb"], r["worker_rss_mb"]) for r in res.values())
    summary.append(f"peak RSS {peak:.0f} MB (target <= 2048 MB)")
    if len(args.sizes) > 1:
        small = min(args.sizes)
        for mode in args.modes:
            a, b = res[(small, mode)], res[(big, mode)]
            summary.append(f"{mode} RSS {small}^2 -> {big}^2: {max(a['driver_rss_mb'], a['worker_rss_mb']):.0f} -> "
                           f"{max(b['driver_rss_mb'], b['worker_rss_mb']):.0f} MB")
    print("summary: " + "; ".join(summary) + f"; {spm:.1f} scenes/minute")


if __name__ == "__main__":
    main()
