"""A bundle's validation runs in a child process, a few at a time, within a CPU budget (service.bundle_check).

On the code before it these fail: validation ran in the API's request threads with no budget (a hostile bundle
took minutes of the API's CPU; ``BundleLimits`` had no ``max_cpu_s``), any number of bundles were validated at
once, and ``/healthz`` waited for a free request thread like any other route.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import anyio.to_thread
import pytest
from fastapi.testclient import TestClient
from svc_helpers import RecordingSender, new_key, pack, upload_bytes, write_tiny_bundle

from panogs_core.errors import BundleError
from panogs_core.io.bundle import BundleLimits, open_bundle
from service.api_app import create_app
from service.bundle_check import BundleOpener, OpenRequest, cpu_budget_s, open_in_child
from service.settings import Settings


def spin_forever(request: OpenRequest, conn: Connection) -> None:
    """A child that only burns CPU: what a check that never ends looks like from outside."""
    while True:
        pass


def allocate_too_much(request: OpenRequest, conn: Connection) -> None:
    """What a check that reads a huge declared size whole looks like: one allocation past the limit."""
    try:
        bytearray(4 * 1024**3)
    except MemoryError:
        conn.send(("memory", None))


def open_when_released(request: OpenRequest, conn: Connection) -> None:
    """Say it started, wait for the test's release (at most 30 s), then open the bundle as the service does.

    The signals are files in ``signals/`` beside the storage's ``scenes/`` folder (the child knows no fixture).
    """
    signals = _signals(Path(request.workdir).parents[1])
    (signals / "started").touch()
    deadline = time.monotonic() + 30
    while not (signals / "release").exists() and time.monotonic() < deadline:
        time.sleep(0.02)
    open_in_child(request, conn)


def _signals(storage: Path) -> Path:
    return storage / "signals"


def _app_client(settings: Settings) -> Callable[[], TestClient]:
    return lambda: TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False))


def _scene_request(client: TestClient, auth: dict[str, str], data: bytes) -> tuple[str, Any]:
    upload = upload_bytes(client, auth, data, filename="hostile.zip")
    response = client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=auth)
    return upload["id"], response


def test_the_core_stops_at_the_file_where_its_budget_ran_out(tmp_path: Path) -> None:
    root = write_tiny_bundle(tmp_path / "bundle")
    with pytest.raises(BundleError) as caught:
        open_bundle(root, limits=BundleLimits(max_cpu_s=0))
    assert any(
        p.startswith("scene.json: frames[0]: validation stopped here, over its CPU budget of 0 s per bundle")
        for p in caught.value.problems
    ), caught.value.problems
    assert open_bundle(root, limits=BundleLimits(max_cpu_s=60)).name  # the same bundle within a budget


def test_the_budget_grows_with_the_archive() -> None:
    assert cpu_budget_s(10, 1000) == 10
    assert cpu_budget_s(10, 3 * 1024**3) == 30


def test_over_budget_is_a_422_naming_the_file_and_the_setting(make_settings: Callable[..., Settings]) -> None:
    settings = make_settings("sqlite", validation_cpu_s=1e-9)
    data = pack(write_tiny_bundle(settings.data_dir / "bundle"))
    auth = new_key(settings)
    with _app_client(settings)() as client:
        upload_id, response = _scene_request(client, auth, data)
        assert response.status_code == 422, response.text
        problems = response.json()["problems"]
        assert any("frames[0]: validation stopped here, over its CPU budget of 1e-09 s" in p for p in problems)
        assert any("PANOGS_VALIDATION_CPU_S" in p for p in problems), problems
        assert client.get(f"/v1/uploads/{upload_id}", headers=auth).status_code == 404  # nothing kept
    assert not any((settings.storage / "scenes").glob("*/*"))


def test_a_check_that_never_ends_is_stopped_by_the_kernel(make_settings: Callable[..., Settings]) -> None:
    """The validator's own check runs between files; one check that runs on is stopped by RLIMIT_CPU."""
    settings = make_settings("sqlite", validation_cpu_s=1e-6)
    data = pack(write_tiny_bundle(settings.data_dir / "bundle"))
    auth = new_key(settings)
    with _app_client(settings)() as client:
        opener: BundleOpener = client.app.state.bundle_opener  # type: ignore[attr-defined]
        opener.target, opener.grace_s = spin_forever, 0  # the kernel's limit at 1 s of CPU
        upload_id, response = _scene_request(client, auth, data)
        assert response.status_code == 422, response.text
        body = response.json()
        assert body["problems"][0].startswith("hostile.zip: validation used its CPU budget of 1e-06 s")
        assert "PANOGS_VALIDATION_CPU_S" in body["problems"][0]
        assert client.get(f"/v1/uploads/{upload_id}", headers=auth).status_code == 404
    assert not any((settings.storage / "scenes").glob("*/*"))


