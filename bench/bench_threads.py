"""GF4CAL_NUM_THREADS (issue 23): 1 thread against 2, ratios in one run, interleaved repeats.

- localize + project: 2e6 points on the real Pleiades Ventoux RPC, uniform over the image at heights over the RPC's
  range: ``localize`` at those heights, then ``project`` of the result (the round trip); goal >= 1.6x;
- localize_dem: a quarter of them on the real SRTM tile (EGM96);
- collect-gcps: ``collect_gcps`` on a rendered 1024 x 1024 scene (tests/matchscene.py, 10 m GSD: the real Pleiades
  texture as reference ortho, the real SRTM crop, a raw image rendered through a true RPC, a biased RPC ~63 px off),
  window 64 px every 32 px (~900 windows); goal >= 1.5x;
- register-pan-ms: the whole workflow (``register_pan_ms``: matching of every band, model, correction.tif,
  ms_on_pan.tif, ms_approx.RPB, report) on a simulated GF7 crop (pan 1024 x 1024, MS 256 x 256, across the first
  MS sub-CCD edge; rendered once into --workdir, ~1 min; --panms-size 4096: a 4096 x 4096 pan crop, where the
  matching is most of a run, not the fixed cost of three plots); goal >= 1.5x.

Each case runs under ``threads.limit(1)`` and ``threads.limit(k)`` alternately (--repeat times): the median wall
and CPU, then the ratio of the minima and the voluntary context switches per run (medians); results must be the
same bits in both (printed). With localize_dem, one more line: the share of a block's CPU spent in Python
dispatching NumPy calls (64 points, every stage of a chunk, times the chunks of a block, against a block) and the
2-thread bound it sets. With the round trip, three more lines: the same share for a round-trip block (a 16-point
round trip against a block's: what holds the GIL, the serial part) and the 2-thread bound it sets; the same round
trip in k processes (half the points each: no GIL shared), the bound the machine itself sets (cores, caches,
memory), against one thread in the same run; and on a pool of k processes that copies the caller's points in and the
results out through shared memory (what a process pool would give the API). With --bound, the same for
collect-gcps and register-pan-ms: k whole runs in k processes against one run on one thread. On a shared
machine the ratios are low: measure when it is idle (the load average is printed before and after each case).

Run: .venv/bin/python bench/bench_threads.py [--points N] [--repeat R (default: 7 point cases, 3 others)]
     [--threads 2] [--workdir DIR] [--cases round_trip,localize_dem,collect,panms] [--bound] [--panms-size PX]
"""
from __future__ import annotations

import argparse
import multiprocessing
import os
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from gdal_gf4cal import DEM, RPCModel, localization, threads

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "tests" / "data"
CASES = ("round_trip", "localize_dem", "collect", "panms")
#: Default runs of each thread count per case (--repeat): the point cases take a second each, seven give a
#: median and a minimum on a shared machine.
REPEAT = {"round_trip": 7, "localize_dem": 7}


