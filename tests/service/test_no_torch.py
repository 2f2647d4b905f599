"""The API needs neither torch nor open3d: the API process never imports torch (not at import, not while serving
uploads, scenes, jobs and queries), and the API install (``pip install 'panogs[service]'``) in a fresh virtual
environment has neither, migrates its database from the wheel and serves ``/healthz``.

Checked in fresh interpreters, because this test session itself imports torch elsewhere.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from fresh_install import FreshInstall, install
from service_harness import REPO, SUPPORT, free_port

SCRIPT = r"""
import json, sys
from pathlib import Path
sys.path[:0] = [{helpers!r}, {support!r}]
steps = {{}}

def mark(step):
    steps[step] = "torch" in sys.modules

from fastapi.testclient import TestClient
from svc_helpers import RecordingSender, make_scene, new_key, pack, write_tiny_bundle
from service.db.migrate import upgrade
from service.api_app import create_app
from service.settings import Settings
mark("import")
settings = Settings(_env_file=None, data_dir=Path({tmp!r}) / "data")
settings.ensure_dirs()
upgrade(settings.database)
bundle = pack(write_tiny_bundle(Path({tmp!r}) / "bundle"))
mark("setup")
with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
    auth = new_key(settings)
    client.get("/readyz")
    scene = make_scene(client, auth, bundle)
    mark("scene")
    job = client.post("/v1/jobs", json={{"scene_id": scene["id"], "config": {{}}}}, headers=auth).json()
    client.get(f"/v1/jobs/{{job['id']}}", headers=auth)
    mark("job")
print(json.dumps(steps))
"""


@pytest.mark.slow  # a fresh interpreter through upload, scene and job
def test_api_never_imports_torch(tmp_path: Path) -> None:
    helpers = str(Path(__file__).parent)
    code = SCRIPT.format(helpers=helpers, support=str(SUPPORT), tmp=str(tmp_path))
    argv = [sys.executable, "-c", code]
    done = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    steps = json.loads(done.stdout.strip().splitlines()[-1])
    assert not steps["import"], "importing service.api_app imported torch"
    assert not steps["scene"], "validating a bundle imported torch"
    assert not steps["job"], "creating or reading a job imported torch"


@pytest.fixture(scope="module")
def api_install(tmp_path_factory: pytest.TempPathFactory) -> FreshInstall:
    """``panogs[service]`` from a wheel in a new virtual environment (shared with the migration test)."""
    return install(tmp_path_factory, "service")


@pytest.mark.slow
def test_api_install_has_no_torch_and_no_open3d(api_install: FreshInstall, tmp_path: Path) -> None:
    code = "import importlib.util as u, json; print(json.dumps({m: bool(u.find_spec(m)) for m in %r}))"
    done = api_install.run(code % ["torch", "open3d", "fastapi", "service", "panogs_core"], cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    found = json.loads(done.stdout)
    assert found == {"torch": False, "open3d": False, "fastapi": True, "service": True, "panogs_core": True}


@pytest.fixture
def api_server(api_install: FreshInstall, tmp_path: Path) -> Iterator[str]:
    """``panogs serve --no-worker`` of the API install, from an empty folder; yields its base URL."""
    port = free_port()
    argv = [str(api_install.panogs), "serve", "--no-worker", "--port", str(port), "--data-dir", "data"]
    log = (tmp_path / "serve.log").open("wb")
    proc = subprocess.Popen(argv, cwd=tmp_path, env=api_install.env(), stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)  # fmt: skip
    try:
        yield _wait_until_up(f"http://127.0.0.1:{port}", proc, tmp_path / "serve.log")
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)
        log.close()


def _wait_until_up(url: str, proc: subprocess.Popen[bytes], log: Path, timeout_s: float = 60) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"panogs serve exited:\n{log.read_text(errors='replace')[-3000:]}"
        try:
            with urllib.request.urlopen(f"{url}/healthz", timeout=1) as response:
                if response.status == 200:
                    return url
        except OSError:
            time.sleep(0.2)
    raise AssertionError(f"panogs serve did not answer in {timeout_s} s:\n{log.read_text(errors='replace')[-3000:]}")


@pytest.mark.slow
def test_api_install_serves(api_server: str, tmp_path: Path) -> None:
    """It answers /healthz, and /readyz: its database was migrated from the wheel on start, in a folder that is
    not the repository."""
    with urllib.request.urlopen(f"{api_server}/healthz", timeout=5) as response:
        assert json.loads(response.read())["status"] == "ok"
    with urllib.request.urlopen(f"{api_server}/readyz", timeout=5) as response:
        assert json.loads(response.read())["checks"] == {"database": "ok", "broker": "ok", "storage": "ok"}
    assert (tmp_path / "data" / "panogs.db").is_file()


@pytest.mark.slow
def test_api_install_refuses_the_embedded_worker_at_once(api_install: FreshInstall, tmp_path: Path) -> None:
    argv = [str(api_install.panogs), "serve", "--port", str(free_port())]
    done = subprocess.run(argv, cwd=tmp_path, env=api_install.env(), capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "torch" in done.stderr
    assert "panogs serve --no-worker" in done.stderr
