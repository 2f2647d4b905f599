"""The import graph of ``panogs_core``, read from the source (no imports run): no cycles, no private imports.

Every ``import`` counts, wherever it is: at module level, inside a function (the lazy torch / open3d imports)
and under ``if TYPE_CHECKING:``. A cycle through any of them means two modules each need the other, so the
shared part belongs in a third; a ``_private`` name used from another module is not private.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / "panogs_core"


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def _absolute(node: ast.ImportFrom, importer: str, is_package: bool) -> str:
    if node.level == 0:
        return node.module or ""
    base = importer.split(".") if is_package else importer.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def import_graph() -> tuple[dict[str, set[str]], list[str]]:
    """Edges importer -> imported module within the package, and every import of another module's private name."""
    modules = _modules()
    edges: dict[str, set[str]] = {name: set() for name in modules}
    private: list[str] = []
    for name, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                edges[name].update(a.name for a in node.names if a.name in modules)
            elif isinstance(node, ast.ImportFrom):
                source = _absolute(node, name, path.name == "__init__.py")
                if source not in modules:
                    continue
                for alias in node.names:
                    submodule = f"{source}.{alias.name}"
                    target = submodule if submodule in modules else source
                    edges[name].add(target)
                    if target == source and _is_private(alias.name) and source != name:
                        private.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno}: {source}.{alias.name}")
    return edges, private


def find_cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """One cycle (as a closed path) per strongly connected component that has one (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(edges.get(node, ())):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1 or node in edges.get(node, ()):
                cycles.append(_closed_path(component, edges))

    for node in sorted(edges):
        if node not in index:
            visit(node)
    return cycles


def _closed_path(component: list[str], edges: dict[str, set[str]]) -> list[str]:
    """A path that starts and ends at the component's first module, inside the component."""
    members = set(component)
    start = min(component)
    path, seen = [start], {start}
    while True:
        options = sorted(edges[path[-1]] & members)
        if (start in options and len(path) > 1) or options == [start]:
            return [*path, start]
        fresh = [m for m in options if m not in seen]
        nxt = fresh[0] if fresh else start
        if nxt == start:
            return [*path, start]
        path.append(nxt)
        seen.add(nxt)


def test_the_package_has_no_import_cycle() -> None:
    edges, _ = import_graph()
    cycles = find_cycles(edges)
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_no_module_imports_another_modules_private_names() -> None:
    _, private = import_graph()
    assert not private, "private names imported from another module:\n" + "\n".join(private)


def test_the_graph_reader_sees_real_edges_and_would_see_a_cycle() -> None:
    edges, _ = import_graph()
    stages = "panogs_core.stages"
    assert f"{stages}.neighbors" in edges[f"{stages}.superprimitives"]
    assert f"{stages}.language_field.triplane" in edges[f"{stages}.language_field"]  # a lazy import inside a function
    assert f"{stages}.masks" in edges[f"{stages}.affinity"]
    looped = {**edges, f"{stages}.masks": edges[f"{stages}.masks"] | {f"{stages}.affinity"}}
    assert [f"{stages}.affinity", f"{stages}.masks", f"{stages}.affinity"] in find_cycles(looped)


@pytest.mark.parametrize(
    ("source", "expected"),
    [("from ._hidden import x", "panogs_core.synthetic._hidden"), ("from .. import errors", "panogs_core")],
)
def test_relative_imports_resolve_against_the_importer(source: str, expected: str) -> None:
    node = ast.parse(source).body[0]
    assert isinstance(node, ast.ImportFrom)
    assert _absolute(node, "panogs_core.synthetic.scene", is_package=False) == expected
