"""Benchmark of the simulator (METHODS §10): full-size scene writing, RPC fit accuracy per sensor, tiled rendering.

Prints wall times and, as the peer measured in the same run, GDAL's own cost of writing the same raster
(gdal.Translate of the rendered image to a tiled DEFLATE GeoTIFF) for the render.
Run: .venv/bin/python bench/bench_simulate.py [--render-size N] [--workers W]
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time

import numpy as np


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--render-size", type=int, default=10240, help="GF4 render size (default the full 10240)")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    from osgeo import gdal
    from gdal_gf4cal.rpc_fit import fit_rpc_from_model
    from gdal_gf4cal.simulate import SENSORS, make_scene, write_scene
    from gdal_gf4cal.simulate.render import render_image
    from gdal_gf4cal.stats import internal_accuracy
    gdal.UseExceptions()
    tmp = tempfile.mkdtemp(prefix="bench_sim_")
    try:
        print("== gf4cal simulate --sensor gf4 (full size, no rendering)")
        t = time.perf_counter()
        res = write_scene("gf4", os.path.join(tmp, "gf4"), seed=0)
        print(f"write_scene gf4 10240x10240: {time.perf_counter() - t:.2f} s")
        g = res.images[""].gcps
        rpc = res.images[""].rpc
        ps, pl = rpc.project(g.lon.to_numpy(), g.lat.to_numpy(), g.h.to_numpy())
        ds, dl = g["sample"].to_numpy() - ps, g["line"].to_numpy() - pl
        ia = internal_accuracy(g["sample"].to_numpy(), g["line"].to_numpy(), ps, pl)
        print(f"GF4 GCP residuals vs RPC: RMS sample {np.sqrt(np.mean(ds**2)):.2f} line {np.sqrt(np.mean(dl**2)):.2f} px;"
              f" after rotation+translation ({ia['theta_rad']:.2e} rad): sample {ia['sample']['rms']:.2f} "
              f"line {ia['line']['rms']:.2f} px (paper 1.85 / 1.54)")
        print("== RPC fit on the check grid, full size (target max <= 0.01 px, RMS <= 0.002 px)")
        for sensor in SENSORS:
            sc = make_scene(sensor, seed=0)
            for im in sc.images:
                t = time.perf_counter()
                _, rep = fit_rpc_from_model(im.current)
                print(f"{sensor:4s} {im.name or '-':6s} {im.size[0]:6d}x{im.size[1]:<6d} max {rep.check.max_px:.2e} px "
                      f"RMS {rep.check.rms_px:.2e} px  ({time.perf_counter() - t:.2f} s)")
        n = args.render_size
        print(f"== rendering GF4 {n}x{n} through the true model, tiled 512, {args.workers} threads")
        sc = make_scene("gf4", seed=0, size=(n, n))
        im = sc.images[0]
        out = os.path.join(tmp, "render.tif")
        t = time.perf_counter()
        render_image(im.true, sc.dem, out, seed=0, gsd_m=im.gsd_m, workers=args.workers)
        t_render = time.perf_counter() - t
        # Peer: GDAL copying the result into a tiled DEFLATE GeoTIFF (the floor of I/O + compression).
        t = time.perf_counter()
        gdal.Translate(os.path.join(tmp, "copy.tif"), out, creationOptions=["TILED=YES", "COMPRESS=DEFLATE"])
        t_gdal = time.perf_counter() - t
        mpix = n * n / 1e6
        import resource
        rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        print(f"peak RSS of the whole benchmark process: {rss_mb:.0f} MB (a 10240^2 Byte image alone is 105 MB)")
        print(f"render: {t_render:.1f} s ({mpix / t_render:.2f} Mpx/s); gdal_translate of the result: {t_gdal:.1f} s; "
              f"ratio render/gdal = {t_render / t_gdal:.1f}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
