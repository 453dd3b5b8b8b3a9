"""The one thread setting of the point kernels (issue 23): ``GF4CAL_NUM_THREADS`` and the pool they share.

``GF4CAL_NUM_THREADS`` (default: the cores this process may run on; ``1``: no pool) is read here and nowhere else
(:func:`num_threads`). The point kernels (:meth:`RPCModel.project <gdal_gf4cal.rpc.RPCModel.project>`,
``localize``, :func:`~gdal_gf4cal.localization.localize_dem` and the sensor-model mixin paths) split an input of
more than :data:`BLOCK` points into fixed blocks (:func:`block_slices`) and run them over one shared
:class:`~concurrent.futures.ThreadPoolExecutor` (:func:`map_blocks`; NumPy, GDAL and PROJ release the GIL);
:func:`~gdal_gf4cal.localization.localize_dem` in blocks of :data:`DEM_BLOCK`. Matching tiles and batch scenes run
on pools of :func:`num_threads` threads too (:func:`pool_workers`), each unit with serial kernels (:func:`serial`).

Results are bit-identical whatever the thread count: the blocks depend on the number of points only, never on the
threads, each block is computed exactly as the serial path computes it (no reduction spans blocks, and a kernel
called inside a block never splits again), and the serial path (``1``) walks the same blocks in order.

The QGIS algorithms run under QGIS's own thread setting (:func:`limit`, per calling thread); Dask workers get
``GF4CAL_NUM_THREADS=1`` and one BLAS thread (:data:`SERIAL_ENV` in :data:`gdal_gf4cal.executors.WORKER_ENV`): one
thread each, the executor parallelises.

BLAS is bounded by the same setting: inside :func:`limit`, :func:`serial` (every block and tile on the pool) and
a ``gf4cal`` command, BLAS computes on the calling thread (:func:`blas_serial`: the BLAS libraries' thread count set to 1
through threadpoolctl in this process, restored when the last such scope ends). The parallelism is this module's
pool, of :func:`num_threads` threads: ``GF4CAL_NUM_THREADS=1`` uses one core, BLAS's threads do not compete with
the pool's for the cores, and no number depends on how many threads OpenBLAS would have split a product over.
"""
from __future__ import annotations

import functools
import os
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Callable, Iterator, List, Optional, Sequence, TypeVar

import numpy as np

try:
    from threadpoolctl import ThreadpoolController
except ImportError:                 # a host Python without it (Debian: python3-threadpoolctl): BLAS keeps its threads
    ThreadpoolController = None

from .errors import Gf4calError

__all__ = ["ENV", "BLOCK", "DEM_BLOCK", "ThreadSettingError", "machine_cores", "num_threads", "limit",
           "block_slices", "map_blocks", "split_points", "serial", "pool_workers", "matmul", "BLAS_SERIAL_SIZE",
           "SERIAL_ENV", "blas_serial", "blas_is_serial", "blas_threads", "run_tasks", "start", "PerThread",
           "rows_times", "rounds", "product_into", "COLUMN_GROUP"]

#: The environment variable of the thread setting.
ENV = "GF4CAL_NUM_THREADS"

#: Points per block of a split kernel: larger inputs are split (below it a pool does not pay). A multiple of the
#: kernels' own cache chunks (8192 to 32768 points), so a block evaluates exactly the chunks the serial path does
#: (project and localize give the same bits for any such block size: each point is computed on its own). 32768
#: points keep a block's working set (the (16, n) Jacobian rows, the Newton state: ~8 MB) small enough that the
#: blocks of two threads share the last-level cache instead of streaming from memory.
BLOCK = 32768

#: Points per block of :func:`~gdal_gf4cal.localization.localize_dem`: there a block is a whole intersection (its
#: own choice of Newton or march), so its numbers depend on the blocks: kept at the size they were pinned with.
DEM_BLOCK = 65536

