#!/usr/bin/env python3
"""Compensation at 1e3 and 1e4 GCPs against the tree before the estimation core (issue 23), in one run.

The pre-core tree is ``git archive``d from the parent of the commit that introduced the estimation core (found in
``git log`` by its message, "estimation: one core", unless ``--old`` names a commit) into a temporary folder. Two
child processes, one per tree, each import its own ``gdal_gf4cal`` and time ``fit_compensation`` on the cases of
``bench_compensation.make_case`` (WorldView-3 RPC, affine truth, 0.5 px noise, 5 % blunders of 20-60 px); the
parent interleaves the calls (old, new, old, new, ...) so that the load of a shared machine falls on both alike,
and prints per case the minimum and median of each tree, their ratio, the ratio of the minimum CPU times (the
steadiest on a loaded machine; BLAS threads count in both) and whether both flagged the same GCPs.

Usage: python bench/bench_compensation_core.py [--repeat N] [--old COMMIT]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
from _timing import extract_tree, interleaved, start_child  # noqa: E402

CASES = [("affine", 1000), ("affine", 10000), ("poly2", 1000), ("poly2", 10000)]


def pre_core_commit() -> str:
    """The parent of the commit whose message introduced the estimation core."""
    out = subprocess.run(["git", "-C", ROOT, "log", "--format=%H %s", "--reverse", "--all"], capture_output=True,
                         text=True, check=True).stdout.splitlines()
    core = next(line.split()[0] for line in out if "estimation: one core" in line)
    return subprocess.run(["git", "-C", ROOT, "rev-parse", f"{core}^"], capture_output=True, text=True,
                          check=True).stdout.strip()


def child() -> None:
    """One tree: reads ``model n`` lines, answers ``{"t": seconds, "outliers": [...]}`` per fit."""
    from bench_compensation import make_case
    from gdal_gf4cal.compensation import fit_compensation
    cases = {}
    print(json.dumps({"ready": True}), flush=True)
    for line in sys.stdin:
        model, n = line.split()
        key = (model, int(n))
        if key not in cases:
            cases[key] = make_case(int(n))
            fit_compensation(cases[key][0], cases[key][1], model)           # warm-up (imports, caches)
        rpc, gcps, _ = cases[key]
        t, c = time.perf_counter(), time.process_time()
        res = fit_compensation(rpc, gcps, model)
        dt, dc = time.perf_counter() - t, time.process_time() - c
        print(json.dumps({"t": dt, "cpu": dc, "outliers": [int(i) for i in res.gcps.index[res.gcps["outlier"]]]}),
              flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--old", default=None, help="commit of the old tree (default: before the estimation core)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        child()
        return
    old = a.old or pre_core_commit()
    what = "the commit given" if a.old else "before the estimation core"
    print(f"old tree: {old[:10]} ({what}); new tree: {ROOT}; load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (a shared machine: read the ratios, not the times)")
    with tempfile.TemporaryDirectory() as tmp:
        procs = {name: start_child(__file__, tree, HERE) for name, tree in (("old", extract_tree(ROOT, old, tmp)),
                                                                             ("new", ROOT))}
        times = {(k, c): [] for k in procs for c in CASES}
        cpu = {(k, c): [] for k in procs for c in CASES}
        flagged = {}
        for key, ans in interleaved(procs, CASES, a.repeat):
            times[key].append(ans["t"])
            cpu[key].append(ans["cpu"])
            flagged[key] = ans["outliers"]
    print(f"{'model':>8} {'GCPs':>6} {'old min s':>10} {'new min s':>10} {'old med s':>10} {'new med s':>10} "
          f"{'new/old (min)':>14} {'(median)':>9} {'(min CPU)':>10}  same outliers")
    for case in CASES:
        to, tn = times[("old", case)], times[("new", case)]
        same = flagged[("old", case)] == flagged[("new", case)]
        print(f"{case[0]:>8} {case[1]:>6} {min(to):>10.4f} {min(tn):>10.4f} {statistics.median(to):>10.4f} "
              f"{statistics.median(tn):>10.4f} {min(tn) / min(to):>14.2f} "
              f"{statistics.median(tn) / statistics.median(to):>9.2f} "
              f"{min(cpu[('new', case)]) / max(min(cpu[('old', case)]), 1e-9):>10.2f}  {same} "
              f"({len(flagged[('new', case)])})")


if __name__ == "__main__":
    main()
