"""The folders a leased task of a job works in (the job's own task, a tile's, the merge's), on either backend.

- **Local backend**: the scene's bundle and the job's folder in place; nothing to fetch or to store back
  (:class:`InPlace`).
- **Object storage**: a scratch folder of this task, removed after it, with the scene's bundle (from the worker's
  bundle cache when it keeps one, else fetched into the scratch folder), the parts of the job's folder the task
  reads fetched into it, and a :class:`service.storage.TreePush` that stores back what it writes under one
  sub-folder.

The task says what it reads and writes (:class:`WorkPlan`); ``Storage.workspace`` makes the folders, and which
backend it runs on is the storage's business. This module holds the types only (it imports nothing of the package).
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol


class Pusher(Protocol):
    """Stores what a task wrote back where the job's folder lives."""

    skip: set[Path]  # files kept under another key already (the scene's checkpoints): never stored again

    def push(self) -> int: ...


@dataclass
class InPlace:
    """The :class:`Pusher` of the local backend: the task wrote into the job's folder itself."""

    skip: set[Path] = field(default_factory=set)

    def push(self) -> int:
        """Nothing to store; no bytes."""
        return 0


@dataclass(frozen=True)
class WorkPlan:
    """What one task of a job reads and writes.

    ``fetch`` and ``push`` are paths under the job's folder: one ending in ``/`` (or empty: the whole folder) is a
    sub-folder, any other a single file.
    """

    name: str  # names the scratch folder (``job``, ``tile``, ``merge``)
    bundle_path: str  # the scene's bundle, as its row stores it
    fetch: tuple[str, ...] = ("",)
    push: str = ""
    # The bundle from the worker's cache, held while the task runs; None: fetched into the scratch folder.
    cached_bundle: Callable[[], AbstractContextManager[Path]] | None = None


@dataclass(frozen=True)
class Workspace:
    """Where the task finds the scene's bundle, where it writes (the job's folder), and what stores that back."""

    bundle: Path
    out: Path
    push: Pusher
