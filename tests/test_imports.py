"""The package's dependencies go one way: no import cycle between its modules, and the
SO(3) maths (`so3jax._so3`) imports nothing from the execution engine."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "so3jax"
#: The execution engine: how a run executes, not what it computes.
ENGINE = {"_engine", "_scalarize", "_frames", "_linear_call", "_updates", "_jax", "_plan"}


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE).with_suffix("")
    parts = [p for p in rel.parts if p != "__init__"]
    return ".".join(parts) if parts else "__init__"


def _imports(path: Path, top_level_only: bool) -> set[str]:
    """The so3jax modules ``path`` imports (relative imports), by module name."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    here = _module_name(path).split(".")
    package = here[:-1] if path.name != "__init__.py" else here
    package = [p for p in package if p != "__init__"]
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    found = set()
    for node in nodes:
        if not isinstance(node, ast.ImportFrom) or node.level == 0:
            continue
        base = package[: len(package) - (node.level - 1)] if node.level > 1 else package
        if node.module:
            found.add(".".join([*base, *node.module.split(".")]))
        else:  # from . import a, b
            found.update(".".join([*base, alias.name]) for alias in node.names)
    return {m for m in found if m}


def _graph(top_level_only: bool) -> dict[str, set[str]]:
    files = sorted(PACKAGE.rglob("*.py"))
    names = {_module_name(f) for f in files}
    graph = {}
    for f in files:
        deps = set()
        for m in _imports(f, top_level_only):
            # `from ._integrators import X` names a package, `from ._so3 import x` a module;
            # `from .x import y` where y is a submodule is kept at its package.
            parent = m.rsplit(".", 1)[0]
            deps.add(m if m in names or parent not in names else parent)
        graph[_module_name(f)] = {d for d in deps if d in names and d != _module_name(f)}
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n):
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if state.get(m) == 1:
                return stack[stack.index(m) :] + [m]
            if m not in state and (found := visit(m)):
                return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state and (found := visit(n)):
            return found
    return None


def test_no_import_cycle():
    graph = _graph(top_level_only=True)
    assert "_so3" in graph and "_engine" in graph  # the graph sees the package
    assert _cycle(graph) is None, _cycle(graph)


def test_cycle_detection_can_fail():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


def test_so3_maths_imports_no_engine_module():
    imported = _imports(PACKAGE / "_so3.py", top_level_only=False)
    assert not imported & {f"{m}" for m in ENGINE}, imported
    assert imported <= {"_types"}, imported
