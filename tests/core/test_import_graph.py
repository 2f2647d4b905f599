"""The import graph of ``panogs_core``, read from the source (no imports run): no cycles, no private imports, no
import from a floor above; no cycle in ``service`` and ``worker``; and the layer rules of the packages: each
imports only the packages of this repository below it (the worker the service and the core, the service the
core), and the core no web, queue or database package.

The declarations here (``PACKAGES``, ``LAYER_RULES``, ``FLOORS``) are the layer sketch at the top of
docs/architecture.md: ``tools/layer_sketch.py --write`` draws it from them, and a test fails when it is stale.

Every ``import`` counts, wherever it is: at module level, inside a function (the lazy torch / open3d imports)
and under ``if TYPE_CHECKING:``. A cycle through any of them means two modules each need the other, so the
shared part belongs in a third; a ``_private`` name used from another module is not private. The layer rules
also count ``importlib.import_module("...")`` and ``__import__("...")`` with a literal name.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import NamedTuple

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "panogs_core"
WEB_QUEUE_DATABASE = (
    "fastapi", "starlette", "uvicorn", "pydantic", "pydantic_settings", "sqlalchemy", "alembic", "celery", "redis",
    "psycopg", "kombu", "boto3", "botocore",
)  # fmt: skip


class Layer(NamedTuple):
    """A package of this repository (or a floor of the core): what it holds, and what of the repository it may
    import (for a floor: its members, the top-level modules and subpackages of ``panogs_core`` on it)."""

    name: str
    role: str
    members: tuple[str, ...]


# The repository's packages, top first; each may import the packages listed (and no other of the three).
PACKAGES: tuple[Layer, ...] = (
    Layer("worker", "Celery app, job and tile tasks", ("service", "panogs_core")),
    Layer("service", "FastAPI, SQLAlchemy, settings, storage (never torch)", ("panogs_core",)),
    Layer("panogs_core", "the algorithm library (no env vars, no global config)", ()),
)
# Top-level package -> the top-level modules none of its modules may import: the repository's packages it may not
# import (``PACKAGES``), and for the core every web, queue and database package.
LAYER_RULES: dict[str, tuple[str, ...]] = {
    "panogs_core": ("service", "worker", *WEB_QUEUE_DATABASE),
    "service": ("worker",),
}
# The core's floors, bottom first: a module imports modules of its own floor and of the floors below, never of one
# above (a type two floors share lives on the lower one). Members are the names after ``panogs_core.``; the
# package's own ``__init__`` is ``panogs_core``.
FLOORS: tuple[Layer, ...] = (
    Layer(
        "base",
        "value types, errors, progress, threads, the heap, colours, point graphs and normals, bounded JSON, stage "
        "snapshots",
        (
            "panogs_core",
            "errors",
            "types",
            "progress",
            "threads",
            "heap",
            "palette",
            "point_graphs",
            "point_normals",
            "bounded_json",
            "snapshots",
        ),
    ),
    Layer("language", "label sets, text encoders, text queries over instances", ("language",)),
    Layer("io", "bundles, run folders, file formats, importers; metrics", ("io", "evaluation")),
    Layer(
        "stages", "the method's stages, the Gaussian scene, the synthetic rooms", ("stages", "gaussians", "synthetic")
    ),
    Layer("pipeline", "a run: the stage table, checkpoints, report.json", ("pipeline",)),
    Layer("tiling", "a building-scale run as tiles", ("tiling",)),
    Layer("cli", "the panogs command", ("cli",)),
)
# Import cycles in service/ and worker/ that are known and being removed (each named, with the change that removes
# it); the check allows exactly these, and fails once one is gone so that its entry goes too.


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules(packages: tuple[Path, ...] = (PACKAGE,)) -> dict[str, Path]:
    return {_module_name(path): path for package in packages for path in sorted(package.rglob("*.py"))}


def _absolute(node: ast.ImportFrom, importer: str, is_package: bool) -> str:
    if node.level == 0:
        return node.module or ""
    base = importer.split(".") if is_package else importer.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def import_graph(packages: tuple[Path, ...] = (PACKAGE,)) -> tuple[dict[str, set[str]], list[str]]:
    """Edges importer -> imported module within ``packages``, and every import of another module's private name."""
    modules = _modules(packages)
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


