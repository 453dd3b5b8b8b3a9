"""Comparison of recomputed numbers with the frozen JSON (issue 10, item 1)."""
from __future__ import annotations

import json
import math
from typing import Any, List

from .scenes import DATA


def load(name: str):
    with open(DATA / f"{name}.json") as fh:
        return json.load(fh)["values"]


def assert_close(got: Any, want: Any, *, rel: float = 1e-6, abs_: float = 0.0, path: str = "") -> None:
    """Recursive comparison: dict keys and list lengths equal, bools/ints/None exact, floats within
    ``max(rel * |want|, abs_)``, NaN only where NaN was frozen. Reports every mismatch, not just the first."""
    bad: List[str] = []
    _walk(got, want, rel, abs_, path, bad)
    assert not bad, f"{len(bad)} frozen value(s) changed:\n" + "\n".join(bad[:40])


def _walk(got, want, rel, abs_, path, bad):
    if isinstance(want, dict):
        if not isinstance(got, dict) or set(got) != set(want):
            if not isinstance(got, dict):
                bad.append(f"{path}: {type(got).__name__} where a dict was frozen")
            else:
                bad.append(f"{path}: keys missing {sorted(set(want) - set(got))[:20]}, "
                           f"new {sorted(set(got) - set(want))[:20]}")
            return
        for k in want:
            _walk(got[k], want[k], rel, abs_, f"{path}/{k}", bad)
    elif isinstance(want, list):
        if not isinstance(got, list) or len(got) != len(want):
            bad.append(f"{path}: length {len(got) if isinstance(got, list) else type(got)} != {len(want)}")
            return
        for i, (g, w) in enumerate(zip(got, want)):
            _walk(g, w, rel, abs_, f"{path}[{i}]", bad)
    elif isinstance(want, bool) or want is None or isinstance(want, str):
        if got != want:
            bad.append(f"{path}: {got!r} != frozen {want!r}")
    elif isinstance(want, int) and not isinstance(got, float):
        if got != want:
            bad.append(f"{path}: {got!r} != frozen {want!r}")
    else:
        g, w = float(got), float(want)
        if math.isnan(w) or math.isnan(g):
            if not (math.isnan(w) and math.isnan(g)):
                bad.append(f"{path}: {g!r} != frozen {w!r}")
        elif abs(g - w) > max(rel * abs(w), abs_):
            bad.append(f"{path}: {g!r} != frozen {w!r} (diff {g - w:.3g})")
