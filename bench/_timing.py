"""Timing helper shared by the benchmarks (run as scripts: ``python bench/bench_x.py``)."""
from __future__ import annotations

import statistics
import time


def timed(fn, repeat: int):
    """Median wall time of ``repeat`` calls of ``fn`` (seconds) and the last result."""
    times, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out
