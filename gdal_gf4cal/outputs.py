"""The one output policy of every file-to-file job (DESIGN.md "Outputs"; METHODS §4.2: never overwrite an input).

A run declares every output up front in an :class:`OutputSet`; before any work the set refuses

* an output that is an input (same path, a symlink or hard link to it, or an ``.RPB`` / ``_RPC.TXT`` sidecar that
  GDAL would read as the RPC of an input image),
* two outputs that are the same file (``--out X.RPB --report X.RPB``),
* an existing output without ``overwrite=True``.

Each output is then written to a temporary next to its target (a hidden name that keeps the target's whole
basename, so writers that look at suffixes such as ``_RPC.TXT`` see the right one), checked (the file exists, is
not empty, and the output's own check passes: GDAL/OGR re-open, feature counts) and, when every output is
written, all are renamed into place together. On any failure, cancel (:class:`CancelledError`), ``KeyboardInterrupt``
or SIGTERM (the CLI turns it into ``KeyboardInterrupt``) every temporary and every folder the run created is
removed, and targets that were being replaced are restored. A temporary's name carries the writing process's id
(``.gf4cal-<pid>x<hex>-<name>``): the next run writing the same target removes the temporaries a killed run
(SIGKILL, power loss) left behind, recognised by that name and a process id that no longer runs (or, for the names
of earlier versions without a pid, ``.gf4cal-<8 hex>-<name>``, by an age of over an hour).

Every GeoTIFF is created with :func:`gtiff_options` (tiled, DEFLATE, BigTIFF when needed). A raster whose size
comes from user input (a resolution, a CRS) is checked before it is written
(:func:`check_raster_size`: a pixel limit, passed with ``force``, and the free space of the output's disk); a
written raster with no valid pixel is refused (:func:`check_raster` ``require_data=True``).

:func:`atomic_output` (single file: write next to the target, then ``os.replace``) lives here too; the writers of
the engine use it, so a file written outside an ``OutputSet`` is still never half-written.
"""
from __future__ import annotations

import os
import re
import shutil
import tempfile
import threading
import time
import uuid
from contextlib import contextmanager
from typing import Callable, Dict, Iterable, Iterator, List, Optional, Sequence

import numpy as np

from ._gdal import gdal_exceptions, open_raster, open_vector
from .errors import CancelledError, Gf4calError, InputOverwriteError

__all__ = ["OutputSet", "atomic_output", "fix_mode", "same_file", "rpc_stem", "check_not_a_shadowing_sidecar",
           "count_features", "check_raster", "check_vector", "check_raster_size", "remove_stale_temporaries",
           "process_tempdir", "raster_has_data", "MAX_RASTER_PIXELS", "check_output_path",
           "scene_stem"]

# Set by the CLI's SIGTERM/SIGINT handler: a run that has been told to stop never commits its outputs, even when the
# KeyboardInterrupt was swallowed on the way (e.g. raised inside a GDAL callback that ignores Python exceptions).
_INTERRUPTED = threading.Event()


def request_interrupt() -> None:
    """Mark the process as interrupted (signal handlers call this): no OutputSet commits afterwards."""
    _INTERRUPTED.set()


# Files SQLite/GDAL may leave next to a temporary (GeoPackage journals, GDAL's .aux.xml).
_COMPANIONS = ("-journal", "-wal", "-shm", ".aux.xml")


def fix_mode(path) -> None:
    """Give a file created through ``mkstemp`` (mode 0600) the usual permissions (0666 & ~umask)."""
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(path, 0o666 & ~mask)


