"""One way to get an executor for tiles and scenes (issue 14): serial, threads, or Dask.

Every unit of work in gdal_gf4cal (the tile function of matching, :func:`gdal_gf4cal.matching.collect.match_tile`,
and the scene function of each batch job, :mod:`gdal_gf4cal.batch`) is a plain top-level function of paths and
parameters: nothing pickled holds an open GDAL dataset, each task opens its own windows. So the same function runs

- ``"serial"`` (or ``1``): in the calling thread;
- ``"threads"`` / ``"threads:N"`` / ``None`` (default, today's behaviour): a :class:`concurrent.futures.ThreadPoolExecutor`;
- ``"local"`` / ``"local:N"``: a ``distributed.LocalCluster`` with N worker processes of 1 thread each;
- ``"tcp://HOST:PORT"``: a running Dask scheduler (``dask scheduler`` + ``dask worker``, shared storage);
- a ``distributed.Client`` or any :class:`concurrent.futures.Executor` passed from Python.

:func:`map_ordered` submits the tasks, reports progress over completed tasks, gathers the results in submission
order (so outputs are deterministic whatever the executor) and cancels what is left on cancel.
"""
from __future__ import annotations

import concurrent.futures as cf
import contextlib
import ctypes
import os
import sys
import threading
import time
import warnings
from typing import Any, Callable, Iterator, List, Optional, Sequence

from . import threads
from .errors import CancelledError, Gf4calError
from .progress import report

#: seconds to wait for a remote scheduler before giving up
CONNECT_TIMEOUT_S = 5.0

#: Environment of the worker processes of a ``local`` cluster. Dask's default sets ``MALLOC_TRIM_THRESHOLD_=65536``
#: (memory back to the OS at once), which also switches off glibc's adaptive mmap threshold: every array above
#: 128 KB (the windows, spectra and stacks of matching) is then a fresh mmap, paid in page faults, and matching ran
#: ~1.5x slower in a worker than in a thread (4x the minor faults, bench/bench_scale.py). Explicit thresholds at
#: glibc's own adaptive maxima keep tile-sized arrays on the heap; memory stays bounded by the tile. For workers
#: you start yourself, set the same in ``distributed.nanny.pre-spawn-environ`` (README). One thread per worker for
#: BLAS and for the point kernels (:data:`gdal_gf4cal.threads.SERIAL_ENV`): the cluster parallelises.
WORKER_ENV = {"MALLOC_MMAP_THRESHOLD_": 32 * 2 ** 20, "MALLOC_TRIM_THRESHOLD_": 64 * 2 ** 20, **threads.SERIAL_ENV}

#: glibc's ``mallopt`` parameters of the two thresholds of :data:`WORKER_ENV` (``malloc.h``).
_MALLOPT = {"MALLOC_TRIM_THRESHOLD_": -1, "MALLOC_MMAP_THRESHOLD_": -3}
_heap_lock = threading.Lock()
_heap: dict = {}                    # "set": whether the thresholds are in force (absent: not tried yet)


def keep_heap() -> bool:
    """This process's glibc malloc keeps tile-sized arrays on its heap from now on: the thresholds of
    :data:`WORKER_ENV` (what a Dask worker gets from its environment) set once through ``mallopt``, unless the
    environment sets them. With glibc's defaults a matching tile's stacks of windows and spectra (1-4 MB) were
    fresh mmaps, page-faulted in and unmapped again call after call (~6 us a page on a KVM guest: 17,000-30,000
    faults per run of collect-gcps on the Sentinel-2 pair or the thread bench's scene, an inverse FFT of 4 windows
    of 256 px 4x slower), and every unmap interrupts the process's other threads. The heap then keeps up to the
    trim threshold (64 MB) free for the next tile instead of handing it back. Returns whether the thresholds are
    in force; not glibc (macOS, Windows, musl): nothing changes."""
    with _heap_lock:
        if "set" not in _heap:
            _heap["set"] = _set_heap_thresholds()
        return _heap["set"]


def _set_heap_thresholds() -> bool:
    """:data:`WORKER_ENV`'s malloc thresholds set in glibc (False: not glibc, or the environment sets them)."""
    if not sys.platform.startswith("linux") or any(k in os.environ for k in _MALLOPT):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    return all(mallopt(_MALLOPT[k], int(WORKER_ENV[k])) == 1 for k in _MALLOPT)   # musl's mallopt: 0


