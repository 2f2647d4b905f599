"""POST /v1/jobs/{id}/render: a PNG of a finished job's Gaussian scene from the pose in the body, or a clear 4xx."""

from __future__ import annotations

import json
import uuid
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from gaussian_runs import opaque_gaussians
from svc_helpers import make_scene, mark_succeeded

from panogs_core.export import write_vocabulary
from panogs_core.gaussian_ply import write_gaussian_ply
from panogs_core.types import Camera, Frame, Vocabulary
from panogs_core.views import write_cameras
from service.renders import MAX_RENDER_PIXELS
from service.settings import Settings
from service.storage import Storage

CAMERA = Camera(width=32, height=24, fx=24.0, fy=24.0, cx=15.5, cy=11.5)


def write_scene_result(out_dir: Path) -> None:
    """A run folder with a red wall (class 0) at z = 2: the files a render reads."""
    out_dir.mkdir(parents=True, exist_ok=True)
    xs, ys = np.meshgrid(np.arange(-1.5, 1.5, 0.04), np.arange(-1.2, 1.2, 0.04))
    means = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 2.0)], 1).astype(np.float32)
    n = len(means)
    scene = opaque_gaussians(means, np.tile([0.9, 0.1, 0.1], (n, 1)), 0.04)
    zeros = np.zeros(n, np.int64)
    write_gaussian_ply(out_dir / "gaussians.ply", scene, np.zeros((n, 3), np.float32), zeros, zeros - 1)
    write_cameras(out_dir / "cameras.json", CAMERA, [Frame(id="f0", T_world_cam=np.eye(4), depth="d.png")])
    write_vocabulary(
        out_dir, Vocabulary(names=("wall",), kinds=("stuff",), embeddings=np.eye(1, 4, dtype=np.float32)), "t"
    )
    (out_dir / "instances.json").write_text("[]")
    np.save(out_dir / "instance_features.npy", np.zeros((0, 4), np.float32))


def _job(client: TestClient, auth: dict[str, str], tiny_zip: bytes, settings: Settings, *, finish: bool) -> str:
    scene = make_scene(client, auth, tiny_zip)
    job = client.post("/v1/jobs", json={"scene_id": scene["id"]}, headers=auth).json()
    if finish:
        ident = uuid.UUID(job["id"])
        write_scene_result(Storage(settings.storage).job_dir(ident))
        mark_succeeded(settings, ident)
    return str(job["id"])


@pytest.fixture
def finished_job(client: TestClient, auth: dict[str, str], tiny_zip: bytes, settings: Settings) -> str:
    return _job(client, auth, tiny_zip, settings, finish=True)


def test_render_returns_the_png_of_the_layer(client: TestClient, auth: dict[str, str], finished_job: str) -> None:
    body = {"T_world_cam": np.eye(4).tolist(), "width": 16, "height": 12, "layer": "color"}
    r = client.post(f"/v1/jobs/{finished_job}/render", json=body, headers=auth)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png"
    img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    assert img.shape == (12, 16, 3)
    assert img[6, 8, 0] > 200  # the red wall fills the view
    assert img[6, 8, 2] < 60


@pytest.mark.parametrize(
    ("body", "needle"),
    [
        ({"T_world_cam": np.eye(4).tolist(), "width": 4000, "height": 4000}, f"at most {MAX_RENDER_PIXELS} pixels"),
        ({"T_world_cam": (2 * np.eye(4)).tolist()}, "not a rigid transform"),
        ({"T_world_cam": [[1, 0], [0, 1]]}, "4x4"),
        ({"T_world_cam": np.eye(4).tolist(), "layer": "relevance"}, "needs a query"),
        ({"T_world_cam": np.eye(4).tolist(), "width": 10}, "both width and height"),
        ({"T_world_cam": np.eye(4).tolist(), "layer": "normals"}, "layer"),
    ],
)
def test_bad_requests_are_refused_with_the_reason(
    client: TestClient, auth: dict[str, str], finished_job: str, body: dict[str, Any], needle: str
) -> None:
    r = client.post(f"/v1/jobs/{finished_job}/render", json=body, headers=auth)
    assert r.status_code == 422, r.text
    assert needle in json.dumps(r.json())


def test_unfinished_and_foreign_jobs(
    client: TestClient,
    auth: dict[str, str],
    other_auth: dict[str, str],
    tiny_zip: bytes,
    settings: Settings,
    finished_job: str,
) -> None:
    body = {"T_world_cam": np.eye(4).tolist()}
    running = _job(client, auth, tiny_zip, settings, finish=False)
    r = client.post(f"/v1/jobs/{running}/render", json=body, headers=auth)
    assert r.status_code == 409
    assert "results exist once it has succeeded" in r.json()["message"]
    assert client.post(f"/v1/jobs/{finished_job}/render", json=body, headers=other_auth).status_code == 404


def test_an_api_host_without_torch_answers_503_with_the_reason(
    client: TestClient, auth: dict[str, str], finished_job: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    from service import renders

    monkeypatch.setattr(renders, "torch_installed", lambda: False)
    r = client.post(f"/v1/jobs/{finished_job}/render", json={"T_world_cam": np.eye(4).tolist()}, headers=auth)
    assert r.status_code == 503
    assert "pipeline extra" in r.json()["message"]