def _compare(k, cases, repeat):
    """Every case under 1 thread and under ``k``, alternately ``repeat`` times: one line each (medians), then the
    minima's ratio (timeit's convention: the run least disturbed by the rest of a shared machine) and the
    voluntary context switches per run (a thread that finds the GIL held sleeps: what a second thread costs), the
    minor page faults and system CPU per run (fresh outputs and temporaries faulted in: kernel work the threads do not
    share well, and counts that survive a loaded machine)."""
    for name, fn, same in cases:
        fn(1)                                            # warm caches (inverse fit, DEM in memory, GDAL cache)
        load0 = os.getloadavg()[0]
        runs = {1: [], k: []}            # (wall, cpu, voluntary switches, minor faults, system cpu) of every run
        outs = {}
        for _ in range(repeat):
            for t in (1, k):
                with threads.limit(t):
                    r, c, w = resource.getrusage(resource.RUSAGE_SELF), time.process_time(), time.perf_counter()
                    outs[t] = fn(t)
                    wall, cpu, r1 = time.perf_counter() - w, time.process_time() - c, \
                        resource.getrusage(resource.RUSAGE_SELF)
                    runs[t].append((wall, cpu, r1.ru_nvcsw - r.ru_nvcsw, r1.ru_minflt - r.ru_minflt,
                                    r1.ru_stime - r.ru_stime))
        (w1, c1, s1, f1, y1), (wk, ck, sk, fk, yk) = ([statistics.median(x[i] for x in runs[t]) for i in range(5)]
                                                      for t in (1, k))
        print(f"{name:22s} 1 thread {w1:6.2f} s (cpu {c1:5.2f})   {k} threads {wk:6.2f} s (cpu {ck:5.2f})   "
              f"ratio {w1 / wk:4.2f}x   same bits: {same(outs[1], outs[k])}   load {load0:.1f} -> "
              f"{os.getloadavg()[0]:.1f}", flush=True)
        m1, mk = (min(x[0] for x in runs[t]) for t in (1, k))
        print(f"{'':22s} minima: 1 thread {m1:6.2f} s   {k} threads {mk:6.2f} s   ratio {m1 / mk:4.2f}x (median "
              f"{w1 / wk:4.2f}x, {repeat} runs each)   voluntary context switches per run: {s1:.0f} | {sk:.0f}   "
              f"cpu {k} threads / 1: {ck / c1:4.2f}", flush=True)
        print(f"{'':22s} minor page faults per run: {f1:.0f} | {fk:.0f}   system cpu: {y1:.3f} s | {yk:.3f} s",
              flush=True)


def _arrays_equal(a, b):
    return all(np.array_equal(x, y, equal_nan=True) for x, y in zip(a, b))


def _points(n):
    """The real Ventoux RPC and ``n`` image points uniform over its image, at heights over its range."""
    rpc = RPCModel.from_file(DATA / "rpc" / "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML")
    w, h = rpc.image_size
    rng = np.random.default_rng(0)
    return rpc, rng.uniform(0, w, n), rng.uniform(0, h, n), rng.uniform(*rpc.height_range, n)


def _round_trip(rpc, s, l, hh):
    lon, lat = rpc.localize(s, l, hh)
    return (lon, lat) + tuple(rpc.project(lon, lat, hh))


def _least_cpu(fn, repeat):
    """Least CPU seconds of ``repeat`` calls of ``fn``."""
    best = float("inf")
    for _ in range(repeat):
        t = time.process_time()
        fn()
        best = min(best, time.process_time() - t)
    return best


def serial_share():
    """The Python share of a round-trip block (what holds the GIL: the NumPy calls dispatched, without arithmetic):
    the least CPU of the round trip of 16 points (one chunk of every kernel) against one of a block, one thread."""
    b = threads.BLOCK
    rpc, s, l, hh = _points(b)
    with threads.limit(1):
        small = _least_cpu(lambda: _round_trip(rpc, s[:16], l[:16], hh[:16]), 100)
        block = _least_cpu(lambda: _round_trip(rpc, s, l, hh), 5)
    share = small / block
    print(f"round trip: {small * 1e6:.0f} us of NumPy calls per block against {block * 1e6:.0f} us CPU for {b:,} "
          f"points: {100 * share:.0f} % in Python (Amdahl: 2 threads <= {2 / (1 + share):.2f}x); load "
          f"{os.getloadavg()[0]:.1f}", flush=True)


