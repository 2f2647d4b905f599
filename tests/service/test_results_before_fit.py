"""A job's results answer before its appearance fit ends; the Gaussian scene (gaussians.ply, renders) waits for the
fit with a 409 that says how far it is, and a fit that fails or is canceled leaves the results answering."""

from __future__ import annotations

import uuid

import numpy as np
import pytest
from fastapi.testclient import TestClient
from svc_helpers import make_scene, mark_results_ready, mark_succeeded
from test_renders import write_scene_result

from service.db.models import FitState, Job, JobState
from service.settings import Settings
from service.storage import Storage

RENDER = {"T_world_cam": np.eye(4).tolist(), "width": 16, "height": 12, "layer": "color"}


def _job(client: TestClient, auth: dict[str, str], tiny_zip: bytes, settings: Settings) -> uuid.UUID:
    scene = make_scene(client, auth, tiny_zip)
    ident = uuid.UUID(client.post("/v1/jobs", json={"scene_id": scene["id"]}, headers=auth).json()["id"])
    write_scene_result(Storage(settings.storage).job_dir(ident))
    return ident


@pytest.fixture
def fitting_job(client: TestClient, auth: dict[str, str], tiny_zip: bytes, settings: Settings) -> uuid.UUID:
    """A running job whose results are recorded and whose fit is a quarter done."""
    ident = _job(client, auth, tiny_zip, settings)
    mark_results_ready(settings, ident, fit_progress=0.25)
    return ident


def test_the_status_shows_the_results_ready_and_the_fit_running(
    client: TestClient, auth: dict[str, str], fitting_job: uuid.UUID
) -> None:
    job = client.get(f"/v1/jobs/{fitting_job}", headers=auth).json()
    assert job["state"] == "running"
    assert job["results_ready"] is True
    assert job["fit"] == {"state": "running", "progress": 0.25, "error": None}


def test_a_queued_job_has_no_results_and_no_fit(
    client: TestClient, auth: dict[str, str], tiny_zip: bytes, settings: Settings
) -> None:
    ident = _job(client, auth, tiny_zip, settings)
    job = client.get(f"/v1/jobs/{ident}", headers=auth).json()
    assert job["results_ready"] is False
    assert job["fit"] is None
    r = client.get(f"/v1/jobs/{ident}/instances", headers=auth)
    assert r.status_code == 409
    assert r.json()["type"] == "conflict"


def test_instances_query_viewer_and_label_artifacts_answer_during_the_fit(
    client: TestClient, auth: dict[str, str], fitting_job: uuid.UUID
) -> None:
    assert client.get(f"/v1/jobs/{fitting_job}/instances", headers=auth).status_code == 200
    r = client.post(f"/v1/jobs/{fitting_job}/query", json={"text": "wall", "min_score": 0}, headers=auth)
    assert r.status_code == 200, r.text
    scene = client.get(f"/v1/jobs/{fitting_job}/viewer-scene", headers=auth)
    assert scene.status_code == 200
    assert scene.headers["cache-control"] == "private, no-cache", "the colours change when the fit ends"
    names = {a["name"] for a in client.get(f"/v1/jobs/{fitting_job}/artifacts", headers=auth).json()["data"]}
    assert "instances.json" in names
    assert "gaussians.ply" not in names
    assert client.get(f"/v1/jobs/{fitting_job}/artifacts/instances.json", headers=auth).status_code == 200


def test_gaussians_ply_and_renders_answer_409_with_the_fit_progress(
    client: TestClient, auth: dict[str, str], fitting_job: uuid.UUID
) -> None:
    for r in (
        client.get(f"/v1/jobs/{fitting_job}/artifacts/gaussians.ply", headers=auth),
        client.post(f"/v1/jobs/{fitting_job}/render", json=RENDER, headers=auth),
    ):
        assert r.status_code == 409, r.text
        body = r.json()
        assert body["type"] == "fit_not_ready"
        assert body["fit"] == {"state": "running", "progress": 0.25, "error": None}
        assert "25% done" in body["message"]
        assert r.headers["retry-after"] == "5"