class ExecutorError(Gf4calError, ConnectionError):
    """The executor could not be started or reached (exit code 2 at the CLI)."""


class SerialExecutor(cf.Executor):
    """A :class:`concurrent.futures.Executor` that runs each task at ``submit`` in the calling thread."""

    def submit(self, fn, /, *args, **kwargs):
        fut: cf.Future = cf.Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # noqa: BLE001 - delivered through the future, like any executor
            if isinstance(exc, (KeyboardInterrupt, CancelledError)):
                raise
            fut.set_exception(exc)
        return fut


@contextlib.contextmanager
def _quiet_tornado():
    # Debian's distributed + tornado 6.2 warn "make_current is deprecated" when an event loop starts.
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        yield


def _client_executor(client):
    return client.get_executor(pure=False)


@contextlib.contextmanager
def get_executor(spec: Any = None, *, workers: Optional[int] = None,
                 connect_timeout_s: float = CONNECT_TIMEOUT_S) -> Iterator[cf.Executor]:
    """Context manager yielding a :class:`concurrent.futures.Executor` for ``spec`` (see the module docstring).

    Parameters
    ----------
    spec : ``None``/``"threads[:N]"``, ``"serial"``, ``"local[:N]"``, ``"tcp://HOST:PORT"`` (or any Dask
        scheduler address), a ``distributed.Client``, or a :class:`concurrent.futures.Executor` (used as is,
        not shut down).
    workers : thread/process count when ``spec`` gives none (default: ``GF4CAL_NUM_THREADS``, else the machine's
        cores, :func:`gdal_gf4cal.threads.num_threads`).
    connect_timeout_s : how long to wait for a remote scheduler.

    Raises
    ------
    ExecutorError : an unknown spec, Dask missing, or an unreachable scheduler (one line, exit 2 at the CLI).
    """
    if isinstance(spec, cf.Executor):
        yield spec
        return
    if spec is not None and hasattr(spec, "get_executor") and hasattr(spec, "scheduler_info"):
        yield _client_executor(spec)
        return
    s = "threads" if spec is None else str(spec).strip()
    kind, _, n = s.partition(":") if "://" not in s else (s, "", "")
    try:
        count = int(n) if n else (workers or threads.num_threads())
    except ValueError:
        raise ExecutorError(f"executor {s!r}: the worker count must be a whole number, e.g. local:2") from None
    if count < 1:
        raise ExecutorError(f"executor {s!r}: give at least 1 worker")
    if kind in ("serial", "1") or (kind == "threads" and count == 1):
        yield SerialExecutor()
        return
    if kind == "threads":
        with cf.ThreadPoolExecutor(max_workers=count) as ex:
            try:
                yield ex
            except BaseException:
                ex.shutdown(wait=True, cancel_futures=True)
                raise
        return
    try:
        import distributed   # optional dependency (Dask runs only): imported when asked for
    except ImportError:
        raise ExecutorError("Dask is not installed; install python3-distributed (apt) or dask[distributed] "
                            "(pip), or run without --dask") from None
    if kind == "local":
        with _local_client(distributed, count) as client:
            yield _client_executor(client)
        return
    if s.startswith(("tcp://", "tls://", "ucx://", "inproc://")):
        with _remote_client(distributed, s, connect_timeout_s) as client:
            yield _client_executor(client)
        return
    raise ExecutorError(f"unknown executor {s!r}; use serial, threads[:N], local[:N] or tcp://HOST:PORT")


@contextlib.contextmanager
def _local_client(distributed, count: int):
    """A Dask client of a local cluster of ``count`` single-threaded worker processes, closed on exit."""
    import dask       # optional dependency, as distributed (see get_executor)
    with _quiet_tornado(), dask.config.set({"distributed.worker.daemon": False,
                                            "distributed.nanny.pre-spawn-environ": dict(WORKER_ENV)}):
        # No dashboard; the scheduler's HTTP server (metrics) on a free port: the default 8787 is often taken
        # by another cluster, and distributed 2022.12 then leaks a socket and warns.
        cluster = distributed.LocalCluster(n_workers=count, threads_per_worker=1, processes=True,
                                           dashboard_address=None, silence_logs=40,
                                           scheduler_kwargs={"dashboard": False, "dashboard_address": ":0"})
        try:
            client = distributed.Client(cluster)
        except BaseException:
            cluster.close()
            raise
    try:
        yield client
    finally:
        with _quiet_tornado():
            client.close()
            cluster.close()


