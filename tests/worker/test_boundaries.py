"""The seam between the service and the worker: the worker imports the service, never the reverse; neither
ships or imports the test doubles; and importing any of their modules builds nothing and writes no file."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("service", "worker")
TEST_ONLY = ("scripted_pipeline", "thread_probe", "pipeline_stand_in", "service_harness", "fresh_install", "tests")
# Alembic scripts: Alembic runs them inside its own context; importing them outside it is meaningless.
NOT_MODULES = ("service.db.migrations.env",)


def source_files(package: str) -> Iterator[Path]:
    yield from sorted((REPO / package).rglob("*.py"))


def imported_names(path: Path) -> set[str]:
    """Every module an ``import`` statement of ``path`` names, at any depth (inside functions too)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def package_edges() -> dict[str, set[str]]:
    """Which of ``PACKAGES`` each package imports."""
    edges: dict[str, set[str]] = {package: set() for package in PACKAGES}
    for package in PACKAGES:
        for path in source_files(package):
            tops = {name.split(".")[0] for name in imported_names(path)}
            edges[package] |= (tops & set(PACKAGES)) - {package}
    return edges


def test_the_worker_depends_on_the_service_and_never_the_reverse() -> None:
    assert package_edges() == {"service": set(), "worker": {"service"}}


def test_no_module_of_service_names_the_worker() -> None:
    """Not even inside a function: the Celery factory and the task names live in ``service.broker``."""
    offenders = {
        str(path.relative_to(REPO)): sorted(n for n in imported_names(path) if n.split(".")[0] == "worker")
        for path in source_files("service")
    }
    assert {k: v for k, v in offenders.items() if v} == {}


@pytest.mark.parametrize("package", PACKAGES)
def test_runtime_packages_ship_no_test_doubles(package: str) -> None:
    for path in source_files(package):
        used = {name for name in imported_names(path) if name.split(".")[0] in TEST_ONLY}
        assert not used, f"{path.relative_to(REPO)} imports test code: {used}"
    assert not (REPO / "service" / "testing.py").exists()
    assert not (REPO / "worker" / "scripted.py").exists()


IMPORT_EVERYTHING = """
import importlib, json, pkgutil, sys
skip = set(sys.argv[1].split(","))
done = []
for package in sys.argv[2:]:
    root = importlib.import_module(package)
    done.append(package)
    for info in pkgutil.walk_packages(root.__path__, prefix=package + "."):
        if info.name not in skip:
            importlib.import_module(info.name)
            done.append(info.name)
print(json.dumps(done))
"""


def test_importing_every_module_writes_nothing(tmp_path: Path) -> None:
    """Run from an empty folder: a module that builds an app or makes its data folders at import shows up
    here as a new file or folder (``./panogs-data`` was one)."""
    cwd = tmp_path / "empty"
    cwd.mkdir()
    argv = [sys.executable, "-c", IMPORT_EVERYTHING, ",".join(NOT_MODULES), *PACKAGES]
    env = {"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    done = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    imported = json.loads(done.stdout.strip().splitlines()[-1])
    assert {"service.api_app", "service.broker", "worker.celery_app", "worker.tasks", "worker.cli"} <= set(imported)
    assert sorted(p.name for p in cwd.iterdir()) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty"], "nothing written under HOME either"
