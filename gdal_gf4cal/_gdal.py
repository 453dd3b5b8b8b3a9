"""Private GDAL/OGR helpers: exceptions scoped to a call, quiet opens (DESIGN.md "Outputs", STYLE.md "GDAL").

The engine runs inside QGIS and other hosts, so it never calls ``gdal.UseExceptions()`` for the process: that would
change how every other GDAL user in the process sees errors. Instead, :func:`gdal_exceptions` turns GDAL, OGR and OSR
exceptions on for the duration of a ``with`` block (or a decorated function) and restores the previous state after.
GDAL 3.6 keeps that state in one process-wide flag per module (``gdal.ExceptionMgr`` only exists from 3.7), so the
scopes are reference-counted under a lock: the first scope to enter saves the state, the last to leave restores it,
which keeps worker threads that open files concurrently from switching exceptions off under each other.
Inside a scope GDAL's own error printer is silenced too (a quiet handler pushed for the calling thread): its errors
reach the caller as the exception's message, and nothing from GDAL (``ERROR 1: sqlite3_exec ...`` on a full disk,
``Warning 1: ...``) lands on the user's stderr beside the one line the interfaces print.
"""
from __future__ import annotations

import functools
import os
import threading
from contextlib import contextmanager
from typing import Iterator, Optional, Type

from osgeo import gdal, ogr, osr

from .errors import Gf4calError

_LOCK = threading.Lock()
_DEPTH = 0
_SAVED: tuple = ()


def _modules():
    return gdal, ogr, osr


def _enter() -> None:
    global _DEPTH, _SAVED
    with _LOCK:
        if _DEPTH == 0:
            mods = _modules()
            _SAVED = tuple(bool(m.GetUseExceptions()) for m in mods)
            for m, was in zip(mods, _SAVED):
                if not was:
                    m.UseExceptions()
        _DEPTH += 1


def _exit() -> None:
    global _DEPTH
    with _LOCK:
        _DEPTH -= 1
        if _DEPTH == 0:
            # GDAL 3.6 keeps the modules' error handlers on a stack: undo in the reverse order of _enter.
            for m, was in reversed(list(zip(_modules(), _SAVED))):
                if not was:
                    m.DontUseExceptions()


@contextmanager
def gdal_exceptions() -> Iterator[None]:
    """Raise ``RuntimeError`` from GDAL/OGR/OSR calls inside the block, GDAL's printer silenced; restore the
    previous setting and handler on exit.

    Usable as a decorator too (:func:`with_gdal_exceptions`). Nested and concurrent scopes are safe.
    """
    _enter()
    gdal.PushErrorHandler("CPLQuietErrorHandler")    # per thread; popped in the same thread below
    try:
        yield
    finally:
        gdal.PopErrorHandler()
        _exit()


def with_gdal_exceptions(func):
    """Decorator form of :func:`gdal_exceptions` for a whole function (GDAL exceptions scoped to the call)."""
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with gdal_exceptions():
            return func(*args, **kwargs)
    return wrapper


@contextmanager
def quiet() -> Iterator[None]:
    """Silence GDAL's error handler (nothing printed on stderr) inside the block; errors still raise."""
    gdal.PushErrorHandler("CPLQuietErrorHandler")
    try:
        yield
    finally:
        gdal.PopErrorHandler()


def with_quiet_errors(func):
    """Decorator: GDAL's error printer silenced for the whole call (:func:`quiet`), for writers that check GDAL's
    return codes themselves (a full disk must reach the user as one line, not as ``ERROR 1: sqlite3_exec ...``)."""
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with quiet():
            return func(*args, **kwargs)
    return wrapper


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (GDAL messages can span lines)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def open_raster(path, *, what: str = "raster", error: Type[Gf4calError] = Gf4calError, update: bool = False,
                quiet_errors: bool = True):
    """Open ``path`` with GDAL (exceptions scoped to the call) or raise ``error`` with one line that says what.

    Returns the ``gdal.Dataset`` (never ``None``)."""
    path = os.fspath(path)
    flags = gdal.OF_RASTER | (gdal.OF_UPDATE if update else 0)
    with gdal_exceptions():
        try:
            if quiet_errors:
                with quiet():
                    ds = gdal.OpenEx(path, flags)
            else:
                ds = gdal.OpenEx(path, flags)
        except RuntimeError as exc:
            raise error(f"cannot open {what} {path}: {first_line(exc)}") from None
    if ds is None:
        raise error(f"cannot open {what} {path}: GDAL does not recognise it as a raster")
    return ds


def try_open_raster(path) -> Optional[object]:
    """Open ``path`` quietly as a raster; ``None`` when GDAL cannot (no message, no exception)."""
    with gdal_exceptions():
        try:
            with quiet():
                return gdal.OpenEx(os.fspath(path), gdal.OF_RASTER)
        except RuntimeError:
            return None


def open_vector(path, *, what: str = "vector file", error: Type[Gf4calError] = Gf4calError, update: bool = False):
    """Open ``path`` with OGR (exceptions scoped to the call) or raise ``error`` with one line; the dataset."""
    path = os.fspath(path)
    flags = gdal.OF_VECTOR | (gdal.OF_UPDATE if update else 0)
    with gdal_exceptions():
        try:
            with quiet():
                ds = gdal.OpenEx(path, flags)
        except RuntimeError as exc:
            raise error(f"cannot open {what} {path}: {first_line(exc)}") from None
    if ds is None:
        raise error(f"cannot open {what} {path}: OGR does not recognise it as a vector file")
    return ds
