"""Scenes: made from complete uploads, validated by the core validator; a bad bundle keeps nothing."""

from __future__ import annotations

import io
import json
import tarfile
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from svc_helpers import (
    BOTH_BACKENDS,
    RecordingSender,
    edit_manifest,
    make_scene,
    new_key,
    pack,
    upload_bytes,
    write_tiny_bundle,
)

from service.api_app import create_app
from service.settings import Settings


def _refused(client: TestClient, auth: dict[str, str], data: bytes, settings: Settings) -> dict[str, object]:
    """Upload ``data``, try to make a scene; assert 422 and that nothing stayed behind."""
    upload = upload_bytes(client, auth, data, filename="bad.zip")
    response = client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=auth)
    assert response.status_code == 422, response.text
    body = response.json()
    assert body["type"] == "invalid_bundle"
    assert body["problems"]
    assert "nothing was kept" in body["message"]
    assert client.get("/v1/scenes", headers=auth).json()["count"] == 0
    assert client.get(f"/v1/uploads/{upload['id']}", headers=auth).status_code == 404
    for sub in ("scenes", "uploads"):
        folder = settings.storage / sub
        assert not folder.exists() or not any(folder.iterdir()), f"{sub} not empty"
    return dict(body)


def _zip(members: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return buffer.getvalue()


def _zip_of(folder: Path, extra: dict[str, bytes]) -> bytes:
    members = {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}
    return _zip({**members, **extra})


class TestCreate:
    @BOTH_BACKENDS
    def test_valid_bundle(self, client: TestClient, auth: dict[str, str], tiny_zip: bytes, settings: Settings) -> None:
        scene = make_scene(client, auth, tiny_zip)
        assert scene["name"] == "tiny"
        assert scene["feature_dim"] == 8
        assert scene["feature_space"] == "test-space"
        assert scene["num_frames"] == 2
        assert scene["has_vocabulary"] is True
        assert scene["size_bytes"] > 0
        assert client.get(f"/v1/scenes/{scene['id']}", headers=auth).json() == scene
        listed = client.get("/v1/scenes", headers=auth).json()
        assert listed["count"] == 1
        assert listed["data"][0]["id"] == scene["id"]
        assert (settings.storage / "scenes" / scene["id"]).is_dir()
        assert not any((settings.storage / "uploads").iterdir())  # the archive is gone once extracted

    def test_tar_gz_and_name(self, client: TestClient, auth: dict[str, str], tmp_path: Path) -> None:
        data = pack(write_tiny_bundle(tmp_path / "b"), "tar.gz")
        upload = upload_bytes(client, auth, data)
        response = client.post("/v1/scenes", json={"upload_id": upload["id"], "name": "kitchen"}, headers=auth)
        assert response.status_code == 201, response.text
        assert response.json()["name"] == "kitchen"

    @BOTH_BACKENDS
    def test_a_control_character_in_the_name_is_refused_and_the_upload_kept(
        self, client: TestClient, auth: dict[str, str], tmp_path: Path
    ) -> None:
        root = write_tiny_bundle(tmp_path / "b")
        edit_manifest(root, lambda m: m.update(name="room\x00/etc/passwd"))
        upload = upload_bytes(client, auth, pack(root, "zip"))
        for body in ({"upload_id": upload["id"], "name": "bad\x1b[2Jname"}, {"upload_id": upload["id"]}):
            response = client.post("/v1/scenes", json=body, headers=auth)
            assert response.status_code == 422, response.text
            assert "control or separator character" in response.json()["message"]
        # Neither refusal used the upload up: the same upload makes a scene once the request names it.
        response = client.post("/v1/scenes", json={"upload_id": upload["id"], "name": "kitchen"}, headers=auth)
        assert response.status_code == 201, response.text
        assert client.get("/v1/scenes", headers=auth).json()["count"] == 1

    def test_upload_used_once(self, client: TestClient, auth: dict[str, str], tiny_zip: bytes) -> None:
        upload = upload_bytes(client, auth, tiny_zip)
        assert client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=auth).status_code == 201
        again = client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=auth)
        assert again.status_code == 409

    def test_incomplete_upload(self, client: TestClient, auth: dict[str, str]) -> None:
        upload = client.post("/v1/uploads", headers={**auth, "Upload-Length": "100"}).json()
        response = client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=auth)
        assert response.status_code == 409
        assert "0 of 100 bytes" in response.json()["message"]

    def test_other_tenant(
        self, client: TestClient, auth: dict[str, str], other_auth: dict[str, str], tiny_zip: bytes
    ) -> None:
        upload = upload_bytes(client, auth, tiny_zip)
        stolen = client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=other_auth)
        assert stolen.status_code == 404
        scene = make_scene(client, auth, tiny_zip)
        assert client.get(f"/v1/scenes/{scene['id']}", headers=other_auth).status_code == 404
        assert client.get("/v1/scenes", headers=other_auth).json()["count"] == 0


