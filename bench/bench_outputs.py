#!/usr/bin/env python3
"""Benchmark of a refine run's outputs with very many GCPs (issue 11): ``gf4cal refine`` with ``--report
--residuals --plot`` on N simulated GCPs (default 1,000,000) of the real WorldView-3 RPC (tests/data/compensation),
timed end to end in a child process, with the child's peak RSS. Goal: 1e6 GCPs in <= 40 s and <= 1.5 GB here.

Usage: python bench/bench_outputs.py [--n N]
"""
from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np
import pandas as pd

from gdal_gf4cal import RPCModel

RPB = os.path.join(os.path.dirname(__file__), "..", "tests", "data", "compensation", "md_dg.RPB")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    args = ap.parse_args()
    rpc = RPCModel.from_file(RPB)
    rng = np.random.default_rng(0)
    n = args.n
    s = rng.uniform(0, 2 * float(rpc.samp_off), n)
    l = rng.uniform(0, 2 * float(rpc.line_off), n)
    h = rng.uniform(float(rpc.height_off) - 100, float(rpc.height_off) + 100, n)
    lon, lat = rpc.localize(s + 3.0, l - 2.0, h)            # a 3/-2 px bias to correct
    with tempfile.TemporaryDirectory() as d:
        gcps = os.path.join(d, "gcps.csv")
        pd.DataFrame({"id": np.arange(n).astype(str), "lon": lon, "lat": lat, "h": h,
                      "sample": s + rng.normal(0, 0.3, n), "line": l + rng.normal(0, 0.3, n)}).to_csv(gcps,
                                                                                                      index=False)
        cmd = [sys.executable, "-m", "gdal_gf4cal.cli", "refine", RPB, "--gcps", gcps, "--model", "translation",
               "--out", os.path.join(d, "out.RPB"), "--report", os.path.join(d, "report.json"),
               "--residuals", os.path.join(d, "res.gpkg"), "--plot", os.path.join(d, "res.png")]
        t = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t
        usage = resource.getrusage(resource.RUSAGE_CHILDREN)
        peak_mb, cpu = usage.ru_maxrss / 1024, usage.ru_utime + usage.ru_stime
        status = "ok" if proc.returncode == 0 else f"exit {proc.returncode}: {proc.stderr.strip()[-300:]}"
        load = os.getloadavg()[0]
        # CPU time (user + sys of the child) is what the run costs; wall time also counts the other processes of
        # a shared machine (load average printed).
        print(f"refine with report, residual GeoPackage and plot, {n:,} GCPs: {wall:.1f} s wall, {cpu:.1f} s CPU, "
              f"peak RSS {peak_mb:.0f} MB ({status}; load average {load:.1f} on {os.cpu_count()} cores); "
              "goal <= 40 s and <= 1500 MB")


if __name__ == "__main__":
    main()