@contextmanager
def atomic_output(path) -> Iterator[str]:
    """Yield a temporary path in ``path``'s folder (same extension, not yet created); on success it replaces
    ``path`` with the usual permissions, on any failure it is removed.

    ``/vsi`` paths (GDAL's virtual file systems) are yielded as they are: there is nothing to make atomic.
    """
    path = os.fspath(path)
    if path.startswith("/vsi"):
        yield path
        return
    folder = os.path.dirname(os.path.abspath(path))
    stem, ext = os.path.splitext(os.path.basename(path))
    fd, tmp = tempfile.mkstemp(prefix=f".{stem}.", suffix=".tmp" + ext, dir=folder)
    os.close(fd)
    os.unlink(tmp)        # writers (GDAL, OGR, pandas) create the file themselves; some refuse an existing one
    try:
        yield tmp
        os.replace(tmp, path)
        fix_mode(path)
    finally:
        _remove(tmp)


# ------------------------------------------------------------------------------------------------ path identity
def same_file(a, b) -> bool:
    """True when ``a`` and ``b`` name the same file: equal absolute paths, or (both existing) the same inode
    (symlinks, hard links, case-insensitive file systems)."""
    a, b = os.fspath(a), os.fspath(b)
    if os.path.abspath(a) == os.path.abspath(b) or os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.exists(a) and os.path.exists(b) and os.path.samefile(a, b)
    except OSError:
        return False


def rpc_stem(path) -> str:
    """``dir/name`` without ``.RPB`` / ``_RPC.TXT`` (sidecars) or the extension (images), lower case."""
    full = os.path.abspath(os.fspath(path))
    low = full.lower()
    for suffix in (".rpb", "_rpc.txt"):
        if low.endswith(suffix):
            return low[:-len(suffix)]
    return os.path.splitext(low)[0]


def scene_stem(path) -> str:
    """A scene's name for its outputs: ``scene.tif`` / ``scene.RPB`` / ``scene_RPC.TXT`` -> ``scene``.

    Only the last extension goes: product names carry dots (``GF4_PMS_E88.5_N32.5_...``) and two scenes must not
    collapse to one output name.
    """
    name = os.path.basename(os.fspath(path))
    stem = os.path.splitext(name)[0] if not name.startswith(".") else name
    if stem.upper().endswith("_RPC"):
        stem = stem[:-4]
    return stem or "scene"


def check_not_a_shadowing_sidecar(out_path, sources: Sequence) -> None:
    """Refuse an ``.RPB`` / ``_RPC.TXT`` output that GDAL would read as the RPC of an input image.

    GDAL looks for ``<stem>.RPB`` and ``<stem>_RPC.TXT`` (any case) next to an image and prefers them to the RPC in
    its TIFF tags, so writing one there silently changes the input's RPC (METHODS §4.2: never overwrite the input).
    Symlinked folders are resolved, so a sidecar reached through another path is refused too.
    """
    out_path = os.fspath(out_path)
    low = os.path.basename(out_path).lower()
    if not (low.endswith(".rpb") or low.endswith("_rpc.txt")):
        return
    stems = {rpc_stem(out_path), rpc_stem(os.path.join(os.path.realpath(os.path.dirname(os.path.abspath(out_path))),
                                                       os.path.basename(out_path)))}
    for src in sources:
        if not src or not isinstance(src, (str, os.PathLike)):
            continue
        src = os.fspath(src)
        if src.lower().endswith((".csv", ".points", ".geojson", ".gpkg", ".json")):
            continue
        src_stems = {rpc_stem(src), rpc_stem(os.path.realpath(src))}
        if stems & src_stems:
            name = os.path.basename(out_path)
            n = len(os.path.basename(rpc_stem(out_path)))
            raise InputOverwriteError(
                f"output {out_path!r} would be read by GDAL as the RPC of the input {src!r}; choose another name "
                f"(e.g. {name[:n]}_refined{name[n:]}) or write a .vrt")


# ------------------------------------------------------------------------------------------------ checks
def count_features(path) -> Dict[str, int]:
    """``{layer name: feature count}`` of a vector file, re-opened with OGR (a :class:`Gf4calError` if it cannot)."""
    ds = open_vector(path, what="written vector file")
    counts = {}
    for i in range(ds.GetLayerCount()):
        lyr = ds.GetLayer(i)
        counts[lyr.GetName()] = int(lyr.GetFeatureCount())
    ds = None
    return counts