class TestBadBundles:
    def test_not_an_archive(self, client: TestClient, auth: dict[str, str], settings: Settings) -> None:
        body = _refused(client, auth, b"just some text, not an archive", settings)
        assert "not a .zip" in body["problems"][0]  # type: ignore[index]

    def test_zip_slip(self, client: TestClient, auth: dict[str, str], settings: Settings, tmp_path: Path) -> None:
        data = _zip_of(write_tiny_bundle(tmp_path / "b"), {"../../escape.txt": b"x"})
        body = _refused(client, auth, data, settings)
        assert any("escape.txt" in p for p in body["problems"])  # type: ignore[union-attr]
        assert not (settings.storage.parent / "escape.txt").exists()

    def test_symlink(self, client: TestClient, auth: dict[str, str], settings: Settings, tmp_path: Path) -> None:
        folder = write_tiny_bundle(tmp_path / "b")
        buffer = io.BytesIO()
        with tarfile.open(fileobj=buffer, mode="w") as tf:
            tf.add(folder, arcname=".")
            link = tarfile.TarInfo("passwd")
            link.type = tarfile.SYMTYPE
            link.linkname = "/etc/passwd"
            tf.addfile(link)
        body = _refused(client, auth, buffer.getvalue(), settings)
        assert any("passwd" in p for p in body["problems"])  # type: ignore[union-attr]

    def test_archive_bomb(self, make_settings: Callable[..., Settings], auth: dict[str, str], tmp_path: Path) -> None:
        settings = make_settings("postgres", bundle_max_bytes=2_000_000)
        data = _zip_of(write_tiny_bundle(tmp_path / "b"), {"padding.bin": bytes(20_000_000)})
        assert len(data) < 200_000  # compresses 100:1
        with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
            key = new_key(settings)
            body = _refused(client, key, data, settings)
        assert any("bytes" in p for p in body["problems"])  # type: ignore[union-attr]

    def test_pickled_npy(self, client: TestClient, auth: dict[str, str], settings: Settings, tmp_path: Path) -> None:
        def pickle_features(root: Path) -> None:
            np.save(root / "features" / "000000.npy", np.array([{"evil": 1}], dtype=object), allow_pickle=True)

        data = pack(write_tiny_bundle(tmp_path / "b", mutate=pickle_features))
        body = _refused(client, auth, data, settings)
        assert any("000000.npy" in p for p in body["problems"])  # type: ignore[union-attr]

    def test_wrong_feature_dim(
        self, client: TestClient, auth: dict[str, str], settings: Settings, tmp_path: Path
    ) -> None:
        def bad_dim(root: Path) -> None:
            np.save(root / "features" / "000001.npy", np.zeros((6, 8, 7), np.float32))

        data = pack(write_tiny_bundle(tmp_path / "b", mutate=bad_dim))
        body = _refused(client, auth, data, settings)
        assert any("000001.npy" in p and "8" in p for p in body["problems"])  # type: ignore[union-attr]

    def test_nan_pose_and_every_problem_listed(
        self, client: TestClient, auth: dict[str, str], settings: Settings, tmp_path: Path
    ) -> None:
        def break_two_things(root: Path) -> None:
            edit_manifest(root, lambda m: m["frames"][0]["pose"][0].__setitem__(3, float("nan")))
            color = root / json.loads((root / "scene.json").read_text())["frames"][1]["color"]
            color.write_bytes(color.read_bytes()[:40])  # truncated image

        data = pack(write_tiny_bundle(tmp_path / "b", mutate=break_two_things))
        problems = _refused(client, auth, data, settings)["problems"]
        assert len(problems) >= 2  # type: ignore[arg-type]
        text = "\n".join(problems)  # type: ignore[arg-type]
        assert "pose" in text
        assert "000001" in text


@pytest.mark.parametrize("body", [{}, {"upload_id": "not-a-uuid"}, {"upload_id": None}, {"upload_id": 1, "x": 2}])
def test_bad_request_body(client: TestClient, auth: dict[str, str], body: dict[str, object]) -> None:
    response = client.post("/v1/scenes", json=body, headers=auth)
    assert response.status_code == 422
    assert response.json()["type"] == "invalid_input"
    assert response.json()["problems"]
