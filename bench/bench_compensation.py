#!/usr/bin/env python3
"""Benchmark of RPC bias compensation (METHODS §4): ``fit_compensation`` timings over GCP-set sizes and models.

Truth: the real WorldView-3 RPC of tests/data/compensation (``md_dg.RPB``) composed with a known affine image-space
error; GCPs spread over the image, 0.5 px noise, 5 % blunders of 20-60 px (robust estimation on). Prints the median
time per fit and the check that every blunder was flagged. The issue-10 refactor must stay within 10 % of the
previous engine: run this script in both trees in the same session, e.g.
``PYTHONPATH=/path/to/old/tree python bench/bench_compensation.py`` (the script imports whichever gdal_gf4cal comes
first on the path and prints its location).

Usage: python bench/bench_compensation.py [--repeat N]
"""
from __future__ import annotations

import argparse
import os

import numpy as np
import pandas as pd

import gdal_gf4cal
from gdal_gf4cal import RPCModel
from gdal_gf4cal.compensation import CompensatedRPC, CompensationResult, fit_compensation
from _timing import timed

RPB = os.path.join(os.path.dirname(__file__), "..", "tests", "data", "compensation", "md_dg.RPB")


def make_case(n, seed=3):
    rpc = RPCModel.from_file(RPB)
    frame = (float(rpc.samp_off), float(rpc.samp_scale), float(rpc.line_off), float(rpc.line_scale))
    truth = CompensatedRPC(rpc, CompensationResult.from_coefficients("affine", frame, [7.0, 3.0, -1.5],
                                                                     [-5.0, 1.0, 2.5]))
    rng = np.random.default_rng(seed)
    w, h = 2 * frame[0], 2 * frame[2]
    s, l = rng.uniform(0, w, n), rng.uniform(0, h, n)
    hh = rng.uniform(float(rpc.height_off) - 100, float(rpc.height_off) + 100, n)
    lon, lat = truth.localize(s, l, hh)
    ms, ml = s + rng.normal(0, 0.5, n), l + rng.normal(0, 0.5, n)
    bad = rng.random(n) < 0.05
    ang = rng.uniform(0, 2 * np.pi, n)
    mag = rng.uniform(20, 60, n)
    ms[bad] += mag[bad] * np.cos(ang[bad])
    ml[bad] += mag[bad] * np.sin(ang[bad])
    gcps = pd.DataFrame({"id": [f"g{i}" for i in range(n)], "lon": lon, "lat": lat, "h": hh, "sample": ms,
                         "line": ml, "role": "control"})
    return rpc, gcps, bad


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    print(f"gdal_gf4cal from {os.path.dirname(gdal_gf4cal.__file__)}")
    print(f"{'model':>12} {'GCPs':>7} {'median s':>10} {'blunders flagged':>18}")
    for model in ("translation", "affine", "poly2"):
        for n in (10, 100, 1000, 10000):
            rpc, gcps, bad = make_case(n)
            t, res = timed(lambda: fit_compensation(rpc, gcps, model), args.repeat)
            flagged = np.asarray(res.gcps["outlier"], bool)
            print(f"{model:>12} {n:>7} {t:>10.4f} {int((flagged & bad).sum()):>8} / {int(bad.sum()):<8}")


if __name__ == "__main__":
    main()
