"""Layering: no project package (or module) imports one that imports it back, directly or through others.

The import graphs are read from the source (``ast``), every import counted wherever it stands (module
level, inside a function, under ``TYPE_CHECKING``), so a cycle cannot hide in a function body.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.conftest import REPO

PACKAGES = ("messages", "gp_model", "fe_node", "controller_node", "gp_trainer")


def imported_modules(tree: ast.AST) -> set[str]:
    """Absolute module names a parsed module imports (relative imports stay inside the package)."""
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
    return names


def package_graph(root: Path, packages: tuple[str, ...] = PACKAGES) -> dict[str, dict[str, str]]:
    """``{package: {imported package: first file importing it}}`` over the project packages under ``root``."""
    graph: dict[str, dict[str, str]] = {p: {} for p in packages if (root / p).is_dir()}
    for package, edges in graph.items():
        for path in sorted((root / package).rglob("*.py")):
            for module in imported_modules(ast.parse(path.read_text(encoding="utf-8"))):
                top = module.split(".")[0]
                if top in graph and top != package:
                    edges.setdefault(top, str(path.relative_to(root)))
    return graph


def module_name(root: Path, path: Path) -> str:
    """Dotted module name of ``path`` under ``root`` (a package's ``__init__`` is the package)."""
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def module_graph(root: Path, packages: tuple[str, ...] = PACKAGES) -> dict[str, dict[str, str]]:
    """``{module: {imported project module: importing module}}`` over every module of ``packages``;
    ``from package import name`` counts for the module ``package.name`` where that is one."""
    paths = {module_name(root, f): f for p in packages for f in sorted((root / p).rglob("*.py"))}
    graph: dict[str, dict[str, str]] = {m: {} for m in paths}
    for module, path in paths.items():
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[:len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                targets = [base, *(f"{base}.{alias.name}" for alias in node.names)]
            else:
                continue
            for target in targets:
                if target in graph and target != module:
                    graph[module].setdefault(target, module)
    return graph


def find_cycle(graph: dict[str, dict[str, str]]) -> list[str] | None:
    """One cycle of package names (first repeated at the end), or None."""
    state: dict[str, str] = {}

    def visit(node: str, path: list[str]) -> list[str] | None:
        state[node] = "open"
        for nxt in graph[node]:
            if state.get(nxt) == "open":
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (cycle := visit(nxt, path + [nxt])):
                return cycle
        state[node] = "done"
        return None

    for start in graph:
        if start not in state and (cycle := visit(start, [start])):
            return cycle
    return None


def test_no_package_imports_a_package_that_imports_it_back():
    graph = package_graph(REPO)
    cycle = find_cycle(graph)
    where = cycle and [f"{a} -> {b} ({graph[a][b]})" for a, b in zip(cycle, cycle[1:])]
    assert cycle is None, f"import cycle between packages: {'; '.join(where)}"


def test_no_module_imports_a_module_that_imports_it_back():
    cycle = find_cycle(module_graph(REPO))
    assert cycle is None, f"import cycle between modules: {' -> '.join(cycle)}"


@pytest.mark.parametrize(("edges", "cyclic"), [
    ({"a": {"b": "a/x.py"}, "b": {"c": "b/y.py"}, "c": {"a": "c/z.py"}}, True),
    ({"a": {"b": "a/x.py"}, "b": {"c": "b/y.py"}, "c": {}}, False),
])
def test_find_cycle_sees_an_indirect_cycle(edges, cyclic):
    assert (find_cycle(edges) is not None) == cyclic


def test_a_function_level_import_counts(tmp_path):
    for package, body in (("low", "def f():\n    from high import g\n"), ("high", "from low import f\n")):
        (tmp_path / package).mkdir()
        (tmp_path / package / "__init__.py").write_text(body)
    assert find_cycle(package_graph(tmp_path, ("low", "high"))) == ["low", "high", "low"]


def test_a_module_cycle_inside_a_package_counts(tmp_path):
    (tmp_path / "pkg").mkdir()
    for name, body in (("__init__", ""), ("a", "def f():\n    from pkg.b import g\n"), ("b", "from . import a\n")):
        (tmp_path / "pkg" / f"{name}.py").write_text(body)
    assert find_cycle(module_graph(tmp_path, ("pkg",))) in (["pkg.a", "pkg.b", "pkg.a"], ["pkg.b", "pkg.a", "pkg.b"])