#: Environment of a process that runs one thread (a Dask worker, :data:`gdal_gf4cal.executors.WORKER_ENV`): the
#: BLAS libraries read these when they load, before any :func:`blas_serial` could act.
SERIAL_ENV = {"OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1, ENV: 1}

T = TypeVar("T")

_local = threading.local()          # .limit (an override for this thread), .in_block (inside a block: serial)
_pool_lock = threading.Lock()
_pool: Optional[ThreadPoolExecutor] = None
_pool_size = 0


class ThreadSettingError(Gf4calError, ValueError):
    """``GF4CAL_NUM_THREADS`` is not a whole number >= 1."""


def machine_cores() -> int:
    """The cores this process may run on (its CPU affinity where the system tells it, else all cores)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def num_threads() -> int:
    """Threads the point kernels may use now: 1 inside a block (never nested), else the :func:`limit` of this
    thread, else ``GF4CAL_NUM_THREADS``, else :func:`machine_cores`."""
    if getattr(_local, "in_block", False):
        return 1
    override = getattr(_local, "limit", None)
    if override is not None:
        return override
    text = os.environ.get(ENV, "").strip()
    if not text:
        return machine_cores()
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise ThreadSettingError(f"{ENV}={text!r} is not a number of threads; set a whole number >= 1 (1: no "
                                 "threads) or unset it (all cores)")
    return value


@contextmanager
def limit(n: Optional[int]) -> Iterator[None]:
    """Within the ``with`` block, the calling thread's kernels use ``n`` threads (``None`` or < 1: unchanged, i.e.
    ``GF4CAL_NUM_THREADS`` or all cores). How a host application (QGIS) passes its own setting."""
    previous = getattr(_local, "limit", None)
    if n is not None and int(n) >= 1:
        _local.limit = int(n)
    try:
        with blas_serial():
            yield
    finally:
        _local.limit = previous


@contextmanager
def serial() -> Iterator[None]:
    """Within the ``with`` block, the calling thread's kernels run serially (:func:`num_threads` is 1): how a unit of
    work that already runs on a pool thread (a tile of matching windows, a scene of a batch) keeps the kernels it
    calls from splitting over the pool again (no threads x threads oversubscription)."""
    previous = getattr(_local, "in_block", False)
    _local.in_block = True
    try:
        with blas_serial():
            yield
    finally:
        _local.in_block = previous


_blas_lock = threading.Lock()
_blas_scopes = 0                    # blas_serial scopes open in this process (any thread)
_blas_limiter = None                # threadpoolctl's limiter of the first open scope (restores the counts)
_blas_seen = (-1, None)             # (len(sys.modules) at the last look, the BLAS libraries' controller)


def _blas_controller():
    """threadpoolctl's controller of the BLAS libraries this process has loaded (NumPy's, SciPy's), looked for
    again only after a Python module was imported (what loads a library); None without threadpoolctl."""
    global _blas_seen
    if ThreadpoolController is None:
        return None
    if _blas_seen[0] != len(sys.modules):
        _blas_seen = (len(sys.modules), ThreadpoolController().select(user_api="blas"))
    return _blas_seen[1]


@contextmanager
def blas_serial() -> Iterator[None]:
    """Within the ``with`` block BLAS computes on the calling thread: the BLAS libraries' thread count
    (process-wide: their C APIs have no per-thread setting; set through threadpoolctl) is 1 while any such block
    is open in any thread, and what it was before is restored when the last one ends. Entered by :func:`limit`
    and :func:`serial`; a no-op without threadpoolctl (then set :data:`SERIAL_ENV` before starting Python)."""
    global _blas_scopes, _blas_limiter
    with _blas_lock:
        if _blas_scopes == 0:
            ctl = _blas_controller()
            _blas_limiter = ctl.limit(limits=1) if ctl is not None and len(ctl.lib_controllers) else None
        _blas_scopes += 1
    try:
        yield
    finally:
        with _blas_lock:
            _blas_scopes -= 1
            if _blas_scopes == 0 and _blas_limiter is not None:
                _blas_limiter.restore_original_limits()
                _blas_limiter = None


def blas_is_serial() -> bool:
    """True while a :func:`blas_serial` scope holds the BLAS libraries at one thread (in any thread of the
    process): then a product of any size is computed on the calling thread, and need not be sliced."""
    return _blas_scopes > 0 and _blas_limiter is not None


def blas_threads() -> Optional[int]:
    """The BLAS libraries' thread count in this process now (the largest over the loaded ones; None: none found,
    or no threadpoolctl)."""
    ctl = _blas_controller()
    counts = [int(c.num_threads) for c in ctl.lib_controllers] if ctl is not None else []
    return max(counts) if counts else None


def pool_workers(workers: Optional[int], tasks: int) -> int:
    """Threads for ``tasks`` units of work: ``workers`` when given (>= 1), else :func:`num_threads`, never more than
    the tasks (1: run them in the calling thread)."""
    n = int(workers) if workers is not None and int(workers) >= 1 else num_threads()
    return max(1, min(n, int(tasks)))


def block_slices(n: int, block: Optional[int] = None) -> List[slice]:
    """The fixed blocks of ``n`` points: ``[0, block), [block, 2 block), ...`` (one slice for ``n <= block``;
    ``block`` defaults to :data:`BLOCK`)."""
    block = BLOCK if block is None else int(block)
    if n <= block:
        return [slice(0, n)]
    return [slice(i, min(i + block, n)) for i in range(0, n, block)]


def map_blocks(fn: Callable[[slice], T], n: int, block: Optional[int] = None) -> List[T]:
    """``[fn(s) for s in block_slices(n, block)]``, the blocks run over the shared pool by up to
    :func:`num_threads` threads (the caller is one of them). Inside ``fn`` the kernels run serially. The first
    failing block's exception (in block order among those run) is raised once every running block has ended."""
    slices = block_slices(n, block)
    if len(slices) == 1:                # one block: the calling thread, as it is (the setting not even read)
        return [fn(slices[0])]
    threads = min(num_threads(), len(slices))
    if threads <= 1:
        return _run_serially(fn, slices)
    results: List[Optional[T]] = [None] * len(slices)
    errors: dict = {}
    counter = iter(range(len(slices)))
    counter_lock = threading.Lock()

    def work() -> None:
        while not errors:
            with counter_lock:
                i = next(counter, None)
            if i is None:
                return
            try:
                results[i] = _in_block(fn, slices[i])
            except BaseException as exc:        # re-raised in the caller, in block order
                errors[i] = exc

    futures = _submit(work, threads - 1)
    work()
    for f in futures:
        if not f.cancel():
            f.result()
    if errors:
        raise errors[min(errors)]
    return results  # type: ignore[return-value]


