"""Fixtures of the browser tests: one ``panogs serve`` (embedded, real pipeline) and one Chromium per module.

Chromium is Debian's ``/usr/bin/chromium`` (``PANOGS_TEST_CHROMIUM`` to use another), driven by Playwright and
drawing WebGL in software (SwiftShader), so the tests need no GPU. Missing Chromium or Playwright skips the tests
on a developer's machine and fails them under CI (``CI=true``), like the service tests' PostgreSQL.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from service_harness import REPO, Procs, free_port, python_path, require_service, wait_for

CHROMIUM = os.environ.get("PANOGS_TEST_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]
ARTIFACTS = REPO / "tests" / "web" / "artifacts"  # screenshots (git-ignored; CI keeps them)


@pytest.fixture(scope="session")
def chromium_path() -> str:
    try:
        import playwright  # noqa: F401
    except ImportError:
        require_service("Playwright", "the Python package playwright", False, "make install")
    require_service("Chromium", CHROMIUM, Path(CHROMIUM).is_file(), "apt-get install -y chromium")
    return CHROMIUM


@pytest.fixture(scope="module")
def browser(chromium_path: str) -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        instance = p.chromium.launch(executable_path=chromium_path, args=CHROMIUM_ARGS)
        yield instance
        instance.close()


@pytest.fixture(scope="module")
def artifacts() -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    return ARTIFACTS


def _create_key(env: dict[str, str], cwd: Path, name: str) -> str:
    argv = [sys.executable, "-m", "service.cli", "keys", "create", "--name", name]
    done = subprocess.run(argv, env=env, cwd=cwd, capture_output=True, text=True, check=True, timeout=120)
    return done.stdout.strip()


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """``panogs serve`` with no configuration in a fresh folder: base URL, two tenants' keys, storage folder."""
    tmp = tmp_path_factory.mktemp("web-serve")
    clean = {k: v for k, v in os.environ.items() if not k.startswith("PANOGS_")}
    procs = Procs({}, tmp)
    procs.env = {**clean, "PYTHONPATH": python_path(), "PYTHONUNBUFFERED": "1"}
    try:
        keys = {name: _create_key(procs.env, tmp, name) for name in ("alice", "mallory")}
        port = free_port()
        proc = procs.start("serve", [sys.executable, "-m", "panogs_core.cli", "serve", "--port", str(port)])
        url = f"http://127.0.0.1:{port}"

        def up() -> bool:
            assert proc.poll() is None, procs.tail("serve")()
            return httpx.get(f"{url}/readyz", timeout=1).status_code == 200

        wait_for(up, 60, "panogs serve", procs.tail("serve"))
        yield {"url": url, "keys": keys, "storage": tmp / "panogs-data" / "storage", "log": procs.tail("serve")}
    finally:
        procs.stop_all()


@pytest.fixture(scope="module")
def bundle_zip(tmp_path_factory: pytest.TempPathFactory, synth_tiny: Path) -> Path:
    """A tiny synthetic scene (``panogs synth --preset tiny``, the session's) zipped, as a user would upload it."""
    tmp = tmp_path_factory.mktemp("web-bundle")
    return Path(shutil.make_archive(str(tmp / "tiny-room"), "zip", synth_tiny))
