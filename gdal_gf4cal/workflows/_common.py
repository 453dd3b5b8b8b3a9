"""Helpers shared by the file-to-file jobs (DESIGN.md "Workflows"): opening inputs the same way everywhere."""
from __future__ import annotations

import os
import warnings
from contextlib import contextmanager
from typing import Any, Dict, Iterator, List, Optional, Tuple

from ..outputs import check_vector
from ..progress import cancel_check  # noqa: F401  (re-exported: every workflow takes it from here)
from ..scene import Scene, open_input  # noqa: F401  (Scene: the opened input the workflows pass around)


def is_path(x) -> bool:
    """True for a file path (str or path-like), False for in-memory objects (tables, models, numbers)."""
    return isinstance(x, (str, os.PathLike))


def _open_image(path) -> Tuple[Optional[Tuple[int, int]], List[str]]:
    """``((width, height), files)`` if GDAL opens ``path`` as a raster with pixels (``files``: the image and its
    sidecars, all inputs), else ``(None, [path])`` (a standalone RPC file): :class:`~gdal_gf4cal.scene.Scene`'s
    rules (:func:`~gdal_gf4cal.scene.open_input`)."""
    _, size, files = open_input(path)
    return size, files


@contextmanager
def collect_warnings(into: List[str]) -> Iterator[None]:
    """Record Python warnings raised by the engine inside the block as one-line strings in ``into``
    (they reach the user as ``report["warnings"]``: CLI ``warning:`` lines, QGIS ``pushWarning``)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    for w in caught:
        if issubclass(w.category, (DeprecationWarning, PendingDeprecationWarning, ResourceWarning)):
            continue
        text = str(w.message).strip().splitlines()
        if text and text[0] not in into:
            into.append(text[0])


def finish_report(rep: Dict[str, Any], warns: List[str]) -> Dict[str, Any]:
    """Merge ``warns`` into ``rep["warnings"]`` (a list of str, always present), without duplicates."""
    out = list(rep.get("warnings") or [])
    for w in warns:
        if w not in out:
            out.append(w)
    rep["warnings"] = out
    return rep


def declare_report_outputs(outs, *, residuals=None, plot=None, report=None) -> None:
    """Declare the optional outputs every estimating job shares: the residual GeoPackage (checked as a vector
    file), the residual plot and ``report.json`` (:class:`~gdal_gf4cal.outputs.OutputSet`)."""
    if residuals:
        outs.declare("residuals", residuals, check=check_vector())
    if plot:
        outs.declare("plot", plot)
    if report:
        outs.declare("report", report)