def run_tasks(tasks: Sequence[Callable[[], T]]) -> List[T]:
    """``[task() for task in tasks]``: independent pieces of work (the outputs of a job, the bands of a tile) run
    over the shared pool by up to :func:`num_threads` threads (:func:`map_blocks`, one task a block: serial
    kernels and BLAS inside, a lone task too: the same numbers for any count; results in order, the first failing
    task's exception raised). Put the longest first."""
    return map_blocks(lambda sl: _in_block(lambda _: tasks[sl.start](), sl), len(tasks), block=1) if tasks else []


def rounds(items: Sequence[T]) -> Iterator[Sequence[T]]:
    """``items`` in consecutive slices of :func:`num_threads` items: work that is computed over the pool a round at a
    time (:func:`run_tasks`) and then written in order by the calling thread, e.g. a raster's tiles: every thread
    has a tile, and one round's results are in memory, not the raster's. One thread: one item a round."""
    step = max(1, num_threads())
    for i in range(0, len(items), step):
        yield items[i:i + step]


def start(task: Callable[[], T]) -> Callable[[], T]:
    """``task()`` begun on a pool thread (serial kernels inside, as a :func:`run_tasks` task) while the caller goes
    on, e.g. GIL-bound plotting beside GDAL writing; returns ``join()``, which gives its result (or raises its
    exception) once it has ended. With one thread, or when no pool thread has taken it by then, the task runs in
    ``join`` on the calling thread: the same numbers for any count."""
    run = functools.partial(_in_block, lambda _: task(), None)
    future = _submit(run, 1)[0] if num_threads() > 1 else None
    return lambda: run() if future is None or future.cancel() else future.result()


