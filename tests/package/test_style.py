"""House style the review enforces (issue 21), read from the source (AST, nothing imported): no private name imported
across packages, imports at module top unless an optional dependency needs otherwise, functions of at most 80
lines but for a few named exceptions, each with its reason."""
from __future__ import annotations

import ast
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[2]
TREES = ("gdal_gf4cal", "processing_provider")

#: Private names still imported across packages, each waiting for its owner's restructuring (issue 21). Empty it.
PRIVATE_PENDING: dict = {}


def _files():
    for tree in TREES:
        yield from sorted((ROOT / tree).rglob("*.py"))


def _imported_from(path: pathlib.Path, node: ast.ImportFrom) -> pathlib.Path:
    """The folder (package) that owns the module ``node`` imports from."""
    if node.level:
        base = path.parent
        for _ in range(node.level - 1):
            base = base.parent
    else:
        base = ROOT
    target = base.joinpath(*(node.module.split(".") if node.module else []))
    return target if target.is_dir() else target.parent


def private_imports_across_packages():
    out = {}
    for path in _files():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and _imported_from(path, node) != path.parent:
                for a in node.names:
                    if a.name.startswith("_") and not a.name.startswith("__"):
                        out[(str(path.relative_to(ROOT)), a.name)] = node.lineno
    return out


def test_no_private_name_imported_across_packages():
    found = private_imports_across_packages()
    new = sorted(set(found) - set(PRIVATE_PENDING))
    assert not new, f"private names imported across packages (make them public where they live): {new}"


#: Functions over 80 lines that stay, at most 10, each with the reason (issue 21).
LONG_ALLOWED = {
    ("gdal_gf4cal/estimation/schur.py", "solve_with_points"):
        "the point elimination with its three reduced-system paths (dense, sparse, indexed) side by side",
}
#: Functions over 80 lines on this branch, each waiting for its owner's helper (issue 21); the lead empties this at
#: merge time, moving at most 10 into LONG_ALLOWED with their reasons.
LONG_PENDING: dict = {}
MAX_LINES = 80


def long_functions():
    out = {}
    for path in _files():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_LINES:
                    out[(str(path.relative_to(ROOT)), node.name)] = n
    return out


def test_functions_of_at_most_80_lines_but_for_10_named_exceptions():
    assert len(LONG_ALLOWED) <= 10
    unexplained = {k: n for k, n in long_functions().items() if k not in LONG_ALLOWED and k not in LONG_PENDING}
    assert not unexplained, f"functions over {MAX_LINES} lines (split them): {unexplained}"


#: Modules whose imports are all at module top (issue 21; an optional dependency may still be imported where used).
TOP_IMPORTS = ["observations.py", "gcp.py", "gcp_formats.py", "outputs.py", "atomic.py", "crop.py", "scene.py",
               "dem.py", "_gdal.py", "rpc.py", "geoid.py", "errors.py", "report/gpkg.py", "report/gpkg_bulk.py",
               "report/json.py", "report/_common.py", "workflows/_common.py", "rpc_io/__init__.py",
               "rpc_io/canonical.py", "rpc_io/text_formats.py", "rpc_io/xml_formats.py", "rpc_io/readers.py",
               "rpc_io/writers.py"]
OPTIONAL = {"qgis", "PyQt5", "matplotlib", "dask", "distributed", "skimage", "tqdm"}


def test_imports_at_module_top():
    late = []
    for name in TOP_IMPORTS:
        path = ROOT / "gdal_gf4cal" / name
        for fn in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(fn):
                if isinstance(node, (ast.Import, ast.ImportFrom)):
                    top = (node.names[0].name if isinstance(node, ast.Import) else node.module or "").split(".")[0]
                    if top not in OPTIONAL:
                        late.append(f"{name}:{node.lineno} {ast.unparse(node)}")
    assert not late, late
