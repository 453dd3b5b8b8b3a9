#!/usr/bin/env python3
"""Chunk sizes of the round trip (issue 23): is the 2-thread limit cache contention that smaller chunks would lift?

For each configuration ``LOCALIZE_CHUNK/PROJECT_CHUNK/BLOCK`` (gdal_gf4cal.rpc, gdal_gf4cal.threads), the round trip
of bench_threads (2e6 points on the real Pleiades Ventoux RPC: ``localize`` then ``project``) under 1 thread, 2
threads and 2 forked processes (half the points each: no GIL), the configurations interleaved in one process in a
new random order every repeat (the load of a shared machine falls on all alike; the bits are checked against the
first 1-thread run). Every localize chunk and project block records its wall interval and its thread CPU
(``time.thread_time``); per configuration and kind the report gives

- the median CPU per point of 1-thread chunks that ran uninterrupted (thread CPU >= 0.9 of their wall);
- the median CPU per point of chunks that ran beside the other thread / process (the CPU the other spent in the
  interval, added to the chunk's own, leaves >= 0.8 of the chunk's CPU overlapped on the two cores), as a multiple of
  the first: the inflation contention causes (a loaded machine hardly lets two threads of one process run together;
  these chunks are the ones that did, so the numbers survive load; their count is printed);
- the total CPU of the 2-thread and 2-process runs against the 1-thread run (paired medians), the wall ratios.

The working set is ~370 bytes a point in localize (41 rows and its inputs), ~230 in project (24 rows): a chunk fits
a 512 KB L2 (Zen 3) below ~1,400 and ~2,200 points.

Usage: python bench/bench_chunks.py [--points N] [--repeat R] [CONFIG ...]   (CONFIG: loc,proj,block)
"""
from __future__ import annotations

import argparse
import collections
import multiprocessing
import os
import random
import statistics as st
import sys
import threading
import time

from gdal_gf4cal import rpc as rpc_module, threads
from gdal_gf4cal.rpc import RPCModel

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_threads import _arrays_equal, _points, _round_trip  # noqa: E402

DEFAULT = ("2048,4096,32768", "4096,32768,32768", "8192,32768,32768", "16384,32768,32768", "16384,8192,32768",
           "32768,32768,32768")
RECORDS: list = []          # (kind, points, thread key, wall start, wall end, thread CPU)


def _recorded(kind, fn):
    def wrapper(arr, *args):
        w, t = time.perf_counter(), time.thread_time()
        r = fn(arr, *args)
        RECORDS.append((kind, arr.size, threading.get_ident() ^ os.getpid(), w, time.perf_counter(),
                        time.thread_time() - t))
        return r
    return wrapper


def _instrument():
    """Record every localize chunk and project block (module attributes the kernels look up at each call)."""
    loc = rpc_module._localize_chunk
    rpc_module._localize_chunk = lambda K, s, *a: _recorded("loc", lambda s_, *b: loc(K, s_, *b))(s, *a)
    RPCModel._project_chunks = staticmethod(_recorded("proj", RPCModel._project_chunks))


def _in_two_processes(pts):
    """The round trip in 2 forked processes (a warm run, then a timed one at a barrier): their records."""
    ctx, n = multiprocessing.get_context("fork"), pts[1].size
    barrier, queue = ctx.Barrier(2), ctx.Queue()

    def child(sl):
        with threads.limit(1):
            _round_trip(pts[0], *(a[sl] for a in pts[1:]))
            RECORDS.clear()
            barrier.wait()
            _round_trip(pts[0], *(a[sl] for a in pts[1:]))
            queue.put(list(RECORDS))
    procs = [ctx.Process(target=child, args=(sl,)) for sl in (slice(0, n // 2), slice(n // 2, n))]
    for p in procs:
        p.start()
    recs = queue.get() + queue.get()
    for p in procs:
        p.join()
    return recs


def measure(pts, configs, repeat):
    """{config: {mode: [(records, cpu, wall) per repeat]}} for modes 1t, 2t, 2p, configs interleaved."""
    with threads.limit(1):
        ref = _round_trip(*pts)
    out = {c: collections.defaultdict(list) for c in configs}
    for _ in range(repeat):
        for c in random.sample(configs, len(configs)):
            rpc_module.LOCALIZE_CHUNK, rpc_module.PROJECT_CHUNK, threads.BLOCK = c
            rpc_module.SERIAL_PROJECT_CHUNK = rpc_module.PROJECT_CHUNK    # the same chunk on 1 and 2 threads
            for mode in ("1t", "2t", "2p"):
                RECORDS.clear()
                cpu, wall = time.process_time(), time.perf_counter()
                if mode == "2p":
                    recs = _in_two_processes(pts)
                    cpu = sum(r[5] for r in recs)
                else:
                    with threads.limit(1 if mode == "1t" else 2):
                        res = _round_trip(*pts)
                    cpu, recs = time.process_time() - cpu, list(RECORDS)
                    assert _arrays_equal(ref, res), f"bits differ with {c}, {mode}"
                out[c][mode].append((recs, cpu, time.perf_counter() - wall))
    return out


def _per_point(recs, mode, full):
    """{(kind, 'alone' | 'beside'): [CPU per point]} of the full-size records of one run."""
    got = collections.defaultdict(list)
    for r in recs:
        kind, size, key, w0, w1, cpu = r
        if size != full[kind] or cpu <= 0:
            continue
        if mode == "1t":
            if cpu >= 0.9 * (w1 - w0):
                got[(kind, "alone")].append(cpu / size)
            continue
        other = sum(o[5] * max(0.0, min(w1, o[4]) - max(w0, o[3])) / (o[4] - o[3]) for o in recs
                    if o[2] != key and o[4] > o[3])
        if cpu + other - (w1 - w0) >= 0.8 * cpu:
            got[(kind, "beside")].append(cpu / size)
    return got


def report(out):
    print(f"load {os.getloadavg()[0]:.1f}; ns per point: 1T chunks alone | 2T, 2P chunks beside the other "
          "(x 1T) [count] || total CPU 2T/1T 2P/1T | wall 1T/2T", flush=True)
    for c, runs in out.items():
        full = {"loc": min(c[0], c[2]), "proj": c[2]}
        per = {m: collections.defaultdict(list) for m in runs}
        for m, rs in runs.items():
            for recs, _, _ in rs:
                for k, v in _per_point(recs, m, full).items():
                    per[m][k] += v
        row = f"{'/'.join(map(str, c)):18s}"
        for kind in ("loc", "proj"):
            alone = st.median(per["1t"][(kind, "alone")] or [float("nan")]) * 1e9
            row += f" {kind} {alone:6.1f}"
            for m in ("2t", "2p"):
                v = per[m][(kind, "beside")]
                row += f" {m} {st.median(v) * 1e9 / alone:5.2f}x[{len(v)}]" if v else f" {m}   -  [0]"
        ratio = {m: st.median(b[1] / a[1] for a, b in zip(runs["1t"], runs[m])) for m in ("2t", "2p")}
        wall = st.median(a[2] / b[2] for a, b in zip(runs["1t"], runs["2t"]))
        print(row + f" || {ratio['2t']:4.2f} {ratio['2p']:4.2f} | {wall:4.2f}", flush=True)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--points", type=int, default=2_000_000)
    p.add_argument("--repeat", type=int, default=6)
    p.add_argument("configs", nargs="*", default=list(DEFAULT))
    a = p.parse_args(argv)
    configs = [tuple(int(v) for v in c.split(",")) for c in a.configs]
    _instrument()
    report(measure(_points(a.points), configs, a.repeat))


if __name__ == "__main__":
    main()