def serial_share_dem():
    """The same for localize_dem on SRTM + EGM96: the least CPU of 64 points (every stage of a chunk on tiny
    arrays: the NumPy calls dispatched) times the chunks of a block, against one block of
    :data:`~gdal_gf4cal.threads.DEM_BLOCK` points, one thread."""
    b = threads.DEM_BLOCK
    rpc, s, l, _ = _points(b)
    dem = DEM.from_file(DATA / "dem" / "N44E005.hgt", geoid="egm96", nodata="nan")
    chunks = -(-b // localization._DEM_CHUNK)
    with threads.limit(1):
        small = _least_cpu(lambda: rpc.localize_dem(s[:64], l[:64], dem), 30)
        block = _least_cpu(lambda: rpc.localize_dem(s, l, dem), 5)
    share = small * chunks / block
    print(f"localize_dem: {small * 1e3:.2f} ms of NumPy calls per chunk x {chunks} chunks against {block * 1e3:.1f} ms "
          f"CPU for {b:,} points: {100 * share:.0f} % in Python (Amdahl: 2 threads <= {2 / (1 + share):.2f}x); load "
          f"{os.getloadavg()[0]:.1f}", flush=True)


def process_bound(label, work, k, repeat, *, split: bool):
    """``work`` in ``k`` forked processes (one thread each, started together at a barrier) against one thread in
    this process, alternately ``repeat`` times: no GIL shared, only the cores, their caches and memory: the bound of
    ``k`` threads on this machine, measured in the same run. ``work(i)``: the share ``i`` of the job when ``split``
    (``work(None)``: all of it), else one whole run (each process does one: ``k`` runs against one)."""
    ctx = multiprocessing.get_context("fork")

    def child(i, barrier, queue):
        with threads.limit(1):
            work(i)                                                  # warm (inverse fit, scratch buffers, outputs)
            barrier.wait()
            w = time.perf_counter()
            work(i)
            queue.put(time.perf_counter() - w)

    def in_processes():
        barrier, queue = ctx.Barrier(k), ctx.Queue()
        procs = [ctx.Process(target=child, args=(i, barrier, queue)) for i in range(k)]
        for p in procs:
            p.start()
        wall = max(queue.get() for _ in procs)
        for p in procs:
            p.join()
        return wall

    one, many = [], []
    runs = 1 if split else k                          # the work of the k processes, in runs of the one thread
    with threads.limit(1):
        work(None)
        for _ in range(repeat):
            w = time.perf_counter()
            work(None)
            one.append(time.perf_counter() - w)
            many.append(in_processes())
    print(f"{label} in {k} processes (no GIL shared): 1 thread {statistics.median(one):6.2f} s, {k} processes "
          f"{statistics.median(many):6.2f} s{'' if split else f' for {k} runs'}: ratio "
          f"{runs * statistics.median(one) / statistics.median(many):4.2f}x (minima {runs * min(one) / min(many):4.2f}x):"
          f" the machine's bound for {k} threads; load {os.getloadavg()[0]:.1f}", flush=True)


def round_trip_bound(n, k, repeat):
    """:func:`process_bound` of the round trip of ``n`` points, ``n / k`` per process."""
    rpc, s, l, hh = _points(n)
    parts = [slice(i * n // k, (i + 1) * n // k) for i in range(k)]

    def work(i):
        sl = slice(None) if i is None else parts[i]
        _round_trip(rpc, s[sl], l[sl], hh[sl])
    process_bound("round trip", work, k, repeat, split=True)


#: :func:`round_trip_pool`: the points and the RPC a forked worker inherits, (5, n) columns of shared memory (sample,
#: line, h in; sample, line out).
_POOL: dict = {}


def _pool_round_trip(a: int, b: int) -> None:
    """A worker of :func:`round_trip_pool`: the round trip of the points ``a:b`` of the shared columns, one thread."""
    rpc, cols = _POOL["rpc"], _POOL["cols"]
    with threads.limit(1):
        cols[3:5, a:b] = _round_trip(rpc, cols[0, a:b], cols[1, a:b], cols[2, a:b])[2:]


def round_trip_pool(n, k, repeat):
    """The round trip as a process pool would serve the API: ``k`` forked workers (kept between calls) share the
    points' memory; a call copies the caller's arrays in, waits for the ``k`` shares and copies the results out, against
    one thread in this process, alternately ``repeat`` times (session 17, a 2-core VM: medians 1.48-1.72x against the
    threads' 1.19-1.37x in the same busy runs, 1.65-1.73x quiet: a little more than threads, the copies in and out
    eating most of what the GIL costs them)."""
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import shared_memory
    rpc, s, l, hh = _points(n)
    shm = shared_memory.SharedMemory(create=True, size=5 * n * 8)
    try:
        _POOL.update(rpc=rpc, cols=np.ndarray((5, n), buffer=shm.buf))
        cols, bounds = _POOL["cols"], [i * n // k for i in range(k + 1)]
        with ProcessPoolExecutor(k, mp_context=multiprocessing.get_context("fork")) as pool:
            def pooled():
                cols[0], cols[1], cols[2] = s, l, hh
                for f in [pool.submit(_pool_round_trip, a, b) for a, b in zip(bounds, bounds[1:])]:
                    f.result()
                return cols[3].copy(), cols[4].copy()

            def alone():
                with threads.limit(1):
                    return _round_trip(rpc, s, l, hh)[2:]

            one, many = [], []
            same = _arrays_equal(pooled(), alone())
            for _ in range(repeat):
                for fn, laps in ((alone, one), (pooled, many)):
                    w = time.perf_counter()
                    fn()
                    laps.append(time.perf_counter() - w)
    finally:
        _POOL.clear()
        shm.close()
        shm.unlink()
    print(f"round trip on a pool of {k} processes (points copied through shared memory): 1 thread "
          f"{statistics.median(one):6.2f} s, pool {statistics.median(many):6.2f} s: ratio "
          f"{statistics.median(one) / statistics.median(many):4.2f}x (minima {min(one) / min(many):4.2f}x), same bits: "
          f"{same}; load {os.getloadavg()[0]:.1f}", flush=True)


def point_cases(n):
    """localize + project of ``n`` points and localize_dem of ``n / 4`` on the real Ventoux RPC and SRTM."""
    rpc, s, l, hh = _points(n)
    dem = DEM.from_file(DATA / "dem" / "N44E005.hgt", geoid="egm96", nodata="nan")

    def round_trip(_):
        return _round_trip(rpc, s, l, hh)

    return {"round_trip": ("localize + project", round_trip, _arrays_equal),
            "localize_dem": ("localize_dem (SRTM)", lambda _: rpc.localize_dem(s[: n // 4], l[: n // 4], dem),
                             _arrays_equal)}


def collect_case(workdir: Path):
    """collect_gcps on the rendered 1024 x 1024 matching scene (built once in ``workdir``)."""
    sys.path.insert(0, str(ROOT / "tests"))
    from matchscene import affine_rpc, build_scene, error_affine, synthetic_rpc
    from gdal_gf4cal.matching import collect_gcps
    size, folder = (1024, 1024), workdir / "collect"
    error = error_affine(shift=(-50.3, 37.6), rotation_rad=0.002, scale=1.001, center=(512, 512))
    if not (folder / "raw.tif").exists():
        t = time.perf_counter()
        build_scene(folder, texture="pleiades", size=size, gsd_m=10.0, ref_px_m=9.0, error=error, seed=1)
        print(f"(collect scene rendered in {time.perf_counter() - t:.0f} s)")
    rpc = affine_rpc(synthetic_rpc(size, 10.0), error)
    dem = DEM.from_file(ROOT / "tests" / "data" / "matching" / "srtm_ventoux_crop.tif")

    def run(_, tag=None):
        g = collect_gcps(str(folder / "raw.tif"), rpc, str(folder / "reference.tif"), dem, spacing_px=32,
                         window_px=64)
        return g

    def same(a, b):
        cols = [c for c in a.columns if c not in ("geometry", "id", "role")]
        return len(a) == len(b) and all(np.array_equal(a[c].to_numpy(), b[c].to_numpy()) for c in cols)

    return {"collect": ("collect-gcps", run, same)}


def panms_case(workdir: Path, size: int = 1024):
    """register_pan_ms on a simulated GF7 crop, pan ``size`` x ``size`` (rendered once in ``workdir``)."""
    from osgeo import gdal
    from gdal_gf4cal.simulate.gf7 import write_gf7_scene
    from gdal_gf4cal.workflows.panms import register_pan_ms
    folder = workdir / f"gf7_{size}"
    if not (folder / "ms" / "misregistration_truth.tif").exists():
        t = time.perf_counter()
        write_gf7_scene(str(folder), seed=0, size=(size, size), crop_center_ms_px=2560, n_gcps=10)
        print(f"(GF7 crop rendered in {time.perf_counter() - t:.0f} s)")
    gdal.UseExceptions()                      # a script: process-wide GDAL state is ours

    def run(k, tag=None):
        """One run at ``k`` threads; ``tag``: another output folder, its stage times not kept (a process of
        :func:`process_bound`)."""
        out = folder / f"out_{k if tag is None else tag}"
        rep = register_pan_ms(str(folder / "pan" / "scene.tif"), str(folder / "ms" / "scene.tif"),
                              dem=str(folder / "dem.tif"), out=str(out), overwrite=True)
        if tag is None:
            STAGES.setdefault(k, []).append(rep["timings_s"])
        return [gdal.Open(str(out / f)).ReadAsArray() for f in ("correction.tif", "ms_on_pan.tif")]

    return {"panms": (f"register-pan-ms (GF7 {size})", run, _arrays_equal)}


#: register-pan-ms: the report's stage times (wall, s) of every run, per thread count.
STAGES: dict = {}


def _print_stages():
    """register-pan-ms per stage (the report's ``timings_s``), the median over the runs of each thread count (the
    first 1-thread run, the warm-up, left out)."""
    for k, laps in sorted(STAGES.items()):
        laps = laps[1:] if k == 1 and len(laps) > 1 else laps
        print(f"  register-pan-ms {k} thread(s) by stage: " + ", ".join(
            f"{name} {statistics.median(lap[name] for lap in laps):.2f} s" for name in laps[0]))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--repeat", type=int, default=None, help="runs of each thread count (default: 7 for the point "
                    "cases, 3 for the others)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--workdir", default="/tmp/gf4cal_bench_threads")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--panms-size", type=int, default=1024, help="pan size of the GF7 crop of register-pan-ms (px; "
                    "4096: 4 ms_on_pan tiles, ~7 s a run on one thread)")
    ap.add_argument("--bound", action="store_true", help="collect and register-pan-ms also in k processes, one run "
                    "each (the machine's bound for k threads; the round trip always has it)")
    args = ap.parse_args()
    wanted = [c.strip() for c in args.cases.split(",") if c.strip()]
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    found = {}
    if {"round_trip", "localize_dem"} & set(wanted):
        found.update(point_cases(args.points))
    if "collect" in wanted:
        found.update(collect_case(workdir))
    if "panms" in wanted:
        found.update(panms_case(workdir, args.panms_size))
    print(f"{args.points:,} points ({args.points // 4:,} for localize_dem), blocks of {threads.BLOCK:,} "
          f"({threads.DEM_BLOCK:,} for localize_dem); {threads.machine_cores()} cores; load average "
          f"{os.getloadavg()[0]:.1f}")
    for c in wanted:
        if c in found:
            _compare(args.threads, [found[c]], args.repeat or REPEAT.get(c, 3))
    if "localize_dem" in wanted:
        serial_share_dem()
    if "round_trip" in wanted:
        serial_share()
        round_trip_bound(args.points, args.threads, args.repeat or REPEAT["round_trip"])
        round_trip_pool(args.points, args.threads, args.repeat or REPEAT["round_trip"])
    for c in ("collect", "panms"):
        if c in wanted and args.bound:
            label, fn, _ = found[c]
            process_bound(label, lambda i, fn=fn: fn(1, tag=f"process_{i}"), args.threads, args.repeat or 3, split=False)
    _print_stages()


if __name__ == "__main__":
    main()