def floor_of(module: str) -> int | None:
    """The floor (0 = the bottom) of a module of ``panogs_core``; None for a module no floor places."""
    parts = module.split(".")
    member = parts[1] if len(parts) > 1 else parts[0]
    return next((i for i, floor in enumerate(FLOORS) if member in floor.members), None)


def upward_imports(edges: Mapping[str, set[str]]) -> list[str]:
    """``importer -> imported (floor a < floor b)`` for every import from a floor above the importer's."""
    upward = []
    for importer, imported in sorted(edges.items()):
        for target in sorted(imported):
            low, high = floor_of(importer), floor_of(target)
            if low is not None and high is not None and high > low:
                upward.append(f"{importer} ({FLOORS[low].name}) -> {target} ({FLOORS[high].name})")
    return upward


def test_every_module_of_the_core_stands_on_a_floor() -> None:
    edges, _ = import_graph()
    unplaced = sorted(m for m in edges if floor_of(m) is None)
    assert not unplaced, f"modules on no floor (place their package in FLOORS): {unplaced}"
    members = [m for floor in FLOORS for m in floor.members]
    assert len(members) == len(set(members)), "a name stands on two floors"


def test_no_module_of_the_core_imports_from_a_floor_above() -> None:
    edges, _ = import_graph()
    upward = upward_imports(edges)
    assert not upward, "imports from a floor above (move the shared part down):\n" + "\n".join(upward)


@pytest.mark.parametrize(
    ("importer", "imported", "upward"),
    [
        ("panogs_core.io.run_folder", "panogs_core.stages.labeling", True),
        ("panogs_core.language.label_sets", "panogs_core.io.bounded_json", True),
        ("panogs_core.gaussians.fit", "panogs_core.pipeline.snapshots", True),
        ("panogs_core.types", "panogs_core.cli", True),
        ("panogs_core.stages.export", "panogs_core.gaussians.ply", False),  # one floor, sideways
        ("panogs_core.tiling.runner", "panogs_core.types", False),
    ],
)
def test_the_floor_rule_fails_on_a_planted_upward_import(importer: str, imported: str, upward: bool) -> None:
    assert bool(upward_imports({importer: {imported}})) is upward


def test_service_and_worker_have_no_import_cycle_but_the_known_ones() -> None:
    edges, _ = import_graph((REPO / "service", REPO / "worker"))
    assert len(edges) > 40, "the reader found no modules of service/ and worker/"
    cycles = find_cycles(edges)
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_a_planted_cycle_is_found() -> None:
    planted = {"service.a": {"service.b"}, "service.b": {"service.a"}, "service.c": {"service.a"}}
    assert find_cycles(planted) == [["service.a", "service.b", "service.a"]]


def test_the_packages_and_the_layer_rules_agree() -> None:
    """Each package may import the repository's packages ``PACKAGES`` lists for it, and the layer rules forbid the
    others; and every package imports only those below it in ``PACKAGES``."""
    names = [layer.name for layer in PACKAGES]
    for i, layer in enumerate(PACKAGES):
        assert set(layer.members) <= set(names[i + 1 :]), f"{layer.name} may import only packages below it"
        forbidden = set(names) - set(layer.members) - {layer.name}
        assert forbidden == {n for n in LAYER_RULES.get(layer.name, ()) if n in names}, layer.name


def test_the_layer_sketch_is_the_rules() -> None:
    from tool_modules import load_tool

    sketch = load_tool("layer_sketch")
    problems = sketch.sketch_difference()
    assert problems == [], "\n".join(problems) + "\nrun tools/layer_sketch.py --write"


def test_a_sketch_edited_by_hand_is_found_and_written_back(tmp_path: Path) -> None:
    from tool_modules import load_tool

    sketch = load_tool("layer_sketch")
    doc = tmp_path / sketch.DOC
    doc.parent.mkdir(parents=True)
    doc.write_text((REPO / sketch.DOC).read_text(encoding="utf-8").replace("-> panogs_core", "-> nothing", 1))
    assert sketch.sketch_difference(tmp_path), "a stale sketch passed"
    assert sketch.write(tmp_path) is True
    assert sketch.sketch_difference(tmp_path) == []
    assert sketch.write(tmp_path) is False