def test_the_scene_answers_once_the_fit_is_done(
    client: TestClient, auth: dict[str, str], fitting_job: uuid.UUID, settings: Settings
) -> None:
    mark_succeeded(settings, fitting_job)
    assert client.get(f"/v1/jobs/{fitting_job}", headers=auth).json()["fit"]["state"] == "succeeded"
    assert client.get(f"/v1/jobs/{fitting_job}/artifacts/gaussians.ply", headers=auth).status_code == 200
    assert client.post(f"/v1/jobs/{fitting_job}/render", json=RENDER, headers=auth).status_code == 200
    scene = client.get(f"/v1/jobs/{fitting_job}/viewer-scene", headers=auth)
    assert scene.headers["cache-control"] == "private, max-age=3600"


@pytest.mark.parametrize(
    ("state", "fit_state"), [(JobState.SUCCEEDED, FitState.FAILED), (JobState.CANCELED, FitState.CANCELED)]
)
def test_a_fit_that_failed_or_was_canceled_leaves_the_results(
    client: TestClient,
    auth: dict[str, str],
    tiny_zip: bytes,
    settings: Settings,
    state: JobState,
    fit_state: FitState,
) -> None:
    ident = _job(client, auth, tiny_zip, settings)
    mark_results_ready(settings, ident, state=state, fit_state=fit_state, fit_progress=0.5)
    job = client.get(f"/v1/jobs/{ident}", headers=auth).json()
    assert job["state"] == state.value
    assert job["results_ready"] is True
    assert job["fit"]["state"] == fit_state.value
    assert client.get(f"/v1/jobs/{ident}/instances", headers=auth).status_code == 200
    assert client.post(f"/v1/jobs/{ident}/query", json={"text": "wall"}, headers=auth).status_code == 200
    r = client.get(f"/v1/jobs/{ident}/artifacts/gaussians.ply", headers=auth)
    assert r.status_code == 409
    assert r.json()["fit"]["state"] == fit_state.value
    assert f"the Gaussian fit {fit_state.value}" in r.json()["message"]
    assert "retry-after" not in r.headers
    assert client.post(f"/v1/jobs/{ident}/render", json=RENDER, headers=auth).status_code == 409


def test_a_cancel_during_the_fit_keeps_the_results(
    client: TestClient, auth: dict[str, str], fitting_job: uuid.UUID, settings: Settings
) -> None:
    """The API asks the running job to stop; the worker ends it canceled (tests/worker: the runner's side), and
    the results stay served."""
    from service.db import crud
    from service.db.session import get_session_factory, session_scope

    r = client.post(f"/v1/jobs/{fitting_job}/cancel", headers={**auth})
    assert r.status_code == 202, r.text
    assert r.json()["cancel_requested"] is True
    with session_scope(get_session_factory(settings.database)) as session:
        job = session.get(Job, fitting_job)
        assert job is not None
        job.lease = "task"
        session.commit()
        assert crud.finish_job(session, fitting_job, "task", JobState.CANCELED)
    job = client.get(f"/v1/jobs/{fitting_job}", headers=auth).json()
    assert job["state"] == "canceled"
    assert job["fit"]["state"] == "canceled", "the fit ends with its job"
    assert client.get(f"/v1/jobs/{fitting_job}/instances", headers=auth).status_code == 200
    names = {a["name"] for a in client.get(f"/v1/jobs/{fitting_job}/artifacts", headers=auth).json()["data"]}
    assert "instances.json" in names, "the results' artifacts stay"


def test_the_fit_states_the_service_records_are_the_pipelines() -> None:
    """``job.fit_state`` stores what ``report.json``'s ``appearance.state`` says: one enum, the pipeline's."""
    from panogs_core.pipeline.result import FIT_STATES
    from panogs_core.pipeline.result import FitState as PipelineFitState

    assert FitState is PipelineFitState
    assert [str(state) for state in FIT_STATES] == ["running", "succeeded", "skipped", "failed", "canceled"]
