"""Atomic file output: kept as a re-export of :mod:`gdal_gf4cal.outputs` (the one output policy, DESIGN.md
"Outputs"), so ``from gdal_gf4cal.atomic import atomic_output`` keeps working."""
from __future__ import annotations

from .outputs import atomic_output, fix_mode

__all__ = ["atomic_output", "fix_mode"]
