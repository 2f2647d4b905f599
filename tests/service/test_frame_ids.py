"""Frame ids are printable text of bounded length, in the core's validator and so at the API's scene creation.

Before this check a frame id was any non-empty string: NUL, newlines, escape sequences or a megabyte of text went
into logs, computed maps' file names and the viewer's lists. These fail on that code.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from svc_helpers import RecordingSender, edit_manifest, new_key, pack, upload_bytes, write_tiny_bundle

from panogs_core.errors import BundleError
from panogs_core.io.bundle import open_bundle
from service.api_app import create_app
from service.settings import Settings

BAD_IDS = {
    "NUL": ("a\x00b", "'a\\x00b' holds control or non-printable characters, expected printable text"),
    "newline": ("000000\n[INFO] forged", "holds control or non-printable characters"),
    "escape": ("\x1b[31mred", "holds control or non-printable characters"),
    "zero-width space": ("a\u200bb", "holds control or non-printable characters"),
    "too long": ("f" * 129, "has 129 characters, expected at most 128"),
}


def _with_id(field: str, value: str) -> Callable[[Path], None]:
    def mutate(root: Path) -> None:
        def edit(doc: dict[str, Any]) -> None:
            if field == "frames":
                doc["frames"][1]["id"] = value
            else:
                doc["skipped_frames"] = [{"id": value, "pose": doc["frames"][0]["pose"]}]

        edit_manifest(root, edit)

    return mutate


@pytest.mark.parametrize("field", ["frames", "skipped_frames"])
@pytest.mark.parametrize("case", sorted(BAD_IDS))
def test_a_frame_id_that_is_not_printable_text_is_refused(tmp_path: Path, case: str, field: str) -> None:
    value, words = BAD_IDS[case]
    root = write_tiny_bundle(tmp_path / "bundle", mutate=_with_id(field, value))
    with pytest.raises(BundleError) as caught:
        open_bundle(root)
    where = "scene.json: frames[1].id" if field == "frames" else "scene.json: skipped_frames[0].id"
    assert any(p.startswith(where) and words in p for p in caught.value.problems), caught.value.problems
    assert all(p.isprintable() for p in caught.value.problems)  # the value is shown escaped


def test_printable_ids_of_any_script_pass(tmp_path: Path) -> None:
    root = write_tiny_bundle(tmp_path / "bundle", mutate=_with_id("frames", "frame 2 – кадр"))
    assert open_bundle(root).frames[1].id == "frame 2 – кадр"


def test_the_api_refuses_the_bundle_naming_the_frame(make_settings: Callable[..., Settings]) -> None:
    settings = make_settings("sqlite")
    data = pack(write_tiny_bundle(settings.data_dir / "bundle", mutate=_with_id("frames", "a\x00b")))
    auth = new_key(settings)
    with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
        upload = upload_bytes(client, auth, data, filename="ids.zip")
        response = client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=auth)
    assert response.status_code == 422, response.text
    assert response.json()["problems"] == [
        "scene.json: frames[1].id: 'a\\x00b' holds control or non-printable characters, expected printable text"
    ]
