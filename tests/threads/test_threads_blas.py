"""GF4CAL_NUM_THREADS bounds BLAS too (issue 23): inside ``threads.limit``, ``threads.serial`` (every block and tile
on the pool) and a ``gf4cal`` command, OpenBLAS computes on the calling thread, and its own setting comes back when
the last such scope ends, whichever thread opened it.

Each case runs in a fresh Python started with ``OPENBLAS_NUM_THREADS=2`` (what OpenBLAS would use without the bound),
so that a bound that does nothing fails; skipped where NumPy's BLAS is not an OpenBLAS with its C API.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from gdal_gf4cal import threads

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")

pytestmark = pytest.mark.skipif(threads.blas_threads() is None, reason="NumPy's BLAS is not OpenBLAS")

SCOPES = r"""
import json, sys, threading
import numpy as np
from gdal_gf4cal import threads
seen = {"start": threads.blas_threads()}
with threads.limit(2):
    seen["limit(2)"] = threads.blas_threads()
    with threads.limit(1):
        seen["nested limit(1)"] = threads.blas_threads()
    seen["after nested"] = threads.blas_threads()
seen["after limit"] = threads.blas_threads()
with threads.serial():
    seen["serial"] = threads.blas_threads()
# scopes of two threads overlapping: BLAS stays at 1 until the last one ends
inside, leave = threading.Event(), threading.Event()
def other():
    with threads.limit(1):
        inside.set()
        leave.wait(10)
t = threading.Thread(target=other)
t.start()
inside.wait(10)
with threads.limit(2):
    pass
seen["other thread's scope still open"] = threads.blas_threads()
leave.set()
t.join()
seen["all closed"] = threads.blas_threads()
# blocks on the pool
seen["in blocks"] = sorted(set(threads.map_blocks(lambda sl: threads.blas_threads(), 8, block=1)))
seen["after blocks"] = threads.blas_threads()
print(json.dumps(seen))
"""

COMMAND = r"""
import argparse, json
from gdal_gf4cal import cli, threads
seen = {}
def run(args):
    seen["in the command"] = threads.blas_threads()
    return 0
status = cli._main(argparse.Namespace(_run=run))
seen["after"] = threads.blas_threads()
print(json.dumps({"status": status, **seen}))
"""


def _run(code, **env):
    e = dict(os.environ, OPENBLAS_NUM_THREADS="2", PYTHONPATH=os.path.abspath(ROOT), **env)
    e.pop(threads.ENV, None)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=e, timeout=120,
                          cwd=os.path.abspath(ROOT))
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_scopes_bound_blas_and_restore_it():
    seen = _run(SCOPES)
    assert seen["start"] == 2
    for key in ("limit(2)", "nested limit(1)", "after nested", "serial", "other thread's scope still open"):
        assert seen[key] == 1, key
    assert seen["in blocks"] == [1]
    for key in ("after limit", "all closed", "after blocks"):
        assert seen[key] == 2, key


def test_a_gf4cal_command_runs_with_one_blas_thread():
    seen = _run(COMMAND)
    assert seen == {"status": 0, "in the command": 1, "after": 2}


def _blas_threads(_):
    return threads.blas_threads()


def test_dask_workers_run_one_blas_thread(monkeypatch):
    """A local cluster's workers start with :data:`threads.SERIAL_ENV` (executors.WORKER_ENV): one BLAS thread
    (OpenBLAS's default is every core). A variable the user set wins over it (distributed's rule)."""
    pytest.importorskip("distributed")
    from gdal_gf4cal.executors import get_executor
    for name in threads.SERIAL_ENV:
        monkeypatch.delenv(name, raising=False)
    with get_executor("local:1") as ex:
        assert ex.submit(_blas_threads, 0).result() == 1



WHOLE_OR_SLICED = r"""
import json, os
import numpy as np
from gdal_gf4cal import RPCModel, _rpc_poly, rpc as rpc_module, threads
rpc = RPCModel.from_file(os.path.join("tests", "data", "rpc", "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML"))
rng = np.random.default_rng(3)
n = 40000
s, l = rng.uniform(0, 40000, n), rng.uniform(0, 40000, n)
h = rng.uniform(*rpc.height_range, n)
seen = {"outside": threads.blas_is_serial()}
with threads.limit(1):
    seen["inside"] = threads.blas_is_serial()
    whole = rpc.localize(s, l, h)
    whole += rpc.project(whole[0], whole[1], h)
seen["after"] = threads.blas_is_serial()
rpc_module.blas_is_serial = _rpc_poly.blas_is_serial = lambda: False     # as without threadpoolctl: sliced
with threads.limit(1):
    sliced = rpc.localize(s, l, h)
    sliced += rpc.project(sliced[0], sliced[1], h)
seen["same"] = all(np.array_equal(a, b) for a, b in zip(whole, sliced))
print(json.dumps(seen))
"""


def test_products_whole_or_sliced_give_the_same_bits():
    """Inside a BLAS-serial scope the kernels' (k, 20) x (20, chunk) products run whole (_rpc_poly.poly_product,
    project: fewer BLAS calls, ~8 % less CPU per localised point); outside it in slices BLAS keeps on the calling
    thread: each column is the same dot product either way, so localize and project give the same bits."""
    seen = _run(WHOLE_OR_SLICED)
    assert seen == {"outside": False, "inside": True, "after": False, "same": True}
