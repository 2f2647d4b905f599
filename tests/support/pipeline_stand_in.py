"""Puts a test double of the pipeline where the service and the worker take the core's. A test helper, not shipped.

A double is a module of this folder with ``run_pipeline``, ``STAGES`` and ``make_config`` (``scripted_pipeline``,
``thread_probe``). The production code has one seam on each side, and no setting names it:
``service.jobs.pipeline_config`` (the API checks a job's config with it) and ``worker.runner.load_pipeline`` (a
worker's first task loads what it runs).

- In the test process, :func:`stand_in` (a context manager) or :func:`use` (with pytest's ``monkeypatch``)
  replaces both.
- A process that a test starts (``panogs worker``, ``panogs serve``, the children they start) gets the double
  named by ``PANOGS_TEST_PIPELINE``, which only ``sitecustomize.py`` of this folder reads: Python runs it at
  start-up when this folder is on ``PYTHONPATH`` (``service_harness.python_path``). Each seam is replaced when its
  module is first imported, not before, so that ``panogs worker`` still sets its thread limits before anything
  loads numpy.
"""

from __future__ import annotations

import importlib
import importlib.abc
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from importlib.machinery import ModuleSpec
from types import ModuleType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # not imported at run time: sitecustomize.py imports this module in every process a test starts
    import pytest

ENV = "PANOGS_TEST_PIPELINE"  # a double's module name, for the processes a test starts


def seams(double: str) -> dict[str, tuple[str, Callable[..., Any]]]:
    """Module -> (attribute, replacement) of each seam, for the double ``double`` (imported on first use)."""

    def pipeline_config(overrides: dict[str, Any]) -> Any:
        return importlib.import_module(double).make_config(overrides)

    def load_pipeline() -> tuple[Any, tuple[str, ...], Callable[[dict[str, Any]], Any]]:
        module = importlib.import_module(double)
        return module.run_pipeline, tuple(module.STAGES), module.make_config

    return {"service.jobs": ("pipeline_config", pipeline_config), "worker.runner": ("load_pipeline", load_pipeline)}


def use(monkeypatch: pytest.MonkeyPatch, double: str) -> None:
    """The double in both seams of this process until the test ends."""
    for module, (attribute, replacement) in seams(double).items():
        monkeypatch.setattr(importlib.import_module(module), attribute, replacement)


@contextmanager
def stand_in(double: str) -> Iterator[None]:
    """The double in both seams of this process while the body runs (for fixtures wider than a test)."""
    saved = []
    try:
        for module_name, (attribute, replacement) in seams(double).items():
            module = importlib.import_module(module_name)
            saved.append((module, attribute, getattr(module, attribute)))
            setattr(module, attribute, replacement)
        yield
    finally:
        for module, attribute, original in reversed(saved):
            setattr(module, attribute, original)


def replace_on_import(double: str) -> None:
    """Replace each seam as soon as its module has run, in this process (``sitecustomize.py``)."""
    sys.meta_path.insert(0, _SeamFinder(seams(double)))


class _SeamFinder(importlib.abc.MetaPathFinder):
    """Finds a seam's module with the other finders, and sets the seam once the module has run."""

    def __init__(self, seams: dict[str, tuple[str, Callable[..., Any]]]) -> None:
        self.seams = seams

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> ModuleSpec | None:
        if fullname not in self.seams:
            return None
        for finder in sys.meta_path:
            find = getattr(finder, "find_spec", None)
            spec = find(fullname, path, target) if finder is not self and find is not None else None
            if spec is not None and spec.loader is not None:
                spec.loader = _ThenReplace(spec.loader, *self.seams[fullname])
                return spec
        return None


class _ThenReplace(importlib.abc.Loader):
    """A module's own loader, then the seam's replacement."""

    def __init__(self, loader: importlib.abc.Loader, attribute: str, replacement: Callable[..., Any]) -> None:
        self.loader, self.attribute, self.replacement = loader, attribute, replacement

    def create_module(self, spec: ModuleSpec) -> ModuleType | None:
        return self.loader.create_module(spec)

    def exec_module(self, module: ModuleType) -> None:
        self.loader.exec_module(module)
        setattr(module, self.attribute, self.replacement)
