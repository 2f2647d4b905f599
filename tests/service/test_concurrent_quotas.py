"""Quotas and disk room that hold when requests arrive at once: the check and the insert it guards run under the
tenant's lock (a row lock on PostgreSQL, the write lock on SQLite), so N concurrent requests accept exactly what
fits; the free-disk check sets aside what the other open uploads have promised and not written; a write that meets
a full volume is a 507."""

from __future__ import annotations

import errno
import shutil
import threading
from collections.abc import Callable, Iterator
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient
from svc_helpers import RecordingSender, make_scene, new_key

from service.api_app import create_app
from service.settings import Settings
from service.storage.chunks import ChunkWriter

MB = 1_000_000
PATCH_AT_0 = {"Tus-Resumable": "1.0.0", "Upload-Offset": "0", "Content-Type": "application/offset+octet-stream"}
BACKENDS = pytest.mark.parametrize("backend", ["postgres", "sqlite"])


@pytest.fixture
def serve(make_settings: Callable[..., Settings]) -> Iterator[Callable[..., tuple[TestClient, Settings]]]:
    """An app served by a TestClient on settings of ``backend`` with ``overrides``; closed at the end."""
    clients: list[TestClient] = []

    def start(backend: str, **overrides: Any) -> tuple[TestClient, Settings]:
        settings = make_settings(backend, **overrides)
        client = TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False))
        client.__enter__()
        clients.append(client)
        return client, settings

    yield start
    for client in clients:
        client.__exit__(None, None, None)


def at_once(n: int, request: Callable[[int], httpx.Response]) -> list[httpx.Response]:
    """``request(i)`` for i < n from n threads released together; the answers in order of i."""
    start = threading.Barrier(n)
    answers: list[httpx.Response | None] = [None] * n
    errors: list[BaseException] = []

    def run(i: int) -> None:
        try:
            start.wait(timeout=30)
            answers[i] = request(i)
        except BaseException as exc:  # named by the assertion below
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(n)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    assert not errors, errors
    return [a for a in answers if a is not None]


def new_upload(client: TestClient, auth: dict[str, str], length: int) -> httpx.Response:
    headers = {**auth, "Tus-Resumable": "1.0.0", "Upload-Length": str(length)}
    return client.post("/v1/uploads", headers=headers)


def statuses(answers: list[httpx.Response]) -> list[int]:
    return sorted(a.status_code for a in answers)


@BACKENDS
def test_concurrent_uploads_take_exactly_the_quota(serve: Callable[..., Any], backend: str) -> None:
    client, settings = serve(backend, quota_bytes=6_500_000)
    for round_ in range(3):  # a fresh tenant each round: a race that slips through once in a while is still caught
        auth = new_key(settings, f"tenant-{round_}")
        answers = at_once(8, lambda _i, auth=auth: new_upload(client, auth, 2 * MB))
        assert statuses(answers) == [201] * 3 + [413] * 5, [a.text for a in answers]
        refused = next(a for a in answers if a.status_code == 413).json()
        assert refused["type"] == "quota_exceeded"
        assert "PANOGS_QUOTA_BYTES" in refused["message"]


@BACKENDS
def test_concurrent_jobs_take_exactly_the_job_slots(serve: Callable[..., Any], backend: str, tiny_zip: bytes) -> None:
    client, settings = serve(backend, quota_concurrent_jobs=4)
    for round_ in range(2):
        auth = new_key(settings, f"tenant-{round_}")
        scene = make_scene(client, auth, tiny_zip)
        body = {"scene_id": scene["id"]}
        answers = at_once(12, lambda _i, auth=auth, body=body: client.post("/v1/jobs", json=body, headers=auth))
        assert statuses(answers) == [202] * 4 + [429] * 8, [a.text for a in answers]
        listed = client.get("/v1/jobs", headers=auth).json()
        assert len(listed["data"]) == 4


@BACKENDS
def test_open_uploads_reserve_their_room_on_the_disk(serve: Callable[..., Any], backend: str) -> None:
    # Creating an upload writes nothing, so the room may be large: the slack between two shares and the room (600 MB)
    # absorbs what other processes of a parallel suite write between the probe and the requests.
    room = 3000 * MB
    probe, _ = serve(backend)
    free = shutil.disk_usage(probe.app.state.storage.root).free  # type: ignore[attr-defined]
    client, settings = serve(backend, min_free_disk_bytes=max(0, free - room), quota_bytes=None)
    auth = new_key(settings)
    share = int(0.4 * room)
    answers = at_once(3, lambda _i: new_upload(client, auth, share))
    assert statuses(answers) == [201, 201, 507], [a.text for a in answers]
    refused = next(a for a in answers if a.status_code == 507).json()
    assert refused["type"] == "insufficient_storage"
    assert "promised to open uploads" in refused["message"]
    # A PATCH of an accepted upload still has its room: the others' reservations are not counted against it.
    upload = next(a for a in answers if a.status_code == 201).json()
    headers = {
        **auth,
        "Tus-Resumable": "1.0.0",
        "Upload-Offset": "0",
        "Content-Type": "application/offset+octet-stream",
    }
    patched = client.patch(f"/v1/uploads/{upload['id']}", content=b"x" * 1000, headers=headers)
    assert patched.status_code == 204, patched.text
    # Abandoning one gives its room back.
    other = [a for a in answers if a.status_code == 201][1].json()
    assert client.delete(f"/v1/uploads/{other['id']}", headers={**auth, "Tus-Resumable": "1.0.0"}).status_code == 204
    assert new_upload(client, auth, share).status_code == 201


@BACKENDS
def test_a_patch_that_meets_a_full_disk_is_a_507(
    serve: Callable[..., Any], backend: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    client, settings = serve(backend)
    auth = new_key(settings)
    upload = new_upload(client, auth, 4 * MB).json()

    def full(self: ChunkWriter, data: bytes | bytearray) -> None:
        # The volume filling between the room check and the write (another process took the space).
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(ChunkWriter, "write", full)
    headers = {
        **auth,
        "Tus-Resumable": "1.0.0",
        "Upload-Offset": "0",
        "Content-Type": "application/offset+octet-stream",
    }
    answer = client.patch(f"/v1/uploads/{upload['id']}", content=b"x" * (2 * MB), headers=headers)
    assert answer.status_code == 507, answer.text
    body = answer.json()
    assert body["type"] == "insufficient_storage"
    assert "resumes at offset 0" in body["message"]
    monkeypatch.undo()
    head = client.head(f"/v1/uploads/{upload['id']}", headers={**auth, "Tus-Resumable": "1.0.0"})
    assert head.headers["Upload-Offset"] == "0"