@contextlib.contextmanager
def _remote_client(distributed, address: str, connect_timeout_s: float):
    """A Dask client of the scheduler at ``address``, closed on exit; an unreachable one is named."""
    try:
        with _quiet_tornado():
            client = distributed.Client(address, timeout=connect_timeout_s)
    except (OSError, TimeoutError) as exc:
        raise ExecutorError(f"cannot reach the Dask scheduler at {address} within {connect_timeout_s:g} s "
                            f"({type(exc).__name__}); start it with `dask scheduler` or check the "
                            "address") from None
    try:
        yield client
    finally:
        with _quiet_tornado():
            client.close()


def dask_client(executor):
    """The ``distributed.Client`` behind an executor from :func:`get_executor` (``None`` for threads/serial)."""
    return getattr(executor, "_client", None)


def map_ordered(fn: Callable, items: Sequence, executor: Optional[cf.Executor] = None, *,
                progress=None, start: float = 0.0, stop: float = 1.0, label: str = "task",
                return_exceptions: bool = False, partial: Optional[Callable[[], float]] = None,
                poll_s: float = 0.25, done: Optional[List[bool]] = None,
                out: Optional[List[Any]] = None) -> List[Any]:
    """Run ``fn(item)`` for every item on ``executor`` (``None``: serially) and return the results in
    submission order (deterministic output whatever the executor).

    Progress goes over completed tasks from ``start`` to ``stop`` (plus ``partial()``, the summed fractions of
    the running tasks, when given); while tasks run it is reported every ``poll_s`` seconds, so a
    :class:`CancelledError` raised by ``progress`` (or Ctrl-C) cancels the pending tasks promptly and propagates.
    On cancel, tasks already running on threads are waited for (they see the cancel through their own progress
    and clean up). With ``return_exceptions`` a failing task gives its exception in its slot instead of raising.
    ``done`` (a list of n False) is set True per slot as results arrive, in ``out`` (a list of n, else a new
    one): what finished before a cancel.
    """
    n = len(items)
    if out is None:
        out = [None] * n
    if n == 0:
        return out

    def frac(k):
        extra = min(max(float(partial()), 0.0), n - k) if partial is not None else 0.0
        return start + (stop - start) * (k + extra) / n

    if executor is None or isinstance(executor, SerialExecutor):
        for i, item in enumerate(items):
            try:
                out[i] = fn(item)
            except (CancelledError, KeyboardInterrupt):
                raise
            except Exception as exc:  # noqa: BLE001 - reported in its slot
                if not return_exceptions:
                    raise
                out[i] = exc
            if done is not None:
                done[i] = True
            report(progress, start + (stop - start) * (i + 1) / n, f"{label} {i + 1}/{n}")
        return out
    futures = {}
    k = 0
    try:
        for i, item in enumerate(items):
            futures[executor.submit(fn, item)] = i
        pending = set(futures)
        while pending:
            finished, pending = cf.wait(pending, timeout=poll_s, return_when=cf.FIRST_COMPLETED)
            for fut in sorted(finished, key=futures.__getitem__):
                i = futures[fut]
                exc = fut.exception()
                if exc is not None:
                    if not return_exceptions:
                        raise exc
                    out[i] = exc
                else:
                    out[i] = fut.result()
                if done is not None:
                    done[i] = True
                k += 1
            report(progress, frac(k), f"{label} {k}/{n}")
    except BaseException:
        for fut in futures:
            fut.cancel()
        if isinstance(executor, cf.ThreadPoolExecutor):
            # Running threads cannot be stopped from outside: wait until they have seen the cancel (through
            # their progress callbacks) and removed their partial outputs, or finished.
            cf.wait([f for f in futures if not f.cancelled()])
            for fut, i in futures.items():
                if done is not None and fut.done() and not fut.cancelled() and fut.exception() is None:
                    out[i], done[i] = fut.result(), True
        elif dask_client(executor) is not None:
            _drain_workers(dask_client(executor))
        raise
    return out


def _executing(dask_worker) -> int:
    return len(dask_worker.state.executing)


def _drain_workers(client, timeout_s: float = 30.0) -> None:
    """After a cancel: wait (at most ``timeout_s``) until the workers run no task any more, so that the cancelled
    tasks have stopped at their next progress call and removed their partial outputs before the caller closes
    the cluster or reports."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            if not sum(client.run(_executing).values()):
                return
        except Exception:  # noqa: BLE001 - workers gone or another distributed version: nothing to wait for
            return
        time.sleep(0.1)