def check_vector(expected: Optional[Dict[str, int]] = None) -> Callable[[str], None]:
    """A check for :meth:`OutputSet.declare`: the file re-opens with OGR and has ``expected`` features per layer."""
    def check(path: str) -> None:
        counts = count_features(path)
        for layer, n in (expected or {}).items():
            if counts.get(layer) != n:
                raise Gf4calError(f"the written file has {counts.get(layer, 0)} features in layer {layer!r} instead "
                                  f"of {n}; check the disk is not full and write again")
    return check


def check_raster(bands: Optional[int] = None, *, require_data: bool = False,
                 empty_reason: str = "") -> Callable[[str], None]:
    """A check for :meth:`OutputSet.declare`: the file re-opens with GDAL (with ``bands`` bands when given); with
    ``require_data`` it must hold a valid pixel (:func:`raster_has_data`), else the run fails naming
    ``empty_reason``."""
    def check(path: str) -> None:
        ds = open_raster(path, what="written raster")
        n = ds.RasterCount
        empty = require_data and not raster_has_data(ds)
        ds = None
        if bands is not None and n != bands:
            raise Gf4calError(f"the written raster has {n} bands instead of {bands}; check the disk and write again")
        if empty:
            raise Gf4calError("the output raster came out without a single valid pixel"
                              + (f": {empty_reason}" if empty_reason else "") + "; nothing was kept")
    return check


#: Largest raster (pixels) written from a size the user chose, unless ``force``: 4e9 px is a 60000 x 60000 px
#: ortho (a whole 0.3 m scene); beyond it a resolution is almost surely a typing error (e.g. degrees for metres).
MAX_RASTER_PIXELS = 4_000_000_000


def raster_has_data(ds, sample: int = 1024) -> bool:
    """True when the raster holds a valid pixel: its mask (no-data, alpha) is set and, without a no-data value or
    alpha, a value is not 0 (GDAL's warper fills with 0). GDAL's approximate min/max (a sample of blocks) answers
    for most rasters; only a raster that looks empty there is read decimated to at most ``sample`` x ``sample``
    (nearest neighbour) per band."""
    for i in range(1, ds.RasterCount + 1):
        band = ds.GetRasterBand(i)
        try:
            with gdal_exceptions():
                lo, hi = band.ComputeRasterMinMax(True)
        except (RuntimeError, TypeError):
            continue                                  # no valid value in the sample: read below
        plain = band.GetNoDataValue() is None and not (band.GetMaskFlags() & 0x04)      # GMF_ALPHA
        if np.isfinite(lo) and np.isfinite(hi) and not (plain and lo == 0 and hi == 0):
            return True
    W, H = ds.RasterXSize, ds.RasterYSize
    bw, bh = min(W, sample), min(H, sample)
    for i in range(1, ds.RasterCount + 1):
        band = ds.GetRasterBand(i)
        data = band.ReadAsArray(0, 0, W, H, buf_xsize=bw, buf_ysize=bh)
        valid = band.GetMaskBand().ReadAsArray(0, 0, W, H, buf_xsize=bw, buf_ysize=bh) > 0
        if band.GetNoDataValue() is None and not (band.GetMaskFlags() & 0x04):   # GMF_ALPHA
            valid &= data != 0
        valid &= np.isfinite(data) if data.dtype.kind == "f" else True
        if np.any(valid):
            return True
    return False