class PerThread:
    """One object per thread, made by ``make()`` on first use in that thread (:meth:`get`), e.g. a GDAL dataset
    (a handle must not be used by two threads at once); released when this object is."""

    def __init__(self, make: Callable[[], T]):
        self._make = make
        self._local = threading.local()

    def get(self):
        obj = getattr(self._local, "obj", None)
        if obj is None:
            obj = self._local.obj = self._make()
        return obj


def split_points(fn: Callable[..., tuple], *arrays, block: Optional[int] = None) -> tuple:
    """``fn(*arrays)`` for flat arrays of the same ``n`` points, ``fn`` returning a tuple of flat per-point arrays:
    up to ``block`` points one call (the serial path as it always was), above it one call per block
    (:func:`map_blocks`), each item joined in block order: copied into its place by the thread that computed the
    block (the copy runs in parallel too), or concatenated when the blocks' items differ in type."""
    n = arrays[0].size
    if n <= (BLOCK if block is None else block):
        return fn(*arrays)
    out: list = []
    placed = []
    lock = threading.Lock()

    def run(sl):
        part = [np.asarray(p).ravel() for p in fn(*(a[sl] for a in arrays))]
        with lock:
            if not out:
                out.extend(np.empty(n, dtype=p.dtype) for p in part)
        fits = len(part) == len(out) and all(p.dtype == o.dtype and p.size == sl.stop - sl.start
                                             for p, o in zip(part, out))
        if fits:
            for o, p in zip(out, part):
                o[sl] = p
        placed.append(fits)
        return part

    parts = map_blocks(run, n, block)
    if all(placed):
        return tuple(out)
    return tuple(np.concatenate([p[k] for p in parts]) for k in range(len(parts[0])))


#: Largest product m x n x k that OpenBLAS computes on the calling thread (its GEMM_MULTITHREAD_THRESHOLD x
#: SMP_THRESHOLD_MIN): above it OpenBLAS splits the product over its own threads with other kernels, whose rounding
#: differs, and which fight the pool's threads for the cores.
BLAS_SERIAL_SIZE = 4 * 65536


