"""No import cycle inside gdal_gf4cal/ (issue 10, Build item 1).

Every module is parsed (AST, nothing imported): module-level and function-level imports, relative and absolute,
become edges of a graph; Tarjan's algorithm finds its strongly connected components; any component with more
than one module is a cycle, listed with one concrete path through it. Only the named module is an edge target
(``from .a import b`` -> ``a.b`` if ``a/b.py`` exists, else ``a``); the implicit import of parent packages is not,
or every package ``__init__`` that re-exports its modules would be a cycle.
"""
from __future__ import annotations

import ast
import pathlib

import pytest

PACKAGE = "gdal_gf4cal"
ROOT = pathlib.Path(__file__).resolve().parents[2] / PACKAGE



def _modules(root: pathlib.Path = ROOT) -> dict:
    """Dotted module name -> path, for every .py file of the package."""
    mods = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mods[".".join(parts)] = path
    return mods


def _resolve(name: str, modules: dict):
    """The longest prefix of ``name`` that is a module of the package (None if outside it)."""
    parts = name.split(".")
    while parts:
        cand = ".".join(parts)
        if cand in modules:
            return cand
        parts.pop()
    return None


def import_graph(modules: dict) -> dict:
    """Module -> set of package modules it imports anywhere in its source (module or function level)."""
    graph = {m: set() for m in modules}
    for mod, path in modules.items():
        is_pkg = path.name == "__init__.py"
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                    base = base[:len(base) - (node.level - 1)] if node.level > 1 else base
                    prefix = ".".join(base + ([node.module] if node.module else []))
                else:
                    prefix = node.module or ""
                for a in node.names:   # `from pkg import submodule` imports the submodule
                    full = f"{prefix}.{a.name}"
                    targets.append(full if full in modules else prefix)
            for t in targets:
                if t.split(".")[0] != PACKAGE:
                    continue
                dst = _resolve(t, modules)
                if dst is not None and dst != mod:
                    graph[mod].add(dst)
    return graph


def strongly_connected(graph: dict) -> list:
    """Tarjan's algorithm (iterative): the strongly connected components with more than one node."""
    index, low, on_stack, stack, out = {}, {}, set(), [], []
    counter = [0]
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter[0]
                    counter[0] += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == node:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def _a_cycle(graph: dict, comp: list) -> list:
    """One concrete cycle through a component (for the failure message): BFS back to its first module."""
    members = set(comp)
    start = comp[0]
    prev = {start: None}
    queue = [start]
    while queue:
        node = queue.pop(0)
        for nxt in sorted(graph[node] & members):
            if nxt == start:
                path = [node]
                while prev[path[-1]] is not None:
                    path.append(prev[path[-1]])
                return list(reversed(path)) + [start]
            if nxt not in prev:
                prev[nxt] = node
                queue.append(nxt)
    return comp


def test_no_import_cycles():
    graph = import_graph(_modules())
    assert f"{PACKAGE}.gcp" in graph and f"{PACKAGE}.gcp_formats" in graph[f"{PACKAGE}.gcp"]
    cycles = [" -> ".join(_a_cycle(graph, comp)) for comp in strongly_connected(graph)]
    assert not cycles, "import cycles in gdal_gf4cal/:\n" + "\n".join(cycles)


def test_gcp_modules_layered():
    """observations <- gcp_formats <- gcp: the schema at the bottom, the dispatch on top (issue 10's cycle)."""
    graph = import_graph(_modules())
    obs, fmt, gcp = (f"{PACKAGE}.{m}" for m in ("observations", "gcp_formats", "gcp"))
    assert fmt not in graph[obs] and gcp not in graph[obs]
    assert gcp not in graph[fmt] and obs in graph[fmt]
    assert {obs, fmt} <= graph[gcp]


def _write_pkg(tmp_path, files: dict) -> pathlib.Path:
    root = tmp_path / PACKAGE
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return root


@pytest.mark.parametrize("files, expected", [
    # module-level relative cycle
    ({"__init__.py": "", "a.py": "from .b import x\n", "b.py": "from .a import y\n"},
     [[f"{PACKAGE}.a", f"{PACKAGE}.b"]]),
    # function-level absolute import closes a three-module cycle through a subpackage
    ({"__init__.py": "", "a.py": "def f():\n    import gdal_gf4cal.sub.c\n", "sub/__init__.py": "",
      "sub/c.py": "from ..b import z\n", "b.py": "from . import a\n"},
     [[f"{PACKAGE}.a", f"{PACKAGE}.b", f"{PACKAGE}.sub.c"]]),
    # a package __init__ re-exporting its modules is not a cycle; neither is an outside import
    ({"__init__.py": "from .a import f\nimport numpy\n", "a.py": "import os\nfrom . import b\n", "b.py": ""}, []),
])
def test_detector_on_synthetic_packages(tmp_path, files, expected):
    graph = import_graph(_modules(_write_pkg(tmp_path, files)))
    assert strongly_connected(graph) == expected
