"""The engine's source as syntax trees, for tests that hold a rule over every module of gdal_gf4cal/ (one
mechanism in one place: GDAL exceptions scoped, GeoTIFF options from ``outputs.gtiff_options``)."""
from __future__ import annotations

import ast
from pathlib import Path
from typing import Iterator, Tuple

import gdal_gf4cal

PKG = Path(gdal_gf4cal.__file__).parent


def engine_nodes(skip: Tuple[str, ...] = ()) -> Iterator[Tuple[str, ast.AST]]:
    """``("module.py:line", node)`` for every syntax node of every engine module but the files named in ``skip``."""
    for path in sorted(PKG.rglob("*.py")):
        if path.name in skip:
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            yield f"{path.relative_to(PKG)}:{getattr(node, 'lineno', 0)}", node
