"""Fixtures of the browser tests: one ``panogs serve`` (embedded, real pipeline) and one Chromium per module.

The served app declares two 2D models an upload may name (``PANOGS_MAP_MODELS``): tiny SAM and CLIP models with
random weights, saved with ``save_pretrained`` (tests/support/tiny_models.py), so a bundle of colour and depth alone
has its maps computed in the worker and free text embedded by that CLIP's text tower (meaningless answers, real code).

Chromium is Debian's ``/usr/bin/chromium`` (``PANOGS_TEST_CHROMIUM`` to use another), driven by Playwright and
drawing WebGL in software (SwiftShader), so the tests need no GPU. Missing Chromium or Playwright skips the tests
on a developer's machine and fails them under CI (``CI=true``), like the service tests' PostgreSQL.
"""

from __future__ import annotations

import json
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


MAP_MODELS = {"masks": "tiny-sam", "features": "tiny-clip"}  # the entry names the served app declares


@pytest.fixture(scope="session")
def map_model_entries(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """``PANOGS_MAP_MODELS`` of the served app: the tiny random models, built once (none without transformers).

    Building imports torch and transformers here (about 4 CPU seconds alone; under ``make test`` another test file
    run by the same process may have imported both already)."""
    try:
        import transformers  # noqa: F401
    except ImportError:
        return {}
    from tiny_models import tiny_clip, tiny_sam

    root = tmp_path_factory.mktemp("web-map-models")
    folders = {"masks": tiny_sam(root / "sam"), "features": tiny_clip(root / "clip")}
    return {MAP_MODELS[kind]: {"kind": kind, "path": str(folder)} for kind, folder in folders.items()}


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory, map_model_entries: dict[str, Any]) -> Iterator[dict[str, Any]]:
    """``panogs serve`` in a fresh folder, configured with nothing but the 2D models' entries: base URL, two tenants'
    keys, storage folder, the entries."""
    tmp = tmp_path_factory.mktemp("web-serve")
    clean = {k: v for k, v in os.environ.items() if not k.startswith("PANOGS_")}
    procs = Procs({}, tmp)
    procs.env = {**clean, "PYTHONPATH": python_path(), "PYTHONUNBUFFERED": "1"}
    if map_model_entries:
        procs.env["PANOGS_MAP_MODELS"] = json.dumps(map_model_entries)
    try:
        keys = {name: _create_key(procs.env, tmp, name) for name in ("alice", "mallory")}
        port = free_port()
        proc = procs.start("serve", [sys.executable, "-m", "panogs_core.cli", "serve", "--port", str(port)])
        url = f"http://127.0.0.1:{port}"

        def up() -> bool:
            assert proc.poll() is None, procs.tail("serve")()
            return httpx.get(f"{url}/readyz", timeout=1).status_code == 200

        wait_for(up, 60, "panogs serve", procs.tail("serve"))
        storage, log = tmp / "panogs-data" / "storage", procs.tail("serve")
        yield {"url": url, "keys": keys, "storage": storage, "log": log, "map_models": map_model_entries}
    finally:
        procs.stop_all()


@pytest.fixture(scope="module")
def bundle_zip(tmp_path_factory: pytest.TempPathFactory, synth_tiny: Path) -> Path:
    """A tiny synthetic scene (``panogs synth --preset tiny``, the session's) zipped, as a user would upload it."""
    tmp = tmp_path_factory.mktemp("web-bundle")
    return Path(shutil.make_archive(str(tmp / "tiny-room"), "zip", synth_tiny))


@pytest.fixture(scope="module")
def bare_bundle_zip(tmp_path_factory: pytest.TempPathFactory, synth_tiny: Path) -> Path:
    """The tiny scene as a capture without 2D maps, zipped: every 3rd frame's colour, depth and pose (4 of 12), no
    masks, feature maps, label set or ground truth; the upload form's models compute the maps."""
    folder = tmp_path_factory.mktemp("web-bare") / "bare-room"
    doc = json.loads((synth_tiny / "scene.json").read_text())
    doc.pop("features", None)
    doc["frames"] = [{k: v for k, v in f.items() if k not in ("features", "masks")} for f in doc["frames"][::3]]
    for frame in doc["frames"]:
        for key in ("color", "depth"):
            (folder / frame[key]).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(synth_tiny / frame[key], folder / frame[key])
    shutil.copyfile(synth_tiny / "geometry.ply", folder / "geometry.ply")  # the room's primitives, as before
    (folder / "scene.json").write_text(json.dumps(doc))
    return Path(shutil.make_archive(str(folder), "zip", folder))