def matmul(a: np.ndarray, b: np.ndarray, out: Optional[np.ndarray] = None) -> np.ndarray:
    """``a @ b`` (2-D, ``a`` small) in column slices of ``b`` that BLAS computes on the calling thread: the same
    numbers on any number of cores and with any BLAS thread setting, and no BLAS threads competing with the pool's
    (the point kernels' polynomial evaluations). ``out``: a (rows, n) array to write into (a reused buffer). Each
    slice is a :func:`product_into`: every column the bits it has in any other product of ``a``."""
    rows, k = a.shape
    n = b.shape[1]
    if out is None:
        out = np.empty((rows, n), dtype=np.result_type(a, b))
    step = max(COLUMN_GROUP, BLAS_SERIAL_SIZE // max(rows * k, 1) // COLUMN_GROUP * COLUMN_GROUP)
    for i in range(0, n, step):
        product_into(a, b[:, i:i + step], out[:, i:i + step])
    return out


#: Columns of ``b`` that :func:`product_into` hands to BLAS together: OpenBLAS's AVX-512 dgemm (SkylakeX and
#: Cooperlake kernels) computes the last 1 to 4 columns of a product whose width is not a multiple of 8 with
#: another kernel, whose rounding differs from the same column's in a wider product (1 ulp).
COLUMN_GROUP = 8


#: Multiply-adds (M x N x K) of the largest product OpenBLAS 0.3.21 computes with its small-matrix kernel on the
#: cores of :data:`SMALL_GEMM_CORES` (no packing): a (4, 20) x (20, 32768) product of the projection costs 252 us in
#: one call and 136 us in four of 8192 columns, a (12, 20) x (20, 16384) Jacobian 278 us against 235 us (a localise +
#: project round trip 6-9 % less CPU on one thread; the Haswell and Zen kernels have no such kernel: there one call).
SMALL_GEMM_MNK = 1_000_000
#: OpenBLAS cores (threadpoolctl's ``architecture``, lower case) with small-matrix GEMM kernels: the AVX-512 ones.
SMALL_GEMM_CORES = frozenset({"skylakex", "cooperlake", "sapphirerapids"})
_small_gemm_seen: tuple = (None, False)      # (the BLAS controller looked at, whether it has small-matrix kernels)


def _gemm_columns(rows: int, k: int) -> Optional[int]:
    """Columns per product of a (rows, k) matrix that stay within the small-matrix kernel (whole column groups);
    None: one product (a BLAS without such kernels, or none known yet). Reads the BLAS libraries :func:`blas_serial`
    last found and never looks for them itself: threadpoolctl walks the loaded libraries holding the dynamic
    loader's lock while its Python callback waits for the GIL, and a thread importing an extension module holds the
    GIL waiting for that lock (a deadlock, seen: register-pan-ms importing PIL while a product looked)."""
    global _small_gemm_seen
    ctl = _blas_seen[1]
    if ctl is not _small_gemm_seen[0]:
        libs = ctl.lib_controllers if ctl is not None else []
        archs = {str(getattr(c, "architecture", "")).lower() for c in libs}
        _small_gemm_seen = (ctl, bool(archs) and archs <= SMALL_GEMM_CORES)
    if not _small_gemm_seen[1]:
        return None
    return max(COLUMN_GROUP, SMALL_GEMM_MNK // max(rows * k, 1) // COLUMN_GROUP * COLUMN_GROUP)


def product_into(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``np.matmul(a, b, out=out)`` (2-D) with every column of the result the bits it has in any other product of
    ``a`` with columns of the same values, on OpenBLAS's Haswell, Zen, SkylakeX and Cooperlake kernels (the suite
    runs on each): the columns in whole groups of :data:`COLUMN_GROUP` (in products small enough for the
    small-matrix kernel where BLAS has one, :func:`_gemm_columns`), the rest in one more, padded with zero columns
    to a group (also what keeps a single column off BLAS's matrix-vector kernels)."""
    n = b.shape[1]
    whole = n - n % COLUMN_GROUP
    step = _gemm_columns(*a.shape) or max(whole, 1)
    for i in range(0, whole, step):
        np.matmul(a, b[:, i:i + step], out=out[:, i:i + step])
    if whole < n:
        padded = np.zeros((b.shape[0], COLUMN_GROUP), dtype=b.dtype)
        padded[:, :n - whole] = b[:, whole:]
        out[:, whole:] = np.matmul(a, padded)[:, :n - whole]
    return out


#: Largest ``m x n`` matrix-vector product OpenBLAS computes on the calling thread (2304 x its
#: GEMM_MULTITHREAD_THRESHOLD).
GEMV_SERIAL_SIZE = 2304 * 4


def rows_times(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` of a tall ``a`` (n, p) and a small ``b`` (p,) or (p, q) in row blocks that BLAS computes on the
    calling thread (:data:`GEMV_SERIAL_SIZE`, :data:`BLAS_SERIAL_SIZE`; :func:`matmul` sliced the other way): each
    row of the result is its own short dot product, so the blocks give the numbers of the one product (whose BLAS threads,
    on a loaded machine, cost more CPU than the product)."""
    n, p = a.shape
    size = GEMV_SERIAL_SIZE if b.ndim == 1 else BLAS_SERIAL_SIZE // max(b.shape[1], 1)
    step = max(1, size // max(p, 1) - 1)
    if n <= step:
        return a @ b
    out = np.empty((n,) + b.shape[1:], dtype=np.result_type(a, b))
    for i in range(0, n, step):
        out[i:i + step] = a[i:i + step] @ b
    return out


def _run_serially(fn, slices):
    return [_in_block(fn, s) for s in slices]


def _in_block(fn, s):
    """``fn(s)`` with the kernels it calls kept serial (no nested split over the pool)."""
    with serial():
        return fn(s)


def _submit(work: Callable[[], None], count: int) -> list:
    """``count`` runs of ``work`` submitted to the process's pool, grown to ``count`` threads at least (under the
    lock: a pool replaced by a larger one is shut down only once nobody can submit to it)."""
    global _pool, _pool_size
    with _pool_lock:
        if _pool is None or _pool_size < count:
            if _pool is not None:
                _pool.shutdown(wait=False)      # its running blocks finish; its threads then exit
            _pool = ThreadPoolExecutor(max_workers=count, thread_name_prefix="gf4cal")
            _pool_size = count
        return [_pool.submit(work) for _ in range(count)]
