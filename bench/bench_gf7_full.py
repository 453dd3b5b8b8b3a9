"""Benchmark of pan-MS registration on a FULL simulated GF7 scene (issue 23; METHODS §9, §10).

1. Render (once, cached in --workdir, outside the repository) the full GF7 product of ``write_gf7_scene(seed=0)``:
   pan 30720² (1 band), MS 7680² (4 bands), RPCs, DEM, true misregistration field. The rendering time is printed
   (goal < 20 min on this 2-core machine); a second run reuses the scene.
2. ``gf4cal register-pan-ms PAN MS --dem DEM --out OUT`` with its default options, in a fresh child process: wall
   time and peak memory (``ru_maxrss`` of that child; goal <= 10 min and <= 3 GB on 2 cores), the stage times of
   its report and the correction's RMS against the true field (the same measurement as bench_panms.py's sizes).

``--ratio``: the same registration on one thread too (``GF4CAL_NUM_THREADS=1``, right after, on the same cached
scene): the 2-thread / 1-thread ratio of issue 23 on a whole product, where the matching is most of the run (the
bench_threads.py crops are mostly fixed costs). Another ~2.5 min.

``--strip ROWS``: instead, time the rendering of a full-width pan strip (30720 x ROWS) and the MS strip of the
same ground (7680 x ROWS/4): the quick profile of the renderer. The load average is printed with every number
(the machine is shared: compare numbers of one run only).

Usage: python bench/bench_gf7_full.py [--workdir DIR] [--workers N] [--ratio] [--strip ROWS] [--render-only]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_panms import build, run_size  # noqa: E402  (the same build and measurement as the crops)


def _load() -> str:
    return "load average " + ", ".join(f"{v:.2f}" for v in os.getloadavg())


def _cpu_s() -> float:
    """CPU seconds of this process so far (all its threads): what the work costs whatever the load."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def strip(rows: int, workers: int) -> int:
    """Render a full-width pan strip and its MS strip (timed, written to a temporary directory)."""
    from gdal_gf4cal.simulate.gf7 import PAN_FULL, RATIO, make_gf7_scene, render_gf7_image
    scene = make_gf7_scene(seed=0)
    y0 = PAN_FULL[1] // 2
    with tempfile.TemporaryDirectory(prefix="bench_gf7_strip_") as tmp:
        for name, win in (("pan", (0, y0, PAN_FULL[0], rows)),
                          ("ms", (0, y0 // RATIO, PAN_FULL[0] // RATIO, rows // RATIO))):
            print(f"{name} strip {win[2]} x {win[3]}: {_load()}", flush=True)
            t, c = time.perf_counter(), _cpu_s()
            render_gf7_image(scene, name, os.path.join(tmp, f"{name}.tif"), window=win, workers=workers)
            dt, dc = time.perf_counter() - t, _cpu_s() - c
            print(f"{name} strip {win[2]} x {win[3]}: {dt:.1f} s wall, {dc:.1f} s CPU ({win[2] * win[3] / dc / 1e6:.3f}"
                  f" Mpx per CPU s, {workers} threads); {_load()}", flush=True)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", default=os.path.join(os.environ.get("TMPDIR", "/tmp"), "gf4cal_bench_gf7_full"),
                    help="where the full scene is rendered once (several GB; keep it outside the repository)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--strip", type=int, default=None, metavar="ROWS", help="only time a full-width strip render")
    ap.add_argument("--render-only", action="store_true", help="render (or reuse) the scene, do not register")
    ap.add_argument("--ratio", action="store_true", help="also register on one thread: the threads' ratio")
    a = ap.parse_args(argv)
    if a.strip:
        return strip(a.strip, a.workers)
    os.makedirs(a.workdir, exist_ok=True)
    print(f"rendering the full GF7 scene into {a.workdir} (cached): {_load()}", flush=True)
    c = _cpu_s()
    render_s = build(a.workdir, 30720, a.workers)
    print(f"render: {render_s:.0f} s wall, {_cpu_s() - c:.0f} s CPU (nan = reused); {_load()}", flush=True)
    if a.render_only:
        return 0
    rows = {}
    for threads in dict.fromkeys([a.workers, 1] if a.ratio else [a.workers]):     # --workers 1: one run
        print(f"register-pan-ms, default options, {threads} thread(s): {_load()}", flush=True)
        row = rows[threads] = run_size(a.workdir, 30720, a.workers, threads=threads)
        print(json.dumps(row, indent=1))
        if "wall_s" not in row:
            print(f"register-pan-ms failed: {row['error']}")
            return 1
        print(f"full GF7 scene (pan 30720², MS 7680²), {threads} thread(s): register-pan-ms {row['wall_s']:.0f} s "
              f"wall ({row['wall_s'] / 60:.1f} min; goal 10 min), {row['cpu_s']:.0f} s CPU, peak "
              f"{row['peak_memory_gb']:.2f} GB (goal 3), correction vs truth RMS {row['correction_vs_truth_rms_px']} "
              f"px; {_load()}", flush=True)
    if a.ratio:
        many, one = rows[a.workers], rows[1]
        print(f"full GF7 scene: register-pan-ms {a.workers} threads / 1: ratio {one['wall_s'] / many['wall_s']:.2f}x "
              f"({one['wall_s']:.0f} s / {many['wall_s']:.0f} s wall; CPU {many['cpu_s'] / one['cpu_s']:.2f}x one "
              f"thread's; goal >= 1.5x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
