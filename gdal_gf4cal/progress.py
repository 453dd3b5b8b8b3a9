"""Progress reporting and cancellation for long operations.

A progress callback is any callable ``progress(fraction, message)`` with ``fraction`` in [0, 1]. To cancel,
the callback raises :class:`gdal_gf4cal.errors.CancelledError`; engine functions let it propagate and leave no
partial output behind. The CLI passes :class:`TextProgressBar`; the QGIS provider an adapter over its feedback.
"""
from __future__ import annotations

import sys
from typing import Callable, Optional

ProgressCallback = Callable[[float, str], None]


def report(progress: Optional[ProgressCallback], fraction: float, message: str = "") -> None:
    """Call ``progress`` if given (clamping ``fraction`` to [0, 1])."""
    if progress is not None:
        progress(min(max(float(fraction), 0.0), 1.0), message)


def scaled(progress: Optional[ProgressCallback], start: float, stop: float) -> Optional[ProgressCallback]:
    """A callback mapping [0, 1] of a sub-task onto [start, stop] of ``progress``."""
    if progress is None:
        return None
    return lambda f, m="": progress(start + (stop - start) * min(max(f, 0.0), 1.0), m)


class TextProgressBar:
    """A one-line progress bar on stderr (only drawn when stderr is a terminal unless ``force``)."""

    def __init__(self, width: int = 40, stream=None, force: bool = False):
        self.width = width
        self.stream = stream or sys.stderr
        self.enabled = force or self.stream.isatty()
        self._last = -1

    def __call__(self, fraction: float, message: str = "") -> None:
        if not self.enabled:
            return
        filled = int(round(fraction * self.width))
        pct = int(fraction * 100)
        if pct == self._last and fraction < 1:
            return
        self._last = pct
        bar = "#" * filled + "-" * (self.width - filled)
        self.stream.write(f"\r[{bar}] {pct:3d}% {message[:40]:<40}")
        if fraction >= 1:
            self.stream.write("\n")
        self.stream.flush()
