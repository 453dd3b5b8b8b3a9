#!/usr/bin/env python3
"""Every ratio of issue 23 in one run (``make bench``): the benchmarks behind its "Must show" items, one after the
other in child processes, then one table of ratio against goal.

Each benchmark prints its own table (shown as it runs); this script reads the ratio lines of that output. A
benchmark whose file is absent (bench_arosics.py, bench_gf7_full.py are written by other sessions), whose optional
tool is missing (rpcm, AROSICS: the benchmark says so) or that fails is listed as such and never stops the run.
The machine may be shared: the load average is printed before and after; read the ratios (each measured within one
benchmark's run, interleaved), not the times.

``--quick`` (the default of ``make bench``): fewer points and repeats, a few minutes in all; the goals are stated at
the issue's sizes (e.g. 2e6 points for the threads, 1e6 correspondences for fit_rpc), so a quick ratio is an
indication. ``--only NAME ...`` runs some of them.

Usage: python bench/bench_issue23.py [--quick] [--only threads rpc ...]
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
NUM = r"([-+]?\d+(?:\.\d+)?)"


def _rows(pattern: str, label: str, goal: str, ok):
    """A parser of one ratio: ``(label, regex with the ratio as its last group, goal text, test of the ratio)``."""
    return (label, re.compile(pattern, re.M), goal, ok)


#: name -> (script, full arguments, quick arguments, [parsers]); goals from issue 23 ("Must show").
BENCHES = {
    "threads": ("bench_threads.py", [], ["--points", "400000", "--repeat", "1"], [
        _rows(rf"^localize \+ project.*ratio\s+{NUM}x", "2 threads / 1, localise + project", ">= 1.6x",
              lambda r: r >= 1.6),
        # the process-pool alternative to threads for the point kernels, measured in the same run
        _rows(rf"^round trip on a pool .*: ratio\s+{NUM}x", "pool of 2 processes / 1 thread, localise + project",
              "(indication)", None),
        # one-second runs of small crops: their fixed costs (tile planning, plots, one output tile) are most of a run;
        # the goal is read on whole scenes (the "matching" and "gf7" rows)
        _rows(rf"^collect-gcps .*ratio\s+{NUM}x", "2 threads / 1, collect-gcps 1024-px crop", "(indication)", None),
        _rows(rf"^register-pan-ms \(GF7 .*ratio\s+{NUM}x", "2 threads / 1, register-pan-ms GF7 1024-px crop",
              "(indication)", None)]),
    "matching": ("bench_matching.py", ["--workers", "2"], ["--workers", "2", "--repeat", "2"], [
        _rows(rf"^ours 2 threads / 1: ratio {NUM}x", "2 threads / 1, collect-gcps 10240-px scene", ">= 1.5x",
              lambda r: r >= 1.5)]),
    "fit_rpc_large": ("bench_fit_rpc_large.py", [], ["--n", "200000"], [
        _rows(rf"ratio\s+{NUM}x", "fit_rpc / one dense lstsq", "<= 3x", lambda r: r <= 3.0)]),
    "compensation_core": ("bench_compensation_core.py", [], ["--repeat", "3"], [
        _rows(rf"^\s*{m}\s+{n}\s+(?:\S+\s+){{4}}{NUM}\s", f"compensation {m} {n} GCPs new/old (min)", "<= 1.0x",
              lambda r: r <= 1.0) for m in ("affine", "poly2") for n in (1000, 10000)]),
    "rpc": ("bench_rpc.py", [], ["--quick"], [
        _rows(rf"^project\s+{NUM}\s+{NUM}\s+{NUM}\s+{NUM}\s+{NUM}", "project / rpcm, one thread, 2e5 points",
              ">= 6x", lambda r: r >= 6.0),
        _rows(rf"^project\s+{NUM}\s+{NUM}\s+{NUM}", "project / GDAL, one thread", ">= 1x", lambda r: r >= 1.0),
        _rows(rf"^localize_dem\s+{NUM}\s+{NUM}\s+{NUM}", "localize_dem / GDAL, one thread", ">= 1.5x",
              lambda r: r >= 1.5)]),
    # the size of the point kernels (2e6 points): rpcm's temporaries leave the cache, ours do not
    "rpc_2e6": ("bench_rpc.py", ["--points", "2000000"], ["--points", "2000000", "--quick"], [
        _rows(rf"^project\s+{NUM}\s+{NUM}\s+{NUM}\s+{NUM}\s+{NUM}", "project / rpcm, one thread, 2e6 points",
              ">= 6x", lambda r: r >= 6.0)]),
    "refine_ortho": ("bench_refine_ortho.py", [], ["--repeat", "3"], [
        _rows(rf"\(gdalwarp \+ refine\): {NUM} \(min wall\)", "refine --ortho / (gdalwarp + refine), wall",
              "<= 1.1x", lambda r: r <= 1.1),
        _rows(rf"{NUM} \(min CPU", "refine --ortho / (gdalwarp + refine), CPU", "<= 1.1x", lambda r: r <= 1.1),
        _rows(rf"differing from gdalwarp's: {NUM} of", "refine --ortho pixels differing from gdalwarp's", "0",
              lambda r: r == 0)]),
    "bundle": ("bench_bundle.py", [], ["--ties", "2000"], [
        _rows(rf"^\s*100000\s+\S+\s+\d+\s+{NUM}\s", "bundle 10 views x 100k ties, s", "< 10 s", lambda r: r < 10.0),
        _rows(rf"^\s*2000\s+\S+\s+\d+\s+{NUM}\s", "bundle 10 views x 2k ties, s", "(indication)", None)]),
    "arosics": ("bench_arosics.py", [], ["--windows", "64", "--repeat", "1"], [
        _rows(rf"^window 64.*ratio\s+{NUM}x", "collect-gcps / AROSICS per valid tie, window 64", ">= 10x",
              lambda r: r >= 10.0)]),
    "gf7": ("bench_gf7_full.py", ["--ratio"], ["--quick"], [
        _rows(rf"^full GF7 scene \(.*?, 2 thread.*?\({NUM} min", "register-pan-ms full GF7 scene, 2 threads, min",
              "<= 10 min", lambda r: r <= 10.0),
        _rows(rf"^full GF7 scene: register-pan-ms 2 threads / 1: ratio {NUM}x",
              "2 threads / 1, register-pan-ms full GF7 scene", ">= 1.5x", lambda r: r >= 1.5)]),
}


def run(name: str, quick: bool, timeout: float) -> dict:
    """Run one benchmark as a child (its output shown as it comes); ``{"status", "output", "seconds"}``."""
    script, full, fast, _ = BENCHES[name]
    path = HERE / script
    if not path.exists():
        return {"status": "absent", "output": "", "seconds": 0.0}
    args = list(fast if quick else full)
    if name == "gf7" and "--quick" in args and "--quick" not in path.read_text():
        args.remove("--quick")
        if quick:
            return {"status": "skipped (no --quick: full GF7 scene)", "output": "", "seconds": 0.0}
    print(f"\n== {script} {' '.join(args)}", flush=True)
    t = time.perf_counter()
    lines = []
    try:
        with subprocess.Popen([sys.executable, str(path)] + args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True, cwd=str(HERE.parent)) as p:
            for line in p.stdout:
                print("   " + line, end="", flush=True)
                lines.append(line)
                if time.perf_counter() - t > timeout:
                    p.kill()
                    return {"status": f"timed out after {timeout:.0f} s", "output": "".join(lines),
                            "seconds": time.perf_counter() - t}
            code = p.wait()
    except OSError as exc:
        return {"status": f"failed to start: {exc}", "output": "", "seconds": 0.0}
    status = "ok" if code == 0 else f"failed (exit {code})"
    return {"status": status, "output": "".join(lines), "seconds": time.perf_counter() - t}


def summarise(results: dict) -> list:
    """Rows ``(label, ratio text, goal, verdict)`` of every parser of every benchmark run."""
    rows = []
    for name, res in results.items():
        parsers = BENCHES[name][3]
        if res["status"] != "ok" and not res["output"]:
            rows.append((f"{name}", "-", "", res["status"]))
            continue
        for label, rx, goal, ok in parsers:
            found = rx.findall(res["output"])
            if not found:
                why = "rpcm not installed" if "rpcm not installed" in res["output"] and "rpcm" in label else (
                    "AROSICS not installed" if "AROSICS not installed" in res["output"] else
                    ("not measured in this mode" if res["status"] == "ok" else res["status"]))
                rows.append((label, "-", goal, why))
                continue
            last = found[-1]
            value = float(last[-1] if isinstance(last, tuple) else last)
            rows.append((label, f"{value:.2f}", goal, "-" if ok is None else ("met" if ok(value) else "NOT met")))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer points and repeats (make bench)")
    ap.add_argument("--only", nargs="+", choices=list(BENCHES), help="run only these")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per benchmark before it is stopped")
    a = ap.parse_args()
    load0 = os.getloadavg()[0]
    print(f"issue 23 benchmarks ({'quick' if a.quick else 'full'}); load average {load0:.1f} on {os.cpu_count()} "
          f"cores", flush=True)
    results = {name: run(name, a.quick, a.timeout) for name in (a.only or BENCHES)}
    rows = summarise(results)
    width = max(len(r[0]) for r in rows)
    print(f"\n== issue 23, every ratio of this run (load average {load0:.1f} before, {os.getloadavg()[0]:.1f} after)")
    print(f"{'what':<{width}}  {'ratio':>8}  {'goal':<12}  verdict")
    for label, value, goal, verdict in rows:
        print(f"{label:<{width}}  {value:>8}  {goal:<12}  {verdict}")
    print("times: " + ", ".join(f"{k} {v['seconds']:.0f} s" for k, v in results.items() if v["seconds"]))


if __name__ == "__main__":
    main()
