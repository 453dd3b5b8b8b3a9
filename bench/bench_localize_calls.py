#!/usr/bin/env python3
"""``localize_dem``: the fixed cost of a small call and the generic path on a geoid DEM, this tree against another
one (default: ``main``), in one run (issue 23).

Two child processes, one per tree (``git archive`` of ``--old`` into a temporary folder), each import their own
``gdal_gf4cal`` and time on the real SRTM tile of Mont Ventoux (tests/data/dem), with and without EGM96:

``rpc N``       the Pleiades RPC's fast path on N image points (1, 4, 16, 256: a small call's fixed cost);
``generic``     the generic path (any non-RPC model) of a simulated ZY-3 push-broom over Ventoux (``make_scene``),
                20,000 points; and the RPC with ``fast_path=False`` (its fallback points take this path).

The parent interleaves the trees (old, new, old, new, ...) so that the load of the shared machine falls on both
alike, and prints per case the least CPU time per call of each tree (``time.process_time`` over a loop of calls),
their ratio, the load average, and whether the results have the same bits (else the largest height difference,
which must stay within the tolerance where the Newton sampler replaces PROJ).

Usage: python bench/bench_localize_calls.py [--repeat N] [--old COMMIT]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
DATA = os.path.join(ROOT, "tests", "data")
sys.path.insert(0, HERE)
from _timing import extract_tree, interleaved, start_child  # noqa: E402

CASES = [("rpc", 1, "egm96"), ("rpc", 4, "egm96"), ("rpc", 16, "egm96"), ("rpc", 256, "egm96"),
         ("rpc", 4, "none"), ("rpc", 256, "none"), ("generic", 20000, "egm96"), ("rpc-generic", 20000, "egm96")]


def _setup(kind: str, n: int, geoid: str):
    """``f() -> (lon, lat, h)`` of one case, and the number of calls per timing."""
    import numpy as np
    from gdal_gf4cal import DEM, RPCModel
    from gdal_gf4cal.localization import localize_dem
    dem = DEM.from_file(os.path.join(DATA, "dem", "N44E005.hgt"), geoid=None if geoid == "none" else geoid,
                        nodata="nan")
    rng = np.random.default_rng(n)
    if kind == "generic":
        from gdal_gf4cal.simulate.sensors import make_scene
        model = make_scene("zy3", seed=0, size=(2000, 2000), dem=dem, center=(5.25, 44.2)).images[0].true
        s, l = rng.uniform(0, 2000, n), rng.uniform(0, 2000, n)
        return (lambda: localize_dem(model, s, l, dem)), 1
    rpc = RPCModel.from_file(os.path.join(DATA, "rpc", "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML"))
    w, h = rpc.image_size
    s, l = rng.uniform(0, w, n), rng.uniform(0, h, n)
    if kind == "rpc-generic":
        return (lambda: localize_dem(rpc, s, l, dem, fast_path=False)), 1
    return (lambda: rpc.localize_dem(s, l, dem)), max(1, 2000 // (n + 10))


def child() -> None:
    """One tree: reads ``kind n geoid`` lines, answers ``{"t": CPU seconds per call, "h": heights}``."""
    import numpy as np
    cases = {}
    print(json.dumps({"ready": True}), flush=True)
    for line in sys.stdin:
        kind, n, geoid = line.split()
        key = (kind, int(n), geoid)
        if key not in cases:
            cases[key] = _setup(*key)
            cases[key][0]()                        # warm: the DEM read, the geoid lattice, the tables
        f, k = cases[key]
        t = time.process_time()
        for _ in range(k):
            out = f()
        t = (time.process_time() - t) / k
        print(json.dumps({"t": t, "h": np.asarray(out[2]).tolist(), "lon": np.asarray(out[0]).tolist()}),
              flush=True)


def main() -> None:
    import numpy as np
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--old", default="main")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child()
    with tempfile.TemporaryDirectory() as tmp:
        procs = {name: start_child(__file__, tree, tree, GF4CAL_NUM_THREADS="1")
                 for name, tree in (("old", extract_tree(ROOT, args.old, tmp)), ("new", ROOT))}
        best, last = {}, {}
        for key, r in interleaved(procs, CASES, args.repeat):
            best[key] = min(best.get(key, np.inf), r["t"])
            last[key] = r
    print(f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f}; old = {args.old}, CPU ms per call "
          f"(least of {args.repeat})")
    for case in CASES:
        o, n = best[("old", case)], best[("new", case)]
        ho, hn = (np.asarray(last[(k, case)]["h"], float) for k in ("old", "new"))
        lo_, ln = (np.asarray(last[(k, case)]["lon"], float) for k in ("old", "new"))
        same = np.array_equal(ho, hn, equal_nan=True) and np.array_equal(lo_, ln, equal_nan=True)
        diff = "same bits" if same else f"max |dh| {np.nanmax(np.abs(ho - hn)):.2e} m"
        print(f"{case[0]:12s} n={case[1]:6d} {case[2]:6s} old {o * 1e3:8.3f}  new {n * 1e3:8.3f}  "
              f"new/old {n / o:5.2f}  {diff}")


if __name__ == "__main__":
    main()
