"""Benchmark of issue 14: collect-gcps on full-size simulated ZY-3 scenes, serially, on threads and on a Dask
LocalCluster, the memory of rendering them, and the 50-scene batch apply-calibration.

Scenes (built once, cached in ``--cache``: ``$GF4CAL_BENCH_CACHE`` or ``/tmp/gf4cal_bench``, so reruns are quick):
the ZY-3 nadir camera (2.1 m GSD) cropped to 8,192^2 and 24,576^2 (the full detector) by the simulator
(``make_scene("zy3", seed=0, size=...)``), rendered through its TRUE model from the built-in texture
(:func:`gdal_gf4cal.simulate.render_image`, tiled), its reference orthophoto (:func:`write_reference_ortho`), its
DEM, and ``scene.RPB`` = the RPC of the CURRENT model (attitude and camera errors of a few px: what the GCPs
measure). Truth of a GCP ``(lon, lat, h)``: ``true.project(lon, lat, h)``. Each build runs in a child process
and records its peak RSS (the rendering audit of issue 14: it must not grow with the scene size).

Prints, in one run:

- windows/s of ``collect_gcps`` serially, on 2 threads and on a LocalCluster of 2 worker processes (1 thread each)
  at both sizes, each after one untimed warm-up pass; the cluster's start-up is reported apart (it is paid once
  per batch, not per window);
- the Dask overhead against threads at 2 workers (target <= 15 %);
- the peak RSS of each run (the driver's, and for Dask the largest worker's; target <= 2 GB, not growing from
  8,192^2 to 24,576^2) and of each render;
- scenes/minute of the 50-scene batch ``apply-calibration`` on a 2-process LocalCluster;
- the machine's load (``uptime``) before and after: the machine is shared.

Each collect run is a child process (``ru_maxrss`` is its own peak). Usage:
    python bench/bench_scale.py [--sizes 8192 24576] [--spacing 256] [--window 64] [--cache DIR] [--scenes 50]
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

SEED = 0


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def cache_dir(arg=None) -> str:
    return arg or os.environ.get("GF4CAL_BENCH_CACHE") or os.path.join("/tmp", "gf4cal_bench")


HEIGHT_M = 1000.0        # the scenes' terrain: a constant height (the throughput of matching does not depend on it)
PATCH = 2048             # the reference is a mosaic of shifted copies of one PATCH^2 texture patch


def _scene(size):
    from gdal_gf4cal.simulate import make_scene
    return make_scene("zy3", seed=SEED, size=(size, size), dem=HEIGHT_M)


def scene_paths(cache, size):
    d = os.path.join(cache, f"zy3_nadir_{size}")
    return {k: os.path.join(d, f) for k, f in (("dir", ""), ("image", "scene.tif"), ("rpc", "scene.RPB"),
                                                ("reference", "reference.tif"), ("meta", "build.json"))}


def _write_reference(path, bounds, res_deg, seed=SEED, scale_m=6.3):
    """The reference orthophoto (EPSG:4326 Byte GeoTIFF over ``bounds``): the simulator's texture on one
    PATCH^2 patch, tiled with per-block shifts (no two blocks alike), written block by block. A full-size
    texture evaluation (~700 Mpx) takes an hour on a shared 2-core machine; the scene is rendered FROM this
    reference, so image and reference agree whatever its content."""
    from osgeo import gdal
    from gdal_gf4cal.simulate import texture_value
    from gdal_gf4cal.simulate.render import create_ortho_tif
    x0, y0, x1, y1 = bounds
    nx, ny = int(np.ceil((x1 - x0) / res_deg)), int(np.ceil((y1 - y0) / res_deg))
    lon = x0 + (np.arange(PATCH) + 0.5) * res_deg
    lat = y1 - (np.arange(PATCH) + 0.5) * res_deg
    patch = np.empty((PATCH, PATCH), np.uint8)
    for r in range(0, PATCH, 256):      # in strips: texture_value's temporaries stay small
        v = texture_value(*np.meshgrid(lon, lat[r:r + 256]), seed, scale_m)
        patch[r:r + 256] = np.clip(np.round(20 + 220 * v), 1, 255).astype(np.uint8)
    gdal.UseExceptions()
    tmp = path + ".tmp.tif"
    ds = create_ortho_tif(tmp, nx, ny, (x0, y1), res_deg)
    band = ds.GetRasterBand(1)
    for j in range(0, ny, PATCH):
        for i in range(0, nx, PATCH):
            k = (j // PATCH) * 7 + i // PATCH
            blk = np.roll(np.roll(patch, 517 * k, axis=1), 313 * k, axis=0)
            if k % 2:
                blk = blk.T.copy()
            band.WriteArray(blk[:min(PATCH, ny - j), :min(PATCH, nx - i)], i, j)
            ds.FlushCache()
    ds = None
    os.replace(tmp, path)


def child_build(args):
    """Build one part of one scene into the cache in this child process (``reference``, then ``image``: the
    engine's tiled render, whose peak RSS is this process's); prints a JSON line and writes it beside the scene."""
    from gdal_gf4cal.rpc_fit import fit_rpc_from_model
    from gdal_gf4cal.simulate.render import model_bounds, render_image
    p = scene_paths(args.cache, args.size)
    os.makedirs(p["dir"], exist_ok=True)
    sc = _scene(args.size)
    im = sc.image("nadir")
    t = time.perf_counter()
    if args.part == "reference":
        W, H = im.size
        _write_reference(p["reference"], model_bounds(im.true, margin=max(0.03, 128.0 / min(W, H))),
                         im.gsd_m / 111320.0, scale_m=3.0 * im.gsd_m)
    else:
        rpc, _ = fit_rpc_from_model(im.current)
        rpc.write_rpb(p["rpc"], overwrite=True)
        render_image(im.true, sc.dem, p["image"], reference=p["reference"], gsd_m=im.gsd_m, workers=args.workers)
    meta = {"size": args.size, "part": args.part, "seconds": time.perf_counter() - t, "rss_mb": _rss_mb(),
            "workers": args.workers}
    with open(p["meta"] + f".{args.part}", "w") as fh:
        json.dump(meta, fh)
    print(json.dumps(meta), flush=True)


def build(cache, size, workers=2):
    """The cached scene of ``size`` (reference then image, each built in a child process the first time);
    returns ``{part: build record}``."""
    p = scene_paths(cache, size)
    out = {}
    for part in ("reference", "image"):
        if not os.path.exists(p["meta"] + f".{part}"):
            print(f"building the {size}^2 ZY-3 scene's {part} in {p['dir']} (once) ...", flush=True)
            r = subprocess.run([sys.executable, __file__, "--child-build", "--part", part, "--size", str(size),
                                "--cache", cache, "--workers", str(workers)], capture_output=True, text=True)
            if r.returncode:
                sys.exit(f"scene build ({part}) failed:\n{r.stderr}")
        with open(p["meta"] + f".{part}") as fh:
            out[part] = dict(json.load(fh), cached=False)
    return out


def child_collect(args):
    """One collect run in this (child) process; prints a JSON line."""
    from gdal_gf4cal.executors import get_executor
    from gdal_gf4cal.matching import collect_gcps
    p = scene_paths(args.cache, args.size)
    true = _scene(args.size).image("nadir").true
    dem = HEIGHT_M
    kw = dict(spacing_px=args.spacing, window_px=args.window, search_px=32)
    if args.tile_windows:
        kw["tile_windows"] = args.tile_windows

    def cpu_s(client):
        """CPU seconds (user + system) of this process and of the Dask workers."""
        r = resource.getrusage(resource.RUSAGE_SELF)
        own = r.ru_utime + r.ru_stime
        if client is None:
            return own, 0.0
        ws = client.run(lambda: sum(resource.getrusage(resource.RUSAGE_SELF)[:2]))
        return own, float(sum(ws.values()))

    t = time.perf_counter()
    with get_executor(args.mode) as ex:
        startup = time.perf_counter() - t
        client = getattr(ex, "_client", None)
        # One untimed pass: worker processes import the engine and open their datasets once (steady state).
        collect_gcps(p["image"], None, p["reference"], dem, executor=ex, **kw)
        dt, cpu = np.inf, (0.0, 0.0)
        for _ in range(max(1, args.repeat)):      # the best of --repeat passes: the machine is shared
            c0 = cpu_s(client)
            t = time.perf_counter()
            g = collect_gcps(p["image"], None, p["reference"], dem, executor=ex, **kw)
            d = time.perf_counter() - t
            c1 = cpu_s(client)
            if d < dt:
                dt, cpu = d, (c1[0] - c0[0], c1[1] - c0[1])
        worker_rss_mb = 0.0
        if client is not None:
            rss = client.run(lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
            worker_rss_mb = max(rss.values()) / 1024
    w = g.attrs["windows"]
    inl = ~g["outlier"].to_numpy(bool)
    ts, tl = true.project(g["lon"].to_numpy(), g["lat"].to_numpy(), g["h"].to_numpy())
    err = np.hypot(g["sample"].to_numpy() - ts, g["line"].to_numpy() - tl)[inl]
    print(json.dumps({"mode": args.mode, "size": args.size, "windows": w["total"], "seconds": dt,
                      "startup_s": startup, "windows_per_s": w["total"] / dt, "n_gcps": int(inl.sum()),
                      "rmse_px": float(np.sqrt(np.mean(err ** 2))) if err.size else None,
                      "offset_px": float(np.hypot(g["dsample"][inl].mean(), g["dline"][inl].mean())),
                      "driver_rss_mb": _rss_mb(), "worker_rss_mb": worker_rss_mb, "cpu_driver_s": cpu[0],
                      "cpu_workers_s": cpu[1]}), flush=True)


def batch_scenes_per_minute(folder, n, mode="local:2"):
    """Scenes/minute of batch apply-calibration over ``n`` GF4-like RPB scenes on ``mode`` (cluster start-up
    excluded, reported apart)."""
    import shutil
    from gdal_gf4cal.batch import apply_calibration_batch
    from gdal_gf4cal.camera import LookAngleModel
    from gdal_gf4cal.executors import get_executor
    from gdal_gf4cal.rpc import RPCModel
    W, K, gsd, lat0 = 10240, 1.30e-6, 50.0, 30.0
    cur = LookAngleModel.from_nominal((W, W), 1.0, K, radial_k1=2.0, name="current")
    S, L = (a.ravel() for a in np.meshgrid(np.linspace(0, W, 21), np.linspace(0, W, 21)))
    tx, ty = cur.tan_angles(S, L)
    new = LookAngleModel.fit(S, L, tx * (1 + 2e-4) + 3 * K, ty * (1 + 2e-4) - 2 * K, size=(W, W), name="new")
    shutil.rmtree(folder, ignore_errors=True)
    os.makedirs(os.path.join(folder, "in"))
    num_s, num_l, den = np.zeros(20), np.zeros(20), np.zeros(20)
    num_s[[1, 2, 3]], num_l[[1, 2, 3]], den[0] = [1.0, 0.015, 0.03], [0.01, -1.0, -0.012], 1.0
    rpc = RPCModel(line_off=W / 2 - 0.5, samp_off=W / 2 - 0.5, lat_off=lat0, long_off=100.0, height_off=500.0,
                   line_scale=W / 2, samp_scale=W / 2, lat_scale=W / 2 * gsd / 110950.0,
                   long_scale=W / 2 * gsd / (111320.0 * np.cos(np.radians(lat0))), height_scale=1000.0,
                   line_num=num_l, line_den=den, samp_num=num_s, samp_den=den)
    scenes = [rpc.write_rpb(os.path.join(folder, "in", f"GF4_PMS_{k:03d}.RPB")) for k in range(n)]
    t = time.perf_counter()
    with get_executor(mode) as ex:
        startup = time.perf_counter() - t
        t = time.perf_counter()
        rep = apply_calibration_batch(cur, new, scenes, os.path.join(folder, "out"), executor=ex)
        dt = time.perf_counter() - t
    return rep["counts"], 60.0 * n / dt, startup


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    except OSError:
        return "?"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[8192, 24576])
    ap.add_argument("--spacing", type=int, default=256)
    ap.add_argument("--window", type=int, default=64)
    ap.add_argument("--cache", default=None, help="scene cache (default $GF4CAL_BENCH_CACHE or /tmp/gf4cal_bench)")
    ap.add_argument("--workers", type=int, default=2, help="render threads when building a scene")
    ap.add_argument("--scenes", type=int, default=50)
    ap.add_argument("--repeat", type=int, default=1, help="timed passes per run (the best is kept)")
    ap.add_argument("--tile-windows", type=int, default=0, help="windows per task (default: the engine's)")
    ap.add_argument("--modes", nargs="+", default=["serial", "threads:2", "local:2"])
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--child-build", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--mode", help=argparse.SUPPRESS)
    ap.add_argument("--size", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--part", choices=("reference", "image"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    args.cache = cache_dir(args.cache)
    if args.child:
        return child_collect(args)
    if args.child_build:
        return child_build(args)
    print(f"load before: {_uptime()}", flush=True)
    builds = {}
    for size in args.sizes:
        b = builds[size] = build(args.cache, size, args.workers)
        print(f"{size:>6}^2 scene: reference {b['reference']['seconds']:.0f} s (peak RSS {b['reference']['rss_mb']:.0f}"
              f" MB), engine render {b['image']['seconds']:.0f} s on {b['image']['workers']} threads (peak RSS "
              f"{b['image']['rss_mb']:.0f} MB)", flush=True)
    res = {}
    for size in args.sizes:
        for mode in args.modes:
            out = subprocess.run([sys.executable, __file__, "--child", "--mode", mode, "--size", str(size),
                                  "--spacing", str(args.spacing), "--window", str(args.window), "--cache",
                                  args.cache, "--repeat", str(args.repeat), "--tile-windows",
                                  str(args.tile_windows)], capture_output=True, text=True)
            if out.returncode:
                sys.exit(f"collect run {size} {mode} failed:\n{out.stderr}")
            r = res[(size, mode)] = json.loads(out.stdout.strip().splitlines()[-1])
            print(f"{size:>6}^2 {mode:>10}: {r['windows_per_s']:7.1f} windows/s ({r['windows']} windows, "
                  f"{r['seconds']:.1f} s; start-up {r['startup_s']:.1f} s apart), {r['n_gcps']} GCPs, rmse vs truth "
                  f"{r['rmse_px']:.3f} px (RPC error {r['offset_px']:.1f} px); peak RSS driver "
                  f"{r['driver_rss_mb']:.0f} MB, worker {r['worker_rss_mb']:.0f} MB; CPU {r['cpu_driver_s']:.1f} s driver + "
                  f"{r['cpu_workers_s']:.1f} s workers", flush=True)
    counts, spm, startup = batch_scenes_per_minute(os.path.join(args.cache, "batch"), args.scenes)
    print(f"batch apply-calibration, {args.scenes} scenes on local:2: {spm:.1f} scenes/minute ({counts}; cluster "
          f"start-up {startup:.1f} s apart)")
    summary = []
    for size in args.sizes:
        th, dk = res.get((size, "threads:2")), res.get((size, "local:2"))
        if th and dk:
            over = th["windows_per_s"] / dk["windows_per_s"] - 1
            cpu = (dk["cpu_driver_s"] + dk["cpu_workers_s"]) / max(th["cpu_driver_s"], 1e-9) - 1
            summary.append(f"Dask overhead vs threads at 2 workers ({size}^2): {100 * over:+.1f} % wall (target <= "
                           f"15 %), {100 * cpu:+.1f} % CPU")
    peak = max(max(r["driver_rss_mb"], r["worker_rss_mb"]) for r in res.values())
    summary.append(f"peak RSS matching {peak:.0f} MB (target <= 2048 MB)")
    if len(args.sizes) > 1:
        small, big = min(args.sizes), max(args.sizes)
        for mode in args.modes:
            a, b = res[(small, mode)], res[(big, mode)]
            summary.append(f"{mode} RSS {small}^2 -> {big}^2: {max(a['driver_rss_mb'], a['worker_rss_mb']):.0f} -> "
                           f"{max(b['driver_rss_mb'], b['worker_rss_mb']):.0f} MB")
        summary.append(f"render RSS {small}^2 -> {big}^2: {builds[small]['image']['rss_mb']:.0f} -> "
                       f"{builds[big]['image']['rss_mb']:.0f} MB")
    print("summary: " + "; ".join(summary) + f"; {spm:.1f} scenes/minute")
    print(f"load after: {_uptime()}")


if __name__ == "__main__":
    main()
