"""House style the review enforces (issue 21), read from the source (AST, nothing imported): no private name imported
across packages, imports at module top unless an optional dependency needs otherwise, functions of at most 80
lines but for a few named exceptions, each with its reason."""
from __future__ import annotations

import ast
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[2]
TREES = ("gdal_gf4cal", "processing_provider")

#: Private names still imported across packages, each waiting for its owner's restructuring (issue 21). Empty it.
PRIVATE_PENDING = {
    ("gdal_gf4cal/workflows/panms.py", "_LIN_ORDER"): "panms -> panms/ package (lookpan) makes it public",
    ("gdal_gf4cal/workflows/panms.py", "_linear_design"): "panms -> panms/ package (lookpan) makes it public",
    ("gdal_gf4cal/workflows/refine.py", "_axis_stats"): "compensation -> compensation/ package (driver)",
}


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
LONG_ALLOWED: dict = {}
#: Functions over 80 lines on this branch, each waiting for its owner's helper (issue 21); the lead empties this at
#: merge time, moving at most 10 into LONG_ALLOWED with their reasons.
LONG_PENDING = {
    ("gdal_gf4cal/lookangle.py", "calibrate_lookangle"): "lookpan",   # 208 lines
    ("gdal_gf4cal/experiments/jl1.py", "run"): "shorten",   # 185 lines
    ("gdal_gf4cal/workflows/block.py", "block_adjust"): "block",   # 174 lines
    ("gdal_gf4cal/experiments/gf4.py", "run"): "shorten",   # 167 lines
    ("gdal_gf4cal/simulate/scene.py", "write_scene"): "shorten",   # 163 lines
    ("gdal_gf4cal/matching/collect.py", "_match_windows"): "shorten",   # 162 lines
    ("gdal_gf4cal/compensation.py", "fit_compensation"): "driver",   # 157 lines
    ("gdal_gf4cal/workflows/panms.py", "register_pan_ms"): "lookpan",   # 146 lines
    ("gdal_gf4cal/workflows/refine.py", "refine_rpc"): "shorten",   # 144 lines
    ("gdal_gf4cal/rpc_fit.py", "fit_rpc"): "shorten",   # 139 lines
    ("gdal_gf4cal/block.py", "_adjust"): "block",   # 126 lines
    ("gdal_gf4cal/estimation/robust.py", "high_breakdown_start"): "driver",   # 125 lines
    ("gdal_gf4cal/simulate/jl1.py", "build_jl1"): "shorten",   # 124 lines
    ("gdal_gf4cal/rpc_fit.py", "fit_rpc_from_model"): "shorten",   # 119 lines
    ("gdal_gf4cal/simulate/jl1.py", "block_observations"): "shorten",   # 118 lines
    ("gdal_gf4cal/report/plot.py", "plot_residuals"): "gis",   # 117 lines
    ("gdal_gf4cal/panms.py", "estimate"): "lookpan",   # 114 lines
    ("gdal_gf4cal/batch.py", "run_batch"): "shorten",   # 109 lines
    ("gdal_gf4cal/workflows/assess.py", "assess_accuracy"): "shorten",   # 104 lines
    ("gdal_gf4cal/intersection.py", "intersect"): "driver",   # 102 lines
    ("gdal_gf4cal/estimation/schur.py", "solve_with_points"): "driver",   # 95 lines
    ("gdal_gf4cal/describe.py", "describe_rpc"): "shorten",   # 95 lines
    ("gdal_gf4cal/workflows/calibrate.py", "calibrate_lookangle_files"): "lookpan",   # 94 lines
    ("gdal_gf4cal/simulate/sensors.py", "make_scene"): "shorten",   # 93 lines
    ("gdal_gf4cal/simulate/gf7.py", "build_gf7"): "shorten",   # 93 lines
    ("gdal_gf4cal/experiments/zy3.py", "run"): "shorten",   # 90 lines
    ("gdal_gf4cal/model_selection.py", "select_model"): "driver",   # 89 lines
    ("gdal_gf4cal/experiments/hj1.py", "run"): "shorten",   # 89 lines
    ("gdal_gf4cal/simulate/render.py", "render_image"): "shorten",   # 88 lines
    ("gdal_gf4cal/matching/raw.py", "match_raw"): "shorten",   # 82 lines
    ("gdal_gf4cal/executors.py", "get_executor"): "shorten",   # 82 lines
    ("processing_provider/base.py", "read_gcps"): "gis",   # 85 lines
}
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
