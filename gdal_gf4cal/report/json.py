"""``report.json``: strict JSON from NumPy scalars/arrays, paths, dataclasses, written atomically.

What the file holds is what was measured (issue 15): a value that could not be computed (``None``, NaN, inf) is
*absent*, not ``null``, and a section without data is omitted (a statistics section of no points, ``"n": 0``;
a section left empty or holding only zero counts such as ``{"n_outliers": 0}``). Readers test ``"check" in rep``,
never ``rep["check"] is None``. Inside arrays (lists) a non-finite number stays ``null`` so that positions hold.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import math
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ._common import PathLike, _cleanup, _temp_path

# ----------------------------------------------------------------------------------------------------------------
# report.json
# ----------------------------------------------------------------------------------------------------------------
_ABSENT = object()   # a value the file leaves out


def _no_data(section: Mapping[str, Any]) -> bool:
    """A section without data: empty, statistics of no points (``n`` = 0), or zero counts only (``n_*`` = 0)."""
    if not section:
        return True
    if isinstance(section.get("n"), int) and not isinstance(section.get("n"), bool) and section["n"] == 0:
        return True
    return all((k == "n" or k.startswith("n_")) and type(v) is int and v == 0 for k, v in section.items())


def _jsonable(obj: Any, *, top: bool = True) -> Any:
    """Convert NumPy scalars/arrays, paths, dataclasses, sets and non-finite floats to plain JSON values; in mappings
    ``None``/NaN values and sections without data are left out (:data:`_ABSENT`), see the module docstring."""
    if isinstance(obj, Mapping):
        out = {}
        for k, v in obj.items():
            v = _jsonable(v, top=False)
            if v is not _ABSENT and v is not None:
                out[str(k)] = v
        return out if top or not _no_data(out) else _ABSENT
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [None if v is _ABSENT else v for v in (_jsonable(v, top=False) for v in obj)]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist(), top=False)
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if obj is None or isinstance(obj, str):
        return obj
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, (_dt.datetime, _dt.date)):
        return obj.isoformat()
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return _jsonable(dataclasses.asdict(obj), top=False)
    if hasattr(obj, "to_dict"):
        return _jsonable(obj.to_dict(), top=False)
    if hasattr(obj, "item") and callable(obj.item):  # other NumPy-like scalars
        return _jsonable(obj.item(), top=False)
    raise TypeError(f"report value of type {type(obj).__name__} is not JSON-serialisable")


def report_text(report: Mapping[str, Any], *, indent: int = 2) -> str:
    """``report`` as the strict JSON text :func:`write_report_json` writes (absent values and sections left out)."""
    return json.dumps(_jsonable(report), indent=indent, allow_nan=False, ensure_ascii=False) + "\n"


def write_report_json(report: Mapping[str, Any], path: PathLike, *, indent: int = 2) -> Path:
    """Write ``report`` as JSON, atomically.

    NumPy scalars and arrays, paths, dataclasses and objects with ``to_dict()`` are converted; values that could
    not be computed (None, NaN, infinities) and sections without data are absent (not ``null``); inside arrays a
    non-finite number is ``null``. The file is strict JSON that any reader accepts.

    Returns
    -------
    pathlib.Path
        The written path.
    """
    path = Path(path)
    text = report_text(report, indent=indent)
    tmp = _temp_path(path)
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    finally:
        _cleanup(tmp)
    return path
