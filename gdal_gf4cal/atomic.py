"""Atomic file output: write next to the target, then ``os.replace`` (DESIGN.md "Outputs").

A reader never sees a half-written file, and a failure (or a cancel) leaves the previous file, if any, untouched.
"""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from typing import Iterator


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
        if os.path.exists(tmp):
            os.unlink(tmp)
