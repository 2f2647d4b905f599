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

from panogs_core.gaussians.ply import write_gaussian_ply
from panogs_core.gaussians.views import write_cameras
from panogs_core.stages.export import write_vocabulary
from panogs_core.types import Camera, Frame, Vocabulary
from service import render_child
from service.api.routes import renders
from service.render_child import MAX_RENDER_PIXELS
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


def test_a_query_that_looks_like_an_option_is_taken_as_a_query(
    client: TestClient, auth: dict[str, str], finished_job: str
) -> None:
    # The query travels to the render child as one "--query=..." token: "-h" is a query the child looks up (not a
    # class of this job's vocabulary, whose space has no text encoder), not a request for the child's help.
    body = {"T_world_cam": np.eye(4).tolist(), "width": 16, "height": 12, "layer": "relevance", "query": "-h"}
    r = client.post(f"/v1/jobs/{finished_job}/render", json=body, headers=auth)
    assert r.status_code == 422, r.text
    assert "query '-h' is not a class of the vocabulary" in r.json()["message"]
    assert "usage:" not in r.text


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
    assert "results exist once its labelling is done" in r.json()["message"]
    assert client.post(f"/v1/jobs/{finished_job}/render", json=body, headers=other_auth).status_code == 404


def test_an_api_host_without_torch_answers_503_with_the_reason(
    client: TestClient, auth: dict[str, str], finished_job: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    from service import render_child

    monkeypatch.setattr(render_child, "torch_installed", lambda: False)
    r = client.post(f"/v1/jobs/{finished_job}/render", json={"T_world_cam": np.eye(4).tolist()}, headers=auth)
    assert r.status_code == 503
    assert "pipeline extra" in r.json()["message"]


@pytest.mark.parametrize(
    ("camera", "field"),
    [
        ({"fx": 1e-300}, "camera.fx"),
        ({"fy": 1e9}, "camera.fy"),
        ({"cx": 1.7e308}, "camera.cx"),
        ({"cy": -1e6}, "camera.cy"),
    ],
)
def test_extreme_camera_values_are_refused_naming_the_field(
    client: TestClient, auth: dict[str, str], finished_job: str, camera: dict[str, float], field: str
) -> None:
    doc = {"width": 32, "height": 24, "fx": 24.0, "fy": 24.0, "cx": 15.5, "cy": 11.5, **camera}
    r = client.post(
        f"/v1/jobs/{finished_job}/render", json={"T_world_cam": np.eye(4).tolist(), "camera": doc}, headers=auth
    )
    assert r.status_code == 422, r.text
    assert field in json.dumps(r.json())
    assert "Traceback" not in r.text


def test_a_crashing_render_child_is_logged_and_answered_without_traceback_or_path(
    client: TestClient,
    auth: dict[str, str],
    finished_job: str,
    settings: Settings,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    from service import render_child

    # The real child process, running a module that crashes the way a rasterizer bug would.
    (tmp_path / "crashing_render.py").write_text(
        "import sys\nraise RuntimeError('overflow while rendering ' + sys.argv[2])\n"
    )
    monkeypatch.setenv("PYTHONPATH", f"{tmp_path}:{Path(render_child.__file__).parents[1]}")
    monkeypatch.setattr(render_child, "RENDER_MODULE", "crashing_render")
    with caplog.at_level("ERROR", logger="service.render_child"):
        r = client.post(f"/v1/jobs/{finished_job}/render", json={"T_world_cam": np.eye(4).tolist()}, headers=auth)
    assert r.status_code == 503
    message = r.json()["message"]
    assert "Traceback" not in r.text
    assert "crashing_render" not in r.text
    assert str(settings.storage) not in r.text
    assert str(tmp_path) not in r.text
    request_id = message.split("request ")[1].split(")")[0]
    logged = [rec.getMessage() for rec in caplog.records if request_id in rec.getMessage()]
    assert logged
    assert "Traceback" in logged[0]
    assert "overflow while rendering" in logged[0]


def test_far_and_mirrored_poses_are_refused(client: TestClient, auth: dict[str, str], finished_job: str) -> None:
    far = np.eye(4)
    far[:3, 3] = [0, 0, 1e7]
    mirrored = np.diag([1.0, 1.0, -1.0, 1.0])
    for pose, needle in ((far, "translation"), (mirrored, "determinant")):
        r = client.post(f"/v1/jobs/{finished_job}/render", json={"T_world_cam": pose.tolist()}, headers=auth)
        assert r.status_code == 422, r.text
        assert "T_world_cam" in json.dumps(r.json())
        assert needle in json.dumps(r.json())


@pytest.mark.parametrize(
    ("query", "needle"),
    [("--", "has no letter or digit"), ("a\x00b", "control characters"), ("chair\x07", "control characters")],
)
def test_a_query_that_is_no_text_is_refused(
    client: TestClient, auth: dict[str, str], finished_job: str, query: str, needle: str
) -> None:
    # A NUL cannot travel in the child's argv, and argparse reads "--query=--" as no value at all: both were 500s.
    body = {"T_world_cam": np.eye(4).tolist(), "width": 16, "height": 12, "layer": "relevance", "query": query}
    r = client.post(f"/v1/jobs/{finished_job}/render", json=body, headers=auth)
    assert r.status_code == 422, r.text
    assert needle in json.dumps(r.json())


def test_a_render_over_its_cpu_budget_is_a_503(
    client: TestClient, auth: dict[str, str], finished_job: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # One CPU second does not even import torch in the child: the kernel stops it, and the client is told why.
    monkeypatch.setattr(render_child, "RENDER_CPU_S", 1)
    body = {"T_world_cam": np.eye(4).tolist(), "width": 16, "height": 12, "layer": "color"}
    r = client.post(f"/v1/jobs/{finished_job}/render", json=body, headers=auth)
    assert r.status_code == 503, r.text
    assert "over its CPU budget of 1 s" in r.json()["message"]


def test_renders_in_flight_are_capped_per_tenant(
    client: TestClient, auth: dict[str, str], finished_job: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    slots = render_child.RenderSlots(per_tenant=1)
    monkeypatch.setattr(renders, "RENDER_SLOTS", slots)
    body = {"T_world_cam": np.eye(4).tolist(), "width": 16, "height": 12, "layer": "color"}
    tenant = uuid.uuid4()
    with slots.hold(tenant):  # another tenant's render in flight takes none of this tenant's slots
        assert client.post(f"/v1/jobs/{finished_job}/render", json=body, headers=auth).status_code == 200
    monkeypatch.setattr(slots, "per_tenant", 0)
    r = client.post(f"/v1/jobs/{finished_job}/render", json=body, headers=auth)
    assert r.status_code == 429, r.text
    assert r.headers["Retry-After"] == str(render_child.RENDER_RETRY_AFTER_S)
    assert r.json()["type"] == "too_many_requests"
    monkeypatch.setattr(slots, "per_tenant", 1)
    assert client.post(f"/v1/jobs/{finished_job}/render", json=body, headers=auth).status_code == 200  # released
