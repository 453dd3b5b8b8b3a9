#!/usr/bin/env python3
"""Benchmark of the block calibration (METHODS §8): one Jilin-1 group, 4 CCDs x 5 bands (pan + 4 MS, blue the
reference band), 20,000 GCP observations and N tie points, solved by ``gdal_gf4cal.block.adjust_block``
(simultaneous sparse Gauss-Newton, robust weights on).

The RPCs are those of a simulated group (``write_scene('jl1', size=(1024, 512))``); the measurements are made with
a known block correction (exterior + cubic interior per image, the model itself) and noise (GCPs 0.2 px, ties
0.1 px), so the recovered correction is checked too. Prints, per tie-point count, the time, the size of each
stage's reduced system (it must not grow with the tie points: they are eliminated by Schur complement) and the
largest error of the recovered correction. Target (issue 12): 20,000 GCP observations + 20,000 tie points < 5 s.

Usage: python bench/bench_block.py [--ties 5000 10000 20000] [--repeat N]
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np
import pandas as pd

import gdal_gf4cal
from gdal_gf4cal.block import BlockCorrectedRPC, ImageCorrection, adjust_block, derive_layout
from gdal_gf4cal.dem import DEM
from gdal_gf4cal.rpc import RPCModel

BANDS = ("blue", "pan", "green", "red", "nir")


def name(k, b):
    return f"ccd{k}" if b == "pan" else f"ccd{k}_{b}"


def make_group(root):
    from gdal_gf4cal.simulate import write_scene
    d = os.path.join(root, "jl1_bench")
    if not os.path.exists(os.path.join(d, "truth.json")):
        write_scene("jl1", d, seed=1, size=(1024, 512), n_gcps=5, check_grid_n=5, reference_ortho=False)
    names = [name(k, b) for b in BANDS for k in range(1, 5)]
    models = {n: RPCModel.from_file(os.path.join(d, n, "scene.RPB")) for n in names}
    return d, models, DEM.from_file(os.path.join(d, "dem.tif"))


def truth_models(models, layout, rng):
    ext = np.array([3.0, -2.0, 0.5, -0.3, 0.2])
    out = {}
    for n, m in models.items():
        inter = rng.normal(0, [2, 1, 0.8, 1.2, 2, 1, 0.8, 0.4])
        if n == layout.reference_ccd:
            inter[[0, 4, 5]] = 0.0
        out[n] = BlockCorrectedRPC(m, ImageCorrection(layout.images[n], layout.time_scale, ext, inter))
    return out


def observations(models, truth, layout, dem, n_gcp_obs, n_ties, rng):
    rows = []
    per = n_gcp_obs // len(models)
    for n, m in models.items():
        W, H = layout.images[n].size
        s, l = rng.uniform(0, W, per), rng.uniform(0, H, per)
        lon, lat, h = m.localize_dem(s, l, dem)
        ms, ml = truth[n].project(lon, lat, h)
        rows.append(pd.DataFrame({"point_id": [f"G{n}_{i}" for i in range(per)], "image_id": n, "kind": "gcp",
                                  "sample": ms + rng.normal(0, 0.2, per), "line": ml + rng.normal(0, 0.2, per),
                                  "sigma": 0.2, "role": "control", "lon": lon, "lat": lat, "h": h}))
    pairs = [(name(k, b), name(k + 1, b)) for b in BANDS for k in range(1, 4)]
    pairs += [(name(k, "blue"), name(k, b)) for k in range(1, 5) for b in BANDS[1:]]
    per = n_ties // len(pairs)
    for j, (a, b) in enumerate(pairs):
        W, H = layout.images[a].size
        same_ccd = a.split("_")[0] == b.split("_")[0]
        m = 3 * per
        s = rng.uniform(0, W, m) if same_ccd else rng.uniform(0.85 * W, W, m)
        l = rng.uniform(0, H, m)
        lon, lat, h = truth[a].localize_dem(s, l, dem)
        sb, lb = truth[b].project(lon, lat, h)
        Wb, Hb = layout.images[b].size
        ok = np.flatnonzero(np.isfinite(sb) & (sb > 0) & (sb < Wb) & (lb > 0) & (lb < Hb))[:per]
        pid = [f"T{j}_{i}" for i in range(ok.size)]
        for im, ss, ll in ((a, s[ok], l[ok]), (b, sb[ok], lb[ok])):
            rows.append(pd.DataFrame({"point_id": pid, "image_id": im, "kind": "tie",
                                      "sample": ss + rng.normal(0, 0.1, ok.size),
                                      "line": ll + rng.normal(0, 0.1, ok.size), "sigma": 0.1, "role": "control",
                                      "lon": np.nan, "lat": np.nan, "h": np.nan}))
    return pd.concat(rows, ignore_index=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ties", type=int, nargs="+", default=[5000, 10000, 20000])
    ap.add_argument("--gcp-obs", type=int, default=20000)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--workdir", default=os.path.join(tempfile.gettempdir(), "gf4cal_bench_block"))
    args = ap.parse_args()
    print(f"gdal_gf4cal from {os.path.dirname(gdal_gf4cal.__file__)}")
    d, models, dem = make_group(args.workdir)
    order = [name(k, "blue") for k in range(1, 5)]
    bands_of = {name(k, b): name(k, "blue") for k in range(1, 5) for b in BANDS[1:]}
    layout = derive_layout(models, order, bands_of=bands_of)
    rng = np.random.default_rng(0)
    truth = truth_models(models, layout, rng)
    print(f"{'ties':>7} {'obs rows':>9} {'wall s':>7} {'CPU s':>7} {'reduced systems':>16} {'iterations':>10} "
          f"{'max err px':>10}")
    for n in args.ties:
        obs = observations(models, truth, layout, dem, args.gcp_obs, n, rng)
        n_ties = obs.loc[obs["kind"] == "tie", "point_id"].nunique()
        best, cpu = np.inf, np.inf
        for _ in range(args.repeat):
            t0, c0 = time.perf_counter(), time.process_time()
            est = adjust_block(obs, models, dem, layout=layout)
            best, cpu = min(best, time.perf_counter() - t0), min(cpu, time.process_time() - c0)
        err = 0.0
        for k in models:
            W, H = layout.images[k].size
            S, L = (a.ravel() for a in np.meshgrid(np.linspace(0, W, 9), np.linspace(0, H, 5)))
            lon, lat, h = truth[k].localize_dem(S, L, dem)
            ps, pl = BlockCorrectedRPC(models[k], est.correction(k)).project(lon, lat, h)
            err = max(err, float(np.nanmax(np.hypot(ps - S, pl - L))))
        sizes = "+".join(str(s["reduced_system_size"]) for s in est.stages)
        its = "+".join(str(s["iterations"]) for s in est.stages)
        print(f"{n_ties:>7} {len(obs):>9} {best:>7.2f} {cpu:>7.2f} {sizes:>16} {its:>10} {err:>10.3f}")
    print("target: 20,000 GCP observations + 20,000 tie points < 5 s; reduced systems the same for every tie count")
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs (wall time grows with the load; CPU s "
          "counts this process's threads)")


if __name__ == "__main__":
    main()
