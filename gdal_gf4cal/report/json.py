"""``report.json``: strict JSON from NumPy scalars/arrays, paths, dataclasses (NaN -> null), written atomically."""
from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import math
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ._common import PathLike, _temp_path, _cleanup


# ----------------------------------------------------------------------------------------------------------------
# report.json
# ----------------------------------------------------------------------------------------------------------------
def _jsonable(obj: Any) -> Any:
    """Convert NumPy scalars/arrays, paths, dataclasses, sets and non-finite floats to plain JSON values."""
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
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
        return _jsonable(dataclasses.asdict(obj))
    if hasattr(obj, "to_dict"):
        return _jsonable(obj.to_dict())
    if hasattr(obj, "item") and callable(obj.item):  # other NumPy-like scalars
        return _jsonable(obj.item())
    raise TypeError(f"report value of type {type(obj).__name__} is not JSON-serialisable")


def write_report_json(report: Mapping[str, Any], path: PathLike, *, indent: int = 2) -> Path:
    """Write ``report`` as JSON, atomically.

    NumPy scalars and arrays, paths, dataclasses and objects with ``to_dict()`` are converted; NaN and infinities
    become ``null`` so the file is strict JSON that any reader accepts.

    Returns
    -------
    pathlib.Path
        The written path.
    """
    path = Path(path)
    text = json.dumps(_jsonable(report), indent=indent, allow_nan=False, ensure_ascii=False) + "\n"
    tmp = _temp_path(path)
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    finally:
        _cleanup(tmp)
    return path
