"""GF4CAL_NUM_THREADS (issue 23): localise + project of 2e6 points with 1 thread and with 2, ratios in one run.

The real Pleiades Ventoux RPC; points uniform over the image at heights over the RPC's range: ``localize`` at those
heights, then ``project`` of the result (the round trip), and ``localize_dem`` on the real SRTM tile (EGM96). The
same blocks run in both settings (bit-identical results, checked here too); only the threads differ. The goal of
issue 23 is >= 1.6x on 2 cores: on a shared machine measure when it is idle (the load is printed).

Run: .venv/bin/python bench/bench_threads.py [--points N] [--repeat R] [--threads 2]
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from gdal_gf4cal import DEM, RPCModel, threads

from _timing import timed

DATA = Path(__file__).resolve().parent.parent / "tests" / "data"


def _run(k, fn, repeat):
    """Median wall time of ``fn`` under ``k`` threads, the CPU time it used (all threads) and its result."""
    with threads.limit(k):
        cpu = time.process_time()
        wall, out = timed(fn, repeat)
        cpu = (time.process_time() - cpu) / repeat
    return wall, cpu, out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    n, k = args.points, args.threads
    rpc = RPCModel.from_file(DATA / "rpc" / "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML")
    dem = DEM.from_file(DATA / "dem" / "N44E005.hgt", geoid="egm96", nodata="nan")
    w, h = rpc.image_size
    rng = np.random.default_rng(0)
    s, l = rng.uniform(0, w, n), rng.uniform(0, h, n)
    hh = rng.uniform(*rpc.height_range, n)

    def round_trip():
        lon, lat = rpc.localize(s, l, hh)
        return (lon, lat) + tuple(rpc.project(lon, lat, hh))

    cases = [("localize + project", round_trip),
             ("localize_dem (SRTM)", lambda: rpc.localize_dem(s[: n // 4], l[: n // 4], dem))]
    print(f"{n:,} points ({n // 4:,} for localize_dem), blocks of {threads.BLOCK:,}; load average "
          f"{os.getloadavg()[0]:.1f} on {threads.machine_cores()} cores")
    for name, fn in cases:
        fn()                                             # warm caches (inverse fit, DEM in memory)
        w1, c1, r1 = _run(1, fn, args.repeat)
        wk, ck, rk = _run(k, fn, args.repeat)
        same = all(np.array_equal(a, b, equal_nan=True) for a, b in zip(r1, rk))
        print(f"{name:22s} 1 thread {w1:6.2f} s (cpu {c1:5.2f} s)   {k} threads {wk:6.2f} s (cpu {ck:5.2f} s)   "
              f"ratio {w1 / wk:4.2f}x   bit-identical: {same}")
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
