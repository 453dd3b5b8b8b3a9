#!/usr/bin/env python3
"""``fit_rpc`` on 1e6 correspondences against one dense ``numpy.linalg.lstsq`` of the same size (issue 23).

The correspondences: uniform random ground points over a 10240^2 vendor-like RPC's cube (bench_fit's model)
projected through it, plus a radial image distortion (3e-4 of the squared normalised radius, ~3 px at the corners)
that no RPC represents exactly, so the fit iterates as on a real sensor. The floor is one ``lstsq`` of the
(n, 39) design of the fit's own first step (the RPC's 20 + 19 monomial columns), timed before and after the
fit in the same run; the ratio uses the faster of the two. Goal: <= 3x.

Usage: python bench/bench_fit_rpc_large.py [--n N] [--repeat R]
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

from gdal_gf4cal.rpc import monomials
from gdal_gf4cal.rpc_fit import fit_rpc
from bench_fit import _model_rpc


def correspondences(n: int, seed: int = 1):
    rng = np.random.default_rng(seed)
    model = _model_rpc()
    lon = rng.uniform(90.0 - 2.6, 90.0 + 2.6, n)
    lat = rng.uniform(31.0 - 2.2, 31.0 + 2.2, n)
    h = rng.uniform(3000.0, 6000.0, n)
    s, l = model.project(lon, lat, h)
    u, v = (s - 5120.0) / 5120.0, (l - 5120.0) / 5120.0
    k = 1.0 + 3e-4 * (u * u + v * v)
    return lon, lat, h, 5120.0 + (s - 5120.0) * k, 5120.0 + (l - 5120.0) * k


def lstsq_floor(lon, lat, h, sample):
    """One dense lstsq of the fit's (n, 39) design (ground normalised to [-1, 1], the sample as right side)."""
    def norm(x):
        return (x - 0.5 * (x.min() + x.max())) / (0.5 * (x.max() - x.min()))
    m = monomials(norm(lon), norm(lat), norm(h))
    r = norm(sample)
    a = np.hstack([m.T, -(m[1:] * r).T])
    t = time.perf_counter()
    np.linalg.lstsq(a, r, rcond=None)
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=1)
    a = ap.parse_args()
    pts = correspondences(a.n)
    print(f"fit_rpc on {a.n} correspondences vs one dense lstsq ({a.n} x 39), load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (a shared machine: read the ratio, not the times)")
    for _ in range(a.repeat):
        t_l1 = lstsq_floor(*pts[:4])
        t = time.perf_counter()
        _, rep = fit_rpc(*pts)
        t_fit = time.perf_counter() - t
        t_l2 = lstsq_floor(*pts[:4])
        print(f"  lstsq {t_l1:7.3f} s / {t_l2:7.3f} s   fit_rpc {t_fit:7.3f} s   ratio {t_fit / min(t_l1, t_l2):5.2f}x "
              f"(goal <= 3)   solves {rep.iterations}, lambda {rep.regularization}, fit rms {rep.fit.rms_px:.2e} px "
              f"max {rep.fit.max_px:.2e} px")


if __name__ == "__main__":
    main()
