"""Results of a finished job: instances, artifact downloads with HTTP Range, and queries (class, vector,
text)."""

from __future__ import annotations

import json
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from declared_run import write_declared_files
from fastapi.testclient import TestClient
from svc_helpers import RecordingSender, make_scene, mark_succeeded, new_key

from panogs_core.io.run_folder import DOWNLOADABLE, RUN_FILES
from service.api_app import create_app
from service.db.models import Artifact
from service.db.session import get_session_factory, session_scope
from service.encoder import EncoderProcess
from service.settings import Settings
from service.storage import Storage

CLASSES = [("wall", "stuff"), ("chair", "thing"), ("table", "thing")]


def write_result(out_dir: Path, embeddings: np.ndarray, space: str, *, per_class: int = 1) -> list[dict[str, Any]]:
    """A finished run's folder: ``per_class`` instances of each class, features next to their class
    embedding."""
    rng = np.random.default_rng(0)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows, feats = [], []
    for k in range(len(CLASSES) * per_class):
        cls = k % len(CLASSES)
        centre = rng.uniform(-3, 3, 3)
        rows.append({"id": k, "class_name": CLASSES[cls][0], "class_index": cls, "kind": CLASSES[cls][1],
                     "score": 0.9, "num_points": 100, "centroid": centre.tolist(),
                     "bbox_min": (centre - 0.5).tolist(), "bbox_max": (centre + 0.5).tolist()})  # fmt: skip
        feature = embeddings[cls] + 0.05 * rng.normal(size=embeddings.shape[1])
        feats.append(feature / np.linalg.norm(feature))
    (out_dir / "instances.json").write_text(json.dumps(rows))
    np.save(out_dir / "instance_features.npy", np.asarray(feats, np.float32))
    np.save(out_dir / "vocabulary.npy", embeddings.astype(np.float32))
    classes = [{"name": n, "kind": k} for n, k in CLASSES]
    vocabulary = {"classes": classes, "embeddings": "vocabulary.npy", "space": space}
    (out_dir / "vocabulary.json").write_text(json.dumps(vocabulary))
    (out_dir / "panoptic.ply").write_bytes(bytes(range(256)) * 40)  # 10240 bytes to fetch in ranges
    (out_dir / "report.json").write_text(json.dumps({"stages": []}))
    return rows


def finish_job(settings: Settings, job_id: str, embeddings: np.ndarray, space: str, **kw: Any) -> None:
    """Write a result folder for the job and mark it succeeded with its artifacts (as the worker does)."""
    ident = uuid.UUID(job_id)
    write_result(Storage(settings.storage).job_dir(ident), embeddings, space, **kw)
    mark_succeeded(settings, ident)


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


@pytest.fixture
def job_id(client: TestClient, auth: dict[str, str], tiny_zip: bytes, settings: Settings) -> str:
    scene = make_scene(client, auth, tiny_zip)
    job = client.post("/v1/jobs", json={"scene_id": scene["id"]}, headers=auth).json()
    finish_job(settings, job["id"], _unit(np.eye(3, 8) + 0.1), "test-space")
    return str(job["id"])


class TestInstancesAndDownloads:
    def test_instances(self, client: TestClient, auth: dict[str, str], job_id: str) -> None:
        body = client.get(f"/v1/jobs/{job_id}/instances", headers=auth).json()
        assert body["count"] == 3
        assert [i["class_name"] for i in body["data"]] == ["wall", "chair", "table"]
        assert len(body["data"][1]["bbox_min"]) == 3

    def test_artifact_list_and_download(self, client: TestClient, auth: dict[str, str], job_id: str) -> None:
        listed = {a["name"]: a for a in client.get(f"/v1/jobs/{job_id}/artifacts", headers=auth).json()["data"]}
        assert set(listed) == {"panoptic.ply", "instances.json", "report.json", "vocabulary.json"}
        ply = listed["panoptic.ply"]
        assert ply["size_bytes"] == 10240
        assert ply["url"] == f"/v1/jobs/{job_id}/artifacts/panoptic.ply"
        whole = client.get(ply["url"], headers=auth)
        assert whole.status_code == 200
        assert whole.content == bytes(range(256)) * 40
        assert whole.headers["etag"] == f'"{ply["sha256"]}"'
        assert whole.headers["accept-ranges"] == "bytes"

    def test_ranges(self, client: TestClient, auth: dict[str, str], job_id: str) -> None:
        url = f"/v1/jobs/{job_id}/artifacts/panoptic.ply"
        part = client.get(url, headers={**auth, "Range": "bytes=256-511"})
        assert part.status_code == 206
        assert part.headers["content-range"] == "bytes 256-511/10240"
        assert part.content == bytes(range(256))
        tail = client.get(url, headers={**auth, "Range": "bytes=-10"})
        assert tail.content == bytes(range(246, 256))
        assert client.get(url, headers={**auth, "Range": "bytes=20000-"}).status_code == 416

    @pytest.mark.parametrize("name", ["gaussians.ply", "..%2F..%2Fpanogs.db", "stages", "instance_features.npy"])
    def test_unknown_artifact(self, client: TestClient, auth: dict[str, str], job_id: str, name: str) -> None:
        assert client.get(f"/v1/jobs/{job_id}/artifacts/{name}", headers=auth).status_code == 404


