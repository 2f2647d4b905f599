"""Folders that a whole test run shares: made by the first pytest process that asks for one, read by the others.

Under pytest-xdist each worker process has session fixtures of its own, so a scene or a pipeline run that tests of
two test files read was made twice when the files ran in different processes. :func:`made_once` makes it once per
run instead: in a folder every process of the run sees (the parent of the workers' temporary folders), under a
file lock, so the second process waits for the first one's folder rather than making its own. Without xdist the
folder is in the session's temporary folder, as before.

A made folder is only read (the fixtures that hand one out say so): a test that changes one copies it first.
A test helper, not shipped.
"""

from __future__ import annotations

import fcntl
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest


def shared_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder the processes of this test run share: the controller's temporary folder under xdist (each worker's
    is a sub-folder of it, ``pytest-N/popen-gw0``), this session's otherwise (also in a pytest that a test starts,
    which inherits ``PYTEST_XDIST_WORKER`` but has a temporary folder of its own)."""
    base = tmp_path_factory.getbasetemp()
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    root = (base.parent if worker and base.name == f"popen-{worker}" else base) / "made-once"
    root.mkdir(exist_ok=True)
    return root


def made_once(tmp_path_factory: pytest.TempPathFactory, name: str, make: Callable[[Path], object]) -> Path:
    """The folder ``name`` of this run, after ``make(folder)`` filled it: called in the first process that asks,
    while the others wait for it. A ``make`` that raises leaves no folder behind, so the next process that asks
    tries again (and fails the same way, in its own test)."""
    folder = shared_root(tmp_path_factory) / name
    with (folder.parent / f"{name}.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        done = folder.parent / f"{name}.made"  # written once the folder is complete
        if not done.is_file():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            try:
                make(folder)
            except BaseException:
                shutil.rmtree(folder, ignore_errors=True)
                raise
            done.touch()
    return folder
