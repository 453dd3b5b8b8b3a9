"""Benchmark of raw-to-raw pan-MS matching (issues 12, 13): matches/s, cells/s and peak memory of
``pan_ms_cells`` on a rendered GF7 crop, extrapolated to the full 7680^2 MS image, against the same matcher run one
window at a time (``tile_windows=1``: a per-window loop of read + resample + correlate, as a straightforward
implementation would do), same run, same windows.

Scene (built once in --workdir, reused): ``write_gf7_scene(size=(N, N))`` (pan N^2, MS (N/4)^2), 10 % cloud.
Each method runs in its own child process (``ru_maxrss`` is its own peak memory); the time is the best of
``--repeat`` runs. Accuracy: RMS of the usable cells' nabla against the simulator's true misregistration.

Usage: python bench/bench_rawmatch.py [--size 4096] [--workdir DIR] [--workers 2] [--repeat 2]
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

FULL_MS = 7680


def build(workdir, size):
    from gdal_gf4cal.simulate.gf7 import write_gf7_scene
    out = os.path.join(workdir, f"gf7_{size}")
    if not os.path.exists(os.path.join(out, "ms", "scene.tif")):
        t = time.time()
        write_gf7_scene(out, seed=3, size=(size, size), clouds=0.1, n_gcps=10, workers=2)
        print(f"scene built in {time.time() - t:.0f} s: {out}", flush=True)
    return out


def run(args, method):
    from gdal_gf4cal.matching import pan_ms_cells
    from gdal_gf4cal.simulate.gf7 import make_gf7_scene, true_misregistration
    out = build(args.workdir, args.size)
    kw = dict(cell_px=64, window_px=32, spacing_px=16, workers=args.workers)
    if method == "loop":
        kw.update(tile_windows=1, workers=1)
    dt = np.inf
    for _ in range(max(args.repeat, 1)):
        t = time.perf_counter()
        cells = pan_ms_cells(os.path.join(out, "pan", "scene.tif"), os.path.join(out, "ms", "scene.tif"),
                             os.path.join(out, "dem.tif"), **kw)
        dt = min(dt, time.perf_counter() - t)
    scene = make_gf7_scene(seed=3, size=(args.size, args.size), clouds=0.1)
    u = cells.usable.to_numpy()
    ts, tl = true_misregistration(scene, cells["sample"][u].to_numpy(), cells["line"][u].to_numpy())
    es, el = cells.d_sample[u] - ts, cells.d_line[u] - tl
    w = cells.attrs["windows"]
    print(json.dumps(dict(method=method, seconds=dt, windows=w["total"], accepted=w["accepted"], cells=len(cells),
                          usable=int(u.sum()), rms_sample=float(np.sqrt(np.mean(es ** 2))),
                          rms_line=float(np.sqrt(np.mean(el ** 2))),
                          peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=4096)
    ap.add_argument("--workdir", default="/tmp/gf4cal_bench_rawmatch")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--child", choices=("ours", "loop"))
    args = ap.parse_args()
    if args.child:
        return run(args, args.child)
    os.makedirs(args.workdir, exist_ok=True)
    build(args.workdir, args.size)
    res = {}
    for method in ("ours", "loop"):
        cmd = [sys.executable, __file__, "--child", method, "--size", str(args.size), "--workdir", args.workdir,
               "--workers", str(args.workers), "--repeat", str(args.repeat if method == "ours" else 1)]
        line = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.strip().splitlines()[-1]
        res[method] = json.loads(line)
        print(line, flush=True)
    o, p = res["ours"], res["loop"]
    ms = args.size // 4
    full = o["seconds"] * (FULL_MS / ms) ** 2
    print(f"pan_ms_cells on MS {ms}^2: {o['windows'] / o['seconds']:.0f} windows/s, {o['cells'] / o['seconds']:.0f} "
          f"cells/s ({args.workers} threads), {o['seconds']:.2f} s; per-window loop {p['seconds']:.2f} s: "
          f"{p['seconds'] / o['seconds']:.1f}x; extrapolated full MS {FULL_MS}^2: {full:.0f} s; cells RMS vs truth "
          f"{o['rms_sample']:.3f} / {o['rms_line']:.3f} px; peak memory {o['peak_mb']:.0f} MB")


if __name__ == "__main__":
    main()
