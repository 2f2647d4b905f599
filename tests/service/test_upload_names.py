"""An upload's filename names its scene: one the scene could not take (over 255 characters) is refused when the
upload is created, before a byte is sent, and leaves nothing behind."""

from __future__ import annotations

import base64
from pathlib import Path

from fastapi.testclient import TestClient
from svc_helpers import BOTH_BACKENDS

from service.db.models import Upload
from service.db.session import get_session_factory, session_scope
from service.settings import Settings


def _create(client: TestClient, auth: dict[str, str], filename: str) -> object:
    metadata = f"filename {base64.b64encode(filename.encode()).decode()}"
    return client.post("/v1/uploads", headers={**auth, "Tus-Resumable": "1.0.0", "Upload-Length": "10",
                                               "Upload-Metadata": metadata})  # fmt: skip


@BOTH_BACKENDS
def test_a_filename_too_long_for_a_scene_name_is_refused_at_creation(
    client: TestClient, auth: dict[str, str], settings: Settings
) -> None:
    refused = _create(client, auth, "a" * 252 + ".zip")
    assert refused.status_code == 422, refused.text  # type: ignore[attr-defined]
    assert "at most 255" in refused.json()["message"]  # type: ignore[attr-defined]
    with session_scope(get_session_factory(settings.database)) as session:
        assert session.query(Upload).count() == 0
    uploads = Path(settings.storage) / "uploads"
    assert not uploads.exists() or not any(uploads.iterdir())
    kept = _create(client, auth, "a" * 251 + ".zip")
    assert kept.status_code == 201  # type: ignore[attr-defined]
    assert kept.json()["filename"] == "a" * 251 + ".zip"  # type: ignore[attr-defined]