def test_the_api_serves_the_declared_downloads(
    client: TestClient, auth: dict[str, str], tiny_zip: bytes, settings: Settings
) -> None:
    """Of a run folder holding every declared file, the API lists and serves exactly the declared downloads, with
    the declared media types, even where a row names another file."""
    scene = make_scene(client, auth, tiny_zip)
    job_id = client.post("/v1/jobs", json={"scene_id": scene["id"]}, headers=auth).json()["id"]
    out_dir = Storage(settings.storage).job_dir(uuid.UUID(job_id))
    write_declared_files(out_dir)
    mark_succeeded(settings, uuid.UUID(job_id))
    with session_scope(get_session_factory(settings.database)) as session:  # a row the declaration does not serve
        path = Storage(settings.storage).rel(out_dir / "instance_features.npy")
        session.add(Artifact(job_id=uuid.UUID(job_id), name="instance_features.npy", path=path, size_bytes=1,
                             sha256="0" * 64, media_type="application/octet-stream"))  # fmt: skip
        session.commit()
    listed = client.get(f"/v1/jobs/{job_id}/artifacts", headers=auth).json()["data"]
    assert {a["name"]: a["media_type"] for a in listed} == {n: f.media_type for n, f in DOWNLOADABLE.items()}
    for spec in RUN_FILES:
        response = client.get(f"/v1/jobs/{job_id}/artifacts/{spec.name.rstrip('/')}", headers=auth)
        if spec.downloadable:
            assert response.status_code == 200, spec.name
            assert response.headers["content-type"] == spec.media_type
            assert response.content == spec.name.encode()
        else:
            assert response.status_code == 404, spec.name


class TestQuery:
    def test_class_name(self, client: TestClient, auth: dict[str, str], job_id: str) -> None:
        body = client.post(f"/v1/jobs/{job_id}/query", json={"text": "Chair"}, headers=auth).json()
        assert body["query_kind"] == "class"
        assert [h["instance_id"] for h in body["hits"]] == [1]
        assert body["hits"][0]["class_name"] == "chair"

    def test_vector(self, client: TestClient, auth: dict[str, str], job_id: str) -> None:
        vector = _unit(np.eye(3, 8) + 0.1)[2].tolist()
        body = client.post(f"/v1/jobs/{job_id}/query", json={"vector": vector, "top_k": 1}, headers=auth).json()
        assert body["query_kind"] == "vector"
        assert [h["instance_id"] for h in body["hits"]] == [2]

    @pytest.mark.parametrize(
        ("body", "needle"),
        [
            ({"vector": [1.0, 0.0]}, "8"),
            ({"text": "chair", "vector": [1.0] * 8}, "exactly one"),
            ({}, "exactly one"),
            ({"text": "   "}, "blank"),
            ({"text": "chair", "top_k": 0}, "top_k"),
            ({"text": "something to sit on"}, "free-text"),
        ],
    )
    def test_refused(self, client: TestClient, auth: dict[str, str], job_id: str, body: Any, needle: str) -> None:
        response = client.post(f"/v1/jobs/{job_id}/query", json=body, headers=auth)
        assert response.status_code == 422, response.text
        assert needle in json.dumps(response.json())

    def test_nan_vector(self, client: TestClient, auth: dict[str, str], job_id: str) -> None:
        raw = '{"vector": [NaN, 0, 0, 0, 0, 0, 0, 0]}'
        headers = {**auth, "Content-Type": "application/json"}
        response = client.post(f"/v1/jobs/{job_id}/query", content=raw, headers=headers)
        assert response.status_code == 422
        assert "NaN" in json.dumps(response.json())


@pytest.fixture(scope="module")
def encoder() -> Iterator[EncoderProcess]:
    process = EncoderProcess()
    yield process
    process.close()


@pytest.mark.slow
def test_free_text_through_the_encoder_process(
    encoder: EncoderProcess, make_settings: Callable[..., Settings], tiny_zip: bytes
) -> None:
    """A free-text query is encoded in the child process (MiniLM, offline) and finds the right instances."""
    pytest.importorskip("sentence_transformers")
    settings = make_settings("postgres")
    embeddings = encoder.encode("minilm-l6", [n for n, _ in CLASSES])
    app = create_app(settings, sender=RecordingSender(), run_reaper=False)
    app.state.encoder = encoder
    with TestClient(app) as client:
        auth = new_key(settings)
        scene = make_scene(client, auth, tiny_zip)
        job = client.post("/v1/jobs", json={"scene_id": scene["id"]}, headers=auth).json()
        finish_job(settings, job["id"], embeddings, "minilm-l6", per_class=2)
        url = f"/v1/jobs/{job['id']}/query"
        first = client.post(url, json={"text": "a chair to sit on"}, headers=auth).json()
        assert first["query_kind"] == "text"
        assert {h["class_name"] for h in first["hits"]} == {"chair"}
        assert len(first["hits"]) == 2
        warm = client.post(url, json={"text": "a table"}, headers=auth).json()
        assert {h["class_name"] for h in warm["hits"]} == {"table"}
        assert warm["took_ms"] < 1000  # the encoder stays loaded
