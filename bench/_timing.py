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


# ---------------------------------------------------------------------------------------------------------------
# One tree against another in one run: a child process per tree, each importing its own gdal_gf4cal, asked in turn.
# ---------------------------------------------------------------------------------------------------------------
def extract_tree(root: str, commit: str, dest: str) -> str:
    """``gdal_gf4cal`` of ``commit`` (``git archive`` of the repository ``root``) unpacked into ``dest``."""
    import subprocess
    import tarfile
    from io import BytesIO
    data = subprocess.run(["git", "-C", root, "archive", commit, "gdal_gf4cal"], capture_output=True,
                          check=True).stdout
    with tarfile.open(fileobj=BytesIO(data)) as tar:
        tar.extractall(dest)
    return dest


def start_child(script: str, tree: str, cwd: str, **env):
    """``python script --child`` importing ``gdal_gf4cal`` from ``tree`` (extra environment ``env``), once it has
    said it is ready (a JSON line)."""
    import json
    import os
    import subprocess
    import sys
    p = subprocess.Popen([sys.executable, os.path.abspath(script), "--child"], stdin=subprocess.PIPE,
                         stdout=subprocess.PIPE, text=True, env=dict(os.environ, PYTHONPATH=tree, **env), cwd=cwd)
    json.loads(p.stdout.readline())
    return p


def ask_child(p, case) -> dict:
    """One case (its fields on a line) sent to a child of :func:`start_child`; its JSON answer."""
    import json
    p.stdin.write(" ".join(map(str, case)) + "\n")
    p.stdin.flush()
    return json.loads(p.stdout.readline())


def interleaved(procs: dict, cases, repeat: int):
    """``((name, case), answer)`` for every case, ``repeat`` rounds, the trees asked in turn and in alternating
    order (old, new, then new, old, ...), so that a shared machine's load falls on both alike; the children are
    closed at the end."""
    try:
        for r in range(repeat):
            for case in cases:
                for name in list(procs) if r % 2 == 0 else list(procs)[::-1]:
                    yield (name, case), ask_child(procs[name], case)
    finally:
        for p in procs.values():
            p.stdin.close()
            p.wait()
