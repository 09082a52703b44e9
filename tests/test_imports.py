"""The house without loops: no module of kftrack imports, directly or through others, itself.

Every module of the package is found with ``pkgutil.walk_packages`` and its source parsed with
``ast``; every import counts, also one inside a function (a lazy import is still a dependency):
``import kftrack.x``, ``from kftrack.x import y``, ``from .x import y``, ``from . import x``,
``from .. import x`` (relative imports resolved against the module's package). The graph of the
kftrack modules must have no cycle (DESIGN: "no module loops"); a cycle is reported as the chain
of modules that closes it.
"""
from __future__ import annotations

import ast
import importlib.util
import pkgutil
from pathlib import Path

import kftrack


def _modules(root: Path, package: str) -> dict[str, Path]:
    """``{module name: source file}`` of every module of the package under ``root``."""
    out = {package: root / "__init__.py"}
    for info in pkgutil.walk_packages([str(root)], prefix=package + "."):
        rel = info.name.split(".")[1:]
        path = root.joinpath(*rel)
        out[info.name] = path / "__init__.py" if info.ispkg else path.with_suffix(".py")
    return out


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The module ``name`` refers to: itself if it is a module, else its package (``from kftrack.x
    import f`` depends on ``kftrack.x``); None outside the package."""
    while name:
        if name in modules:
            return name
        name = name.rpartition(".")[0]
    return None


def import_graph(root: Path, package: str = "kftrack") -> dict[str, set[str]]:
    """``{module: {kftrack modules it imports}}``, every import statement of its source counted."""
    modules = _modules(root, package)
    graph = {}
    for mod, path in modules.items():
        is_pkg = path.name == "__init__.py"
        base = mod if is_pkg else mod.rpartition(".")[0]  # the package relative imports start from
        deps = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    parts = base.split(".")
                    anchor = ".".join(parts[:len(parts) - (node.level - 1)])
                    src = anchor + ("." + node.module if node.module else "")
                else:
                    src = node.module or ""
                # "from . import x" and "from .pkg import mod" import modules; "from .x import f" a name
                targets = [src] + [f"{src}.{a.name}" for a in node.names]
            else:
                continue
            for t in targets:
                dep = _resolve(t, modules) if t.split(".")[0] == package else None
                # a package that holds the module is imported before it anyway: not an edge
                if dep is not None and dep != mod and not mod.startswith(dep + "."):
                    deps.add(dep)
        graph[mod] = deps
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle ``[a, b, ..., a]`` of the directed graph, or None (depth-first search, three colours)."""
    state, stack = {}, []

    def visit(u):
        state[u] = 1
        stack.append(u)
        for v in sorted(graph.get(u, ())):
            if state.get(v) == 1:
                return stack[stack.index(v):] + [v]
            if v not in state:
                found = visit(v)
                if found:
                    return found
        stack.pop()
        state[u] = 2
        return None

    for u in sorted(graph):
        if u not in state:
            found = visit(u)
            if found:
                return found
    return None


def _root() -> Path:
    return Path(importlib.util.find_spec("kftrack").origin).parent


def test_the_walk_sees_the_package():
    graph = import_graph(_root())
    # the walk finds subpackages and lazy imports: sensors.radar, and kalman -> kernels
    assert "kftrack.sensors.radar" in graph and "kftrack.kalman" in graph
    assert "kftrack.kernels" in graph["kftrack.kalman"]
    assert len(graph) >= 30


def test_find_cycle_reports_a_loop():
    # the detector itself: a loop of three through a lazy edge, and none without it
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert find_cycle(g) == ["a", "b", "c", "a"]
    g["c"] = set()
    assert find_cycle(g) is None


def test_relative_and_lazy_imports_are_edges(tmp_path, monkeypatch):
    # a synthetic package with the import forms the walk must see: a loop only through an
    # import inside a function, a subpackage and a "from .. import x"
    monkeypatch.syspath_prepend(str(tmp_path))  # walk_packages imports subpackages to list them
    pkg = tmp_path / "loopy_pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from .b import f\n")
    (pkg / "b.py").write_text("def f():\n    from .sub import c\n")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "c.py").write_text("from .. import a\n")
    graph = import_graph(pkg, "loopy_pkg")
    cycle = find_cycle(graph)
    assert cycle is not None and set(cycle) == {"loopy_pkg.a", "loopy_pkg.b", "loopy_pkg.sub.c"}
    (pkg / "b.py").write_text("def f():\n    pass\n")  # without the lazy import: no loop
    assert find_cycle(import_graph(pkg, "loopy_pkg")) is None


def test_no_import_cycle():
    cycle = find_cycle(import_graph(_root()))
    assert cycle is None, "kftrack modules import each other round a loop: " + " -> ".join(cycle)


def test_result_types_live_at_the_bottom_and_are_re_exported():
    # the drivers build FilterResult without importing the public filter; the old import paths work
    from kftrack import engines, kalman, kernels, results

    assert kalman.FilterResult is results.FilterResult is engines.FilterResult
    assert kalman.SmootherResult is results.SmootherResult
    assert kalman.Update is kernels.Update
    graph = import_graph(_root())
    assert graph["kftrack.results"] == set() and graph["kftrack.kernels"] == set()
    assert graph["kftrack._validate"] == set()  # validation knows nothing of the filters
