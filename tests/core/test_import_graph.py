"""The import graph of ``panogs_core``, read from the source (no imports run): no cycles, no private imports; and
the layer rules of the packages: the core imports neither the service nor the worker nor any web, queue or
database package, and the service never imports the worker.

Every ``import`` counts, wherever it is: at module level, inside a function (the lazy torch / open3d imports)
and under ``if TYPE_CHECKING:``. A cycle through any of them means two modules each need the other, so the
shared part belongs in a third; a ``_private`` name used from another module is not private. The layer rules
also count ``importlib.import_module("...")`` and ``__import__("...")`` with a literal name.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator, Mapping
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "panogs_core"
WEB_QUEUE_DATABASE = (
    "fastapi", "starlette", "uvicorn", "pydantic", "pydantic_settings", "sqlalchemy", "alembic", "celery", "redis",
    "psycopg", "kombu", "boto3", "botocore",
)  # fmt: skip
# Top-level package -> the top-level modules none of its modules may import.
LAYER_RULES: dict[str, tuple[str, ...]] = {
    "panogs_core": ("service", "worker", *WEB_QUEUE_DATABASE),
    "service": ("worker",),
}


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


def package_sources(package: str) -> dict[str, str]:
    """Source text by module name for every module of a top-level package of the repository."""
    root = REPO / package
    sources = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(REPO).with_suffix("").parts
        sources[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path.read_text(encoding="utf-8")
    return sources


def absolute_imports(source: str) -> Iterator[tuple[int, str]]:
    """(line, module) of every absolute import of ``source``, at any depth, and of every ``import_module`` or
    ``__import__`` call with a literal name. Relative imports stay inside their own package, so no layer rule
    concerns them."""
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            yield from ((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.lineno, node.module
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            called = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            if called in ("import_module", "__import__") and isinstance(node.args[0].value, str):
                yield node.lineno, node.args[0].value


def broken_layer_rules(sources: Mapping[str, str], rules: Mapping[str, tuple[str, ...]] = LAYER_RULES) -> list[str]:
    """``module:line imports name`` for every import that the layer rule of the module's package forbids."""
    broken = []
    for module, source in sources.items():
        forbidden = rules.get(module.partition(".")[0], ())
        for line, name in absolute_imports(source):
            if name.partition(".")[0] in forbidden:
                broken.append(f"{module}:{line} imports {name}")
    return broken


@pytest.mark.parametrize("package", sorted(LAYER_RULES))
def test_each_package_keeps_its_layer_rule(package: str) -> None:
    sources = package_sources(package)
    assert len(sources) > 10, f"the checker found no modules of {package}"
    broken = broken_layer_rules(sources)
    assert not broken, f"{package} may not import {', '.join(LAYER_RULES[package])}:\n" + "\n".join(broken)


PLANTED = {
    "at module level": "import {name}\n",
    "inside a function": "def f():\n    from {name}.sub import thing\n    return thing\n",
    "under TYPE_CHECKING": "from typing import TYPE_CHECKING\n\nif TYPE_CHECKING:\n    import {name}.x as y\n",
    "by import_module": "import importlib\n\n\ndef g():\n    return importlib.import_module('{name}.cli')\n",
    "by __import__": "def h():\n    return __import__('{name}')\n",
}
RULE_PAIRS = [(package, name) for package, names in LAYER_RULES.items() for name in names]


@pytest.mark.parametrize(("package", "name"), RULE_PAIRS)
@pytest.mark.parametrize("how", sorted(PLANTED))
def test_every_layer_rule_fails_on_a_planted_violation(package: str, name: str, how: str) -> None:
    (broken,) = broken_layer_rules({f"{package}.planted": PLANTED[how].format(name=name)})
    assert broken.startswith(f"{package}.planted:")
    assert broken.split(" imports ")[1].partition(".")[0] == name


def test_the_layer_rules_leave_allowed_imports_alone() -> None:
    allowed = {"worker.planted": "import service.db\nimport celery\n", "panogs_core.planted": "import numpy\n"}
    relative = {"panogs_core.io.planted": "from ..pipeline import run\n"}
    assert broken_layer_rules({**allowed, **relative}) == []


@pytest.mark.parametrize(
    ("source", "expected"),
    [("from ._hidden import x", "panogs_core.synthetic._hidden"), ("from .. import errors", "panogs_core")],
)
def test_relative_imports_resolve_against_the_importer(source: str, expected: str) -> None:
    node = ast.parse(source).body[0]
    assert isinstance(node, ast.ImportFrom)
    assert _absolute(node, "panogs_core.synthetic.scene", is_package=False) == expected
