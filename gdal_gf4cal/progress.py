"""Progress reporting and cancellation for long operations.

A progress callback is any callable ``progress(fraction, message)`` with ``fraction`` in [0, 1]. To cancel,
the callback raises :class:`gdal_gf4cal.errors.CancelledError`; engine functions let it propagate and leave no
partial output behind. The CLI passes :class:`TextProgressBar`; the QGIS provider an adapter over its feedback.
"""
from __future__ import annotations

import logging
import sys
from typing import Callable, Optional

log = logging.getLogger(__name__)

ProgressCallback = Callable[[float, str], None]


def cancel_check(progress):
    """A callable for :class:`~gdal_gf4cal.outputs.OutputSet` ``cancelled=``: asks ``progress`` (QGIS feedback
    adapters expose ``is_cancelled()`` / ``isCanceled()``)."""
    for name in ("is_cancelled", "isCanceled"):
        f = getattr(progress, name, None)
        if callable(f):
            return f
    return None


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
    """CLI progress: a tqdm bar with ETA on stderr when it is a terminal (or ``force``); otherwise quiet, with a
    log line (logger ``gdal_gf4cal.progress``, INFO) at every quarter and at each new stage message."""

    def __init__(self, width: int = 40, stream=None, force: bool = False):
        self.width = width
        self.stream = stream or sys.stderr
        self.enabled = force or (hasattr(self.stream, "isatty") and self.stream.isatty())
        self._last = -1
        self._bar = None
        self._message = None

    def _make_bar(self):
        try:
            from tqdm import tqdm
        except ImportError:      # pragma: no cover - python3-tqdm is a dependency (Makefile APT_PACKAGES)
            return None
        return tqdm(total=100, file=self.stream, ncols=self.width + 60, leave=True, dynamic_ncols=False,
                    bar_format="{percentage:3.0f}%|{bar}| [{elapsed}<{remaining}] {desc}")

    def __call__(self, fraction: float, message: str = "") -> None:
        pct = int(fraction * 100)
        if not self.enabled:
            if (pct // 25 != self._last // 25 or message != self._message) and pct != self._last:
                log.info("%3d%% %s", pct, message)
            self._last, self._message = pct, message
            return
        if self._bar is None:
            self._bar = self._make_bar()
            if self._bar is None:
                return
        if pct != self._last:
            self._bar.update(max(pct - self._bar.n, 0))
            self._last = pct
        if message != self._message:
            self._bar.set_description_str(message[:40], refresh=True)
            self._message = message
        if fraction >= 1:
            self._bar.close()
            self._bar = None
