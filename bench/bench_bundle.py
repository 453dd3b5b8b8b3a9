#!/usr/bin/env python3
"""Benchmark of the bundle adjustment of separate views (METHODS §11, issue 22): ``adjust_views`` on simulated
multi-date views (``gdal_gf4cal.simulate.views``: 10 views, affine per view, 0.2 px tie noise; a tie is seen by
every view whose image holds it, ~8 of 10), robust weights on.

Prints, per tie count, the wall and CPU time of ``adjust_views`` (input checks, intersection start, Gauss-Newton with
the points eliminated by Schur complement, robust reweighting, report), the ratio to the target (issue 22: 10 views
x 100,000 ties < 10 s; the machine's 1-minute load average during the run beside it), the side of the reduced
system (it must not grow with the ties: 6 per view) and the tie
reprojection after. The simulation is not timed.

``--threads 1 2`` runs every tie count at each thread setting (:func:`gdal_gf4cal.threads.limit`; the numbers are the
same), ``--repeat N`` interleaves N rounds of all settings (compare within one run: the machine is shared).

Usage: python bench/bench_bundle.py [--views 10] [--ties 10000 100000] [--no-robust] [--threads 1 2] [--repeat 1]
"""
from __future__ import annotations

import argparse
import os
import time

from gdal_gf4cal.bundle import adjust_views
from gdal_gf4cal.simulate.views import simulate_views
from gdal_gf4cal.threads import limit

TARGET_S = 10.0


def run(sim, n_ties: int, robust: bool, threads=None) -> dict:
    load = os.getloadavg()[0]
    with limit(threads):
        wall, cpu = time.perf_counter(), time.process_time()
        est = adjust_views(sim.observations, sim.models, robust=robust)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    return {"ties": n_ties, "threads": threads or "-", "rays": len(sim.observations), "wall_s": wall, "cpu_s": cpu,
            "load": 0.5 * (load + os.getloadavg()[0]),
            "reduced": est.reduced_size, "steps": est.iterations, "after_px": est.reprojection["after"]["all"],
            "converged": est.converged}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=10)
    ap.add_argument("--ties", type=int, nargs="+", default=[10000, 100000])
    ap.add_argument("--no-robust", action="store_true")
    ap.add_argument("--threads", type=int, nargs="+", default=[None])
    ap.add_argument("--repeat", type=int, default=1)
    a = ap.parse_args(argv)
    sims = {n: simulate_views("multi-date", a.views, n_ties=n, noise_px=0.2, seed=1) for n in a.ties}
    rows = [run(sims[n], n, not a.no_robust, t) for _ in range(a.repeat) for n in a.ties for t in a.threads]
    print(f"bundle adjustment, {a.views} views, robust={'off' if a.no_robust else 'on'} "
          f"(target: 100,000 ties < {TARGET_S:g} s)")
    print(f"{'ties':>8} {'threads':>7} {'rays':>8} {'wall s':>8} {'cpu s':>8} {'ratio':>6} {'reduced':>8} "
          f"{'steps':>6} {'after px':>9} {'load':>5}")
    for r in rows:
        print(f"{r['ties']:>8} {r['threads']:>7} {r['rays']:>8} {r['wall_s']:>8.2f} {r['cpu_s']:>8.2f} "
              f"{r['wall_s'] / TARGET_S:>6.2f} {r['reduced']:>8} {r['steps']:>6} {r['after_px']:>9.3f} "
              f"{r['load']:>5.1f}"
              + ("" if r["converged"] else "  (not converged)"))
    sizes = {r["reduced"] for r in rows}
    print("reduced system " + ("constant: " if len(sizes) == 1 else "GROWS: ") + ", ".join(map(str, sorted(sizes))))


if __name__ == "__main__":
    main()