def _human_bytes(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if n < 1024 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024.0
    return f"{n:.1f} PB"


def check_raster_size(width: float, height: float, *, bands: int, bytes_per_sample: int, out_path, what: str,
                      force: bool = False, limit: int = MAX_RASTER_PIXELS, force_option: str = "--force") -> None:
    """Refuse, before writing, a raster whose size came from user input and is too large: more than ``limit`` pixels
    (unless ``force``) or more bytes (uncompressed) than the free space of ``out_path``'s disk (unless ``force``:
    compression may make it fit). ``what`` names the size's origin in the message (e.g. "at --res 0.0005 m")."""
    pixels = float(width) * float(height)
    size = f"{int(width):,} x {int(height):,} px"
    if pixels > limit and not force:
        raise Gf4calError(f"the output raster would be {size} ({pixels:.2g} px) {what}: more than the limit of "
                          f"{limit:.2g} px; check the value, or pass {force_option} to write it anyway")
    need = pixels * bands * bytes_per_sample
    folder = os.path.dirname(os.path.abspath(os.fspath(out_path)))
    while folder and not os.path.isdir(folder):
        folder = os.path.dirname(folder)
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return
    if need > free and not force:
        raise Gf4calError(f"the output raster would be {size} {what}, {_human_bytes(need)} uncompressed, and "
                          f"{folder} has {_human_bytes(free)} free; free space, choose another folder, or pass "
                          f"{force_option} if compression will make it fit")


def gtiff_options(*, tile: Optional[int] = None, predictor: Optional[int] = None, zlevel: Optional[int] = None,
                  threads: Optional[int] = None, extra: Sequence[str] = ()) -> List[str]:
    """GTiff creation options of every raster the project writes: tiled (``tile`` x ``tile`` blocks, GDAL's 256
    when None), DEFLATE (level ``zlevel``, GDAL's 6 when None; ``predictor`` 2 for integers, 3 for floats),
    BigTIFF when the file may pass 4 GB (GDAL's IF_SAFER), blocks compressed on ``threads`` threads; ``extra``: the
    writer's own (interleave, photometric, sparse)."""
    opts = ["TILED=YES"] + ([f"BLOCKXSIZE={tile}", f"BLOCKYSIZE={tile}"] if tile is not None else [])
    opts.append("COMPRESS=DEFLATE")
    opts += [f"ZLEVEL={zlevel}"] if zlevel is not None else []
    opts += [f"PREDICTOR={predictor}"] if predictor is not None else []
    opts.append("BIGTIFF=IF_SAFER")
    opts += [f"NUM_THREADS={threads}"] if threads is not None else []
    return opts + list(extra)


_TMP_RE = re.compile(r"^\.gf4cal-(?:(?P<pid>\d+)x[0-9a-f]{6}|(?P<legacy>[0-9a-f]{8}))-(?:old-)?(?P<name>.+)$")
#: Age after which a temporary of an earlier version (no process id in its name) is taken as left by a dead run.
_LEGACY_STALE_S = 3600.0


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:           # e.g. EPERM: it runs, as another user
        return True
    return True


def process_tempdir(prefix: str) -> "tempfile.TemporaryDirectory":
    """A ``tempfile.TemporaryDirectory`` named ``<prefix><pid>_...`` in the system's temporary folder, after removing
    the ones of the same prefix whose process no longer runs (left by a killed run)."""
    base = tempfile.gettempdir()
    pattern = re.compile(re.escape(prefix) + r"(\d+)_")
    try:
        entries = os.listdir(base)
    except OSError:
        entries = []
    for entry in entries:
        m = pattern.match(entry)
        if m and not _pid_alive(int(m.group(1))):
            shutil.rmtree(os.path.join(base, entry), ignore_errors=True)
    return tempfile.TemporaryDirectory(prefix=f"{prefix}{os.getpid()}_")


def remove_stale_temporaries(path) -> List[str]:
    """Remove the temporaries (and their companions) a killed earlier run left for the output ``path``: hidden
    ``.gf4cal-<pid>x<hex>-<name>`` (also ``-old-``) next to it whose process no longer runs, and legacy
    ``.gf4cal-<8 hex>-<name>`` over an hour old. Returns the names removed."""
    folder, name = os.path.split(os.path.abspath(os.fspath(path)))
    try:
        entries = os.listdir(folder)
    except OSError:
        return []
    removed = []
    for entry in entries:
        m = _TMP_RE.match(entry)
        if not m or m.group("name") != name:
            continue
        full = os.path.join(folder, entry)
        if m.group("pid") is not None:
            stale = not _pid_alive(int(m.group("pid")))
        else:
            try:
                stale = time.time() - os.lstat(full).st_mtime > _LEGACY_STALE_S
            except OSError:
                stale = False
        if stale:
            _remove(full)
            removed.append(entry)
    return removed


def _remove(path: str) -> None:
    for p in [path] + [path + c for c in _COMPANIONS]:
        try:
            if os.path.isdir(p) and not os.path.islink(p):
                shutil.rmtree(p, ignore_errors=True)
            elif os.path.lexists(p):
                os.unlink(p)
        except OSError:
            pass


def _check_not_an_input(path: str, inputs: Sequence[str]) -> None:
    for i in inputs:
        if same_file(path, i):
            raise InputOverwriteError(f"output {path!r} is an input; choose a new output path")
    check_not_a_shadowing_sidecar(path, inputs)


def check_output_path(path, *, overwrite: bool = False, inputs: Iterable = (), directory: bool = False) -> str:
    """The one write rule for an output path (:meth:`OutputSet.declare` and every library writer use it): not one
    of ``inputs`` (also through links and shadowing sidecars), not an existing file unless ``overwrite``, not a
    folder unless ``directory``. Raises :class:`~gdal_gf4cal.errors.InputOverwriteError` (one line: the path and
    what to do); returns the path as text."""
    path = os.fspath(path)
    _check_not_an_input(path, [os.fspath(i) for i in inputs if isinstance(i, (str, os.PathLike)) and os.fspath(i)])
    if os.path.lexists(path) and not overwrite:
        raise InputOverwriteError(f"output {path!r} exists; remove it, choose a new path or pass --overwrite "
                                  "(overwrite=True)")
    if os.path.isdir(path) and not directory:
        raise InputOverwriteError(f"output {path!r} is a folder; give a file name")
    return path


class _Output:
    __slots__ = ("key", "path", "tmp", "check", "is_dir")

    def __init__(self, key, path, tmp, check, is_dir):
        self.key, self.path, self.tmp, self.check, self.is_dir = key, path, tmp, check, is_dir


class OutputSet:
    """Every output of one run, written all-or-nothing (module docstring; DESIGN.md "Outputs").

    Usage::

        outs = OutputSet(inputs=[image, gcps, dem], overwrite=overwrite)
        rpc_tmp = outs.declare("rpc", out)                 # refuses collisions and existing files at once
        rep_tmp = outs.declare("report", report) if report else None
        with outs:                                         # creates missing folders; cleans up on any failure
            ... work, write to rpc_tmp / rep_tmp ...
        # leaving the block without an exception checks and renames every output together

    Parameters
    ----------
    inputs : paths the run reads; no output may be one of them (also through links and shadowing sidecars)
    overwrite : replace existing outputs (never an input)
    cancelled : optional callable returning True when the user cancelled; checked before the renames
    """

    def __init__(self, inputs: Iterable = (), *, overwrite: bool = False,
                 cancelled: Optional[Callable[[], bool]] = None):
        self.inputs: List[str] = [os.fspath(p) for p in inputs if isinstance(p, (str, os.PathLike)) and os.fspath(p)]
        self.overwrite = bool(overwrite)
        self.cancelled = cancelled
        self._outputs: Dict[str, _Output] = {}
        self._created_dirs: List[str] = []
        self._probed: set = set()
        self._folders: List[tuple] = []
        self._token = f"{os.getpid()}x{uuid.uuid4().hex[:6]}"
        self._entered = False
        self.committed = False

    # -------------------------------------------------------------------------------------------- declaring
    def add_input(self, path) -> None:
        """Declare one more input (e.g. a sidecar found while opening); re-checks the outputs against it."""
        if isinstance(path, (str, os.PathLike)) and os.fspath(path):
            self.inputs.append(os.fspath(path))
            for o in self._outputs.values():
                self._check_against_inputs(o.path, [os.fspath(path)])

    def _check_against_inputs(self, path: str, inputs: Sequence[str]) -> None:
        _check_not_an_input(path, inputs)

    def declare(self, key: str, path, *, check: Optional[Callable[[str], None]] = None,
                directory: bool = False) -> str:
        """Declare output ``key`` at ``path`` and return the temporary path to write it to (not yet created).

        Refuses at once an output that is an input, that another output already names, or that exists without
        ``overwrite``. ``check(tmp)`` runs on the written temporary before the renames (raise to fail the run).
        ``directory=True`` declares a folder output (written as a temporary folder, renamed as a whole).
        """
        if self._entered and self.committed:
            raise Gf4calError("this output set was already written; make a new one")
        path = os.fspath(path)
        if not path:
            raise Gf4calError(f"output {key}: empty path; give a file name")
        if key in self._outputs:
            raise Gf4calError(f"output {key!r} declared twice")
        for other in self._outputs.values():
            if same_file(path, other.path) or \
                    os.path.normcase(os.path.abspath(path)).lower() == os.path.normcase(
                        os.path.abspath(other.path)).lower():
                raise InputOverwriteError(f"outputs {other.key} and {key} are the same file {path!r}; give each "
                                          "output its own path")
        check_output_path(path, overwrite=self.overwrite, inputs=self.inputs, directory=directory)
        if path.startswith("/vsi"):
            tmp = path
        else:
            remove_stale_temporaries(path)
            folder, name = os.path.split(os.path.abspath(path))
            tmp = os.path.join(folder, f".gf4cal-{self._token}-{name}")
        self._outputs[key] = _Output(key, path, tmp, check, directory)
        if self._entered:
            self._make_folder(path)
        return tmp

    def declare_folder(self, key: str, path) -> str:
        """Declare a folder output that the run fills in place (a simulated scene, an experiment); returns ``path``.

        Refused when it is an input or holds an input, or exists and is not empty without ``overwrite``. On failure
        the folder is removed if this run created it, else every entry the run added to it is removed.
        """
        path = os.fspath(path)
        if not path:
            raise Gf4calError(f"output {key}: empty path; give a folder name")
        if os.path.lexists(path) and not os.path.isdir(path):
            raise InputOverwriteError(f"output folder {path!r} is a file; give a folder name")
        real = os.path.realpath(path)
        for i in self.inputs:
            ri = os.path.realpath(i)
            if same_file(path, i) or ri.startswith(real.rstrip(os.sep) + os.sep):
                raise InputOverwriteError(f"output folder {path!r} holds the input {i!r}; choose another folder")
        if os.path.isdir(path) and os.listdir(path) and not self.overwrite:
            raise InputOverwriteError(f"output folder {path!r} exists and is not empty; choose a new folder or "
                                      "pass --overwrite (overwrite=True)")
        before = set(os.listdir(path)) if os.path.isdir(path) else None
        self._folders.append((path, before))
        return path

    def set_check(self, key: str, check: Optional[Callable[[str], None]]) -> None:
        """Set the check of output ``key`` once the run knows what to expect (e.g. the feature counts)."""
        self._outputs[key].check = check

    def tmp(self, key: str) -> str:
        """The temporary path of output ``key``."""
        return self._outputs[key].tmp

    def path(self, key: str) -> str:
        """The final path of output ``key``."""
        return self._outputs[key].path

    @property
    def paths(self) -> Dict[str, str]:
        """``{key: final path}`` of every declared output (what reports list under ``outputs``)."""
        return {k: o.path for k, o in self._outputs.items()}

    def __contains__(self, key: str) -> bool:
        return key in self._outputs

    # -------------------------------------------------------------------------------------------- writing
    def _make_folder(self, path: str) -> None:
        folder = os.path.dirname(os.path.abspath(path))
        missing = []
        while folder and not os.path.isdir(folder):
            missing.append(folder)
            parent = os.path.dirname(folder)
            if parent == folder:
                break
            folder = parent
        for d in reversed(missing):
            try:
                os.mkdir(d)
            except FileExistsError:
                continue
            except OSError as exc:
                raise Gf4calError(f"cannot create the output folder {d}: {exc.strerror}; check the path and that "
                                  f"you can write in {os.path.dirname(d)}") from None
            self._created_dirs.append(d)
        self._probe(os.path.dirname(os.path.abspath(path)))

    def _probe(self, folder: str) -> None:
        """Refuse, before any work, a folder where no file can be created (permissions, an immutable or read-only
        folder: also as root): one line naming the folder instead of a failure at the first write."""
        if folder in self._probed:
            return
        try:
            fd, probe = tempfile.mkstemp(prefix=f".gf4cal-{self._token}-probe-", dir=folder)
            os.close(fd)
            os.remove(probe)
        except OSError as exc:
            raise Gf4calError(f"cannot write in the output folder {folder}: {exc.strerror}; choose a folder you "
                              "can write to") from None
        self._probed.add(folder)

    def __enter__(self) -> "OutputSet":
        self._entered = True
        try:
            for o in self._outputs.values():
                if not o.path.startswith("/vsi"):
                    self._make_folder(o.path)
            for path, before in self._folders:
                if before is None:
                    self._make_folder(os.path.join(path, "x"))
                else:
                    self._probe(path)
        except BaseException:
            self.abort()
            raise
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is not None:
            self.abort()
            return False
        try:
            self.commit()
        except BaseException:
            self.abort()
            raise
        return False

    def commit(self) -> Dict[str, str]:
        """Check every written temporary, then rename them all into place (restoring replaced files on failure)."""
        todo = [o for o in self._outputs.values() if not o.path.startswith("/vsi")]
        for o in todo:
            if not os.path.lexists(o.tmp):
                raise Gf4calError(f"output {o.key} ({o.path}) was not written; nothing was kept")
            if not o.is_dir and os.path.getsize(o.tmp) == 0:
                raise Gf4calError(f"output {o.key} ({o.path}) came out empty (disk full?); nothing was kept")
            if o.check is not None:
                o.check(o.tmp)
        if _INTERRUPTED.is_set():
            raise KeyboardInterrupt("interrupted before the outputs were written; nothing was kept")
        if self.cancelled is not None and self.cancelled():
            raise CancelledError("cancelled before the outputs were written; nothing was kept")
        backups: List[tuple] = []
        done: List[_Output] = []
        try:
            for o in todo:
                if os.path.lexists(o.path):          # overwrite=True: keep the old one until all are in place
                    bak = os.path.join(os.path.dirname(os.path.abspath(o.path)),
                                       f".gf4cal-{self._token}-old-{os.path.basename(o.path)}")
                    os.replace(o.path, bak) if not os.path.isdir(o.path) else os.rename(o.path, bak)
                    backups.append((o.path, bak))
                os.replace(o.tmp, o.path)
                done.append(o)
                if not o.is_dir:
                    fix_mode(o.path)
        except BaseException:
            for o in done:
                _remove(o.path)
            for path, bak in backups:
                try:
                    os.replace(bak, path)
                except OSError:
                    pass
            raise
        for _, bak in backups:
            _remove(bak)
        self.committed = True
        self._created_dirs = []
        self._folders = []
        return self.paths

    def abort(self) -> None:
        """Remove every temporary and every folder this run created (empty ones; nothing else)."""
        for o in self._outputs.values():
            if not o.path.startswith("/vsi") and o.tmp != o.path:
                _remove(o.tmp)
        for path, before in self._folders:
            if before is not None and os.path.isdir(path):
                for name in set(os.listdir(path)) - before:
                    _remove(os.path.join(path, name))
            elif before is None and os.path.isdir(path) and os.path.realpath(path) in {
                    os.path.realpath(d) for d in self._created_dirs}:
                shutil.rmtree(path, ignore_errors=True)
        self._folders = [] if self.committed else self._folders
        for d in reversed(self._created_dirs):
            try:
                os.rmdir(d)
            except OSError:
                pass
        self._created_dirs = []