def test_a_validation_past_its_memory_limit_is_a_422_naming_it(make_settings: Callable[..., Settings]) -> None:
    settings = make_settings("sqlite", validation_memory_bytes=1024**3)
    data = pack(write_tiny_bundle(settings.data_dir / "bundle"))
    auth = new_key(settings)
    with _app_client(settings)() as client:
        client.app.state.bundle_opener.target = allocate_too_much  # type: ignore[attr-defined]
        upload_id, response = _scene_request(client, auth, data)
        assert response.status_code == 422, response.text
        assert response.json()["problems"][0] == (
            "hostile.zip: validation needed more than its memory limit of 1,073,741,824 bytes of address space "
            "(PANOGS_VALIDATION_MEMORY_BYTES) and was stopped"
        )
        assert client.get(f"/v1/uploads/{upload_id}", headers=auth).status_code == 404


def test_validations_past_the_slots_are_a_503_and_keep_the_upload(make_settings: Callable[..., Settings]) -> None:
    settings = make_settings("sqlite", validation_slots=1)
    data = pack(write_tiny_bundle(settings.data_dir / "bundle"))
    auth = new_key(settings)
    with _app_client(settings)() as client:
        opener: BundleOpener = client.app.state.bundle_opener  # type: ignore[attr-defined]
        upload = upload_bytes(client, auth, data, filename="tiny.zip")
        with opener.slot():  # another bundle is being validated
            response = client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=auth)
        assert response.status_code == 503, response.text
        assert response.headers["Retry-After"]
        assert "PANOGS_VALIDATION_SLOTS" in response.json()["message"]
        assert client.get(f"/v1/uploads/{upload['id']}", headers=auth).json()["state"] == "complete"
        retried = client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=auth)
        assert retried.status_code == 201, retried.text


def test_healthz_answers_while_every_request_thread_waits_on_a_validation(
    make_settings: Callable[..., Settings],
) -> None:
    settings = make_settings("sqlite")
    signals = _signals(settings.storage)
    signals.mkdir(parents=True)
    data = pack(write_tiny_bundle(settings.data_dir / "bundle"))
    auth = new_key(settings)
    with _app_client(settings)() as client:
        opener: BundleOpener = client.app.state.bundle_opener  # type: ignore[attr-defined]
        opener.target = open_when_released
        upload = upload_bytes(client, auth, data, filename="tiny.zip")

        def one_thread() -> None:
            anyio.to_thread.current_default_thread_limiter().total_tokens = 1

        client.portal.call(one_thread)  # type: ignore[union-attr]
        answers: list[int] = []
        scene = threading.Thread(
            target=lambda: answers.append(
                client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=auth).status_code
            )
        )
        scene.start()
        deadline = time.monotonic() + 60
        while not (signals / "started").exists():
            assert time.monotonic() < deadline, "the validation child never started"
            time.sleep(0.02)
        try:
            assert client.get("/healthz").status_code == 200
            assert scene.is_alive(), "/healthz answered only after the validation that held the only thread"
        finally:
            (signals / "release").touch()
            scene.join(60)
        assert answers == [201]
