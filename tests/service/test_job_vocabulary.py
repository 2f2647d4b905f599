"""A job's vocabulary over REST: a built-in name, the bundle's own, or inline classes, checked
before the job row exists; never a path of the host, and no message repeats one.

The worker half runs ``execute_job`` in-process on the same database: with the scripted pipeline here (its
instances take the inline names the worker hands it), with the real pipeline in ``TestRealPipeline`` (slow).
"""

from __future__ import annotations

import json
import shutil
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scripted_pipeline as scripted
from fastapi.testclient import TestClient
from sqlalchemy import func, select
from svc_helpers import BOTH_BACKENDS, RecordingSender, make_scene, new_key

from service.api_app import create_app
from service.db.models import Job, JobState, Scene
from service.db.session import get_session_factory, session_scope
from service.schemas import MAX_VOCABULARY_CLASSES
from service.settings import Settings
from service.storage import Storage
from worker import leased, runner

INLINE = {
    "classes": [
        {"name": "lamp", "embedding": [1, 0, 0, 0, 0, 0, 0, 0]},
        {"name": "Rug", "kind": "stuff", "embedding": [0, 1, 0, 0, 0, 0, 0, 0.5]},
        {"name": "wall", "embedding": [0, 0, 1, 0, 0, 0, 0, 0]},
    ]
}  # the tiny bundle's features are 8-d


@pytest.fixture(autouse=True)
def quick_stages(monkeypatch: pytest.MonkeyPatch) -> None:
    """The stand-in pipeline's stages take 0.2 s each by default (for tests that stop a job mid-run); nothing
    here waits on a stage, and each run here was 1.2 s of sleep."""
    monkeypatch.setenv("PANOGS_SCRIPTED_STAGE_S", "0.01")


@pytest.fixture
def scene(client: TestClient, auth: dict[str, str], tiny_zip: bytes) -> dict[str, Any]:
    return make_scene(client, auth, tiny_zip)


def _post(client: TestClient, auth: dict[str, str], scene_id: str, vocabulary: Any, **headers: str) -> Any:
    body = {"scene_id": scene_id, "vocabulary": vocabulary}
    return client.post("/v1/jobs", json=body, headers={**auth, **headers})


def _job_count(settings: Settings) -> int:
    with session_scope(get_session_factory(settings.database)) as session:
        return int(session.scalar(select(func.count()).select_from(Job)) or 0)


def _problems(response: Any) -> str:
    body = response.json()
    return " | ".join([body["message"], *(body.get("problems") or [])])


def _run_worker(
    settings: Settings, job_id: str, pipeline: Any = scripted.run_pipeline,
    make_config: Any = scripted.make_config, stages: tuple[str, ...] = scripted.STAGES,
) -> JobState | None:  # fmt: skip
    env = leased.JobEnv(
        settings=settings, session_factory=get_session_factory(settings.database), storage=Storage(settings.storage),
        pipeline=pipeline, make_config=make_config, stages=stages,
    )  # fmt: skip
    return runner.execute_job(uuid.UUID(job_id), lease="t-1", worker="test", env=env)


class Spy:
    """The scripted pipeline, recording the ``vocabulary`` the worker hands it."""

    def __init__(self) -> None:
        self.seen: list[Any] = []

    def __call__(self, *args: Any, **kw: Any) -> Any:
        self.seen.append(kw["vocabulary"])
        return scripted.run_pipeline(*args, **kw)


class TestNoPaths:
    @BOTH_BACKENDS
    def test_other_tenants_vocabulary_file_is_refused(
        self, client: TestClient, auth: dict[str, str], settings: Settings, tiny_zip: bytes
    ) -> None:
        """Tenant B names the vocabulary.json of tenant A's scene: 422, nothing echoed, no job row."""
        scene_a = make_scene(client, auth, tiny_zip)
        with session_scope(get_session_factory(settings.database)) as session:
            row = session.get(Scene, uuid.UUID(scene_a["id"]))
            assert row is not None
            victim = Storage(settings.storage).path(row.bundle_path) / "vocabulary.json"
        assert victim.is_file()  # the file is there: the refusal is not for want of it
        bob = new_key(settings, "bob")
        scene_b = make_scene(client, bob, tiny_zip)
        for spec in (str(victim), f"{victim.parent}/../bundle/vocabulary.json", "vocabulary.json"):
            response = _post(client, bob, scene_b["id"], spec)
            assert response.status_code == 422, response.text
            text = response.text
            assert "vocabulary" in _problems(response)
            assert str(settings.storage) not in text
            assert "vocabulary.json" not in text
        assert _job_count(settings) == 0

    def test_system_file_is_refused_without_echo(
        self, client: TestClient, auth: dict[str, str], scene: dict[str, Any], settings: Settings
    ) -> None:
        for spec in ("/etc/passwd", "/nonexistent/x", "C:\\Windows\\win.ini", "~/.ssh/id_rsa", "x" * 20_000):
            response = _post(client, auth, scene["id"], spec)
            assert response.status_code == 422, response.text
            assert "passwd" not in response.text
            assert "ssh" not in response.text
            assert "win.ini" not in response.text
            assert "not a built-in label set" in _problems(response) or "at most 64" in _problems(response)
        # existing and missing files are answered alike: no file-existence test
        exists = _problems(_post(client, auth, scene["id"], "/etc/passwd"))
        missing = _problems(_post(client, auth, scene["id"], "/etc/passwx"))
        assert exists == missing
        assert _job_count(settings) == 0

    def test_unknown_name_is_named(self, client: TestClient, auth: dict[str, str], scene: dict[str, Any]) -> None:
        response = _post(client, auth, scene["id"], "coco")
        assert response.status_code == 422
        problems = _problems(response)
        assert "vocabulary" in problems
        assert "'coco'" in problems
        assert "scannet20" in problems

    def test_stored_path_from_before_is_refused_by_the_worker(
        self, client: TestClient, auth: dict[str, str], scene: dict[str, Any], settings: Settings
    ) -> None:
        """A queued row that still names a file (made before this check) fails in the worker; the pipeline
        never sees the value and the error does not repeat it."""
        job = _post(client, auth, scene["id"], None).json()
        secret = str(settings.storage / "scenes" / "vocabulary.json")
        with session_scope(get_session_factory(settings.database)) as session:
            row = session.get(Job, uuid.UUID(job["id"]))
            assert row is not None
            row.vocabulary = secret
            session.commit()
        spy = Spy()
        assert _run_worker(settings, job["id"], spy) == JobState.FAILED
        got = client.get(f"/v1/jobs/{job['id']}", headers=auth).json()
        assert got["error"]["type"] == "InputError"
        assert "unknown built-in label set" in got["error"]["message"]
        assert secret not in got["error"]["message"]
        assert "vocabulary.json" not in got["error"]["message"]
        assert spy.seen == []


class TestBuiltin:
    @BOTH_BACKENDS
    def test_names_case_insensitive(
        self, client: TestClient, auth: dict[str, str], scene: dict[str, Any], settings: Settings
    ) -> None:
        response = _post(client, auth, scene["id"], " ScanNet20 ")
        assert response.status_code == 202, response.text
        assert response.json()["vocabulary"] == "scannet20"
        assert _post(client, auth, scene["id"], "matterport21").json()["vocabulary"] == "matterport21"
        default = _post(client, auth, scene["id"], None).json()
        assert default["vocabulary"] is None  # the bundle's own
        spy = Spy()
        assert _run_worker(settings, response.json()["id"], spy) == JobState.SUCCEEDED
        assert _run_worker(settings, default["id"], spy) == JobState.SUCCEEDED
        assert spy.seen == ["scannet20", None]  # names are handed on as names, for the pipeline's name-only resolver


class TestInline:
    @BOTH_BACKENDS
    def test_stored_shown_and_run(
        self, client: TestClient, auth: dict[str, str], scene: dict[str, Any], settings: Settings
    ) -> None:
        response = _post(client, auth, scene["id"], INLINE)
        assert response.status_code == 202, response.text
        job = response.json()
        shown = [{"name": "lamp", "kind": "thing"}, {"name": "Rug", "kind": "stuff"}, {"name": "wall", "kind": "stuff"}]
        assert job["vocabulary"] == {"classes": shown}  # kinds as the run uses them; embeddings not echoed
        assert client.get(f"/v1/jobs/{job['id']}", headers=auth).json()["vocabulary"] == {"classes": shown}
        assert client.get("/v1/jobs", headers=auth).json()["data"][0]["vocabulary"] == {"classes": shown}
        with session_scope(get_session_factory(settings.database)) as session:
            row = session.get(Job, uuid.UUID(job["id"]))
            assert row is not None
            assert row.vocabulary is None
            assert row.vocabulary_embeddings == [c["embedding"] for c in INLINE["classes"]]  # type: ignore[index]
        spy = Spy()
        assert _run_worker(settings, job["id"], spy) == JobState.SUCCEEDED
        (vocabulary,) = spy.seen
        assert vocabulary.names == ("lamp", "Rug", "wall")
        assert vocabulary.kinds == ("thing", "stuff", "stuff")
        np.testing.assert_allclose(np.linalg.norm(vocabulary.embeddings, axis=1), 1.0, atol=1e-6)
        instances = client.get(f"/v1/jobs/{job['id']}/artifacts/instances.json", headers=auth).json()
        assert [i["class_name"] for i in instances] == ["lamp", "Rug"]
        written = client.get(f"/v1/jobs/{job['id']}/artifacts/vocabulary.json", headers=auth).json()
        assert [c["name"] for c in written["classes"]] == ["lamp", "Rug", "wall"]

    def test_names_only(self, client: TestClient, auth: dict[str, str], scene: dict[str, Any]) -> None:
        response = _post(client, auth, scene["id"], {"classes": [{"name": "lamp"}, {"name": "floor"}]})
        assert response.status_code == 202, response.text
        assert response.json()["vocabulary"]["classes"][1] == {"name": "floor", "kind": "stuff"}

    def test_idempotent_retry(self, client: TestClient, auth: dict[str, str], scene: dict[str, Any]) -> None:
        key = {"Idempotency-Key": "inline-1"}
        first = _post(client, auth, scene["id"], INLINE, **key)
        again = _post(client, auth, scene["id"], INLINE, **key)
        assert first.status_code == again.status_code == 202
        assert first.json()["id"] == again.json()["id"]
        changed = {"classes": [*INLINE["classes"][:2], {"name": "door", "embedding": [0, 0, 0, 1, 0, 0, 0, 0]}]}
        other = _post(client, auth, scene["id"], changed, **key)
        assert other.status_code == 422
        assert "Idempotency-Key" in other.json()["message"]

    def test_dimension_must_match_the_scene(
        self, client: TestClient, auth: dict[str, str], scene: dict[str, Any], settings: Settings
    ) -> None:
        wide = {"classes": [{"name": "lamp", "embedding": [1.0] * 512}]}
        response = _post(client, auth, scene["id"], wide)
        assert response.status_code == 422
        message = response.json()["message"]
        assert "vocabulary.classes[*].embedding" in message
        assert "512" in message
        assert "8-d" in message
        assert _job_count(settings) == 0

    @pytest.mark.parametrize(
        ("vocabulary", "expected"),
        [
            ({"classes": []}, "vocabulary.inline.classes: List should have at least 1 item"),
            ({"classes": [{"name": "a"}, {"name": "A"}]}, "repeats classes[0]"),
            ({"classes": [{"name": "  "}]}, "vocabulary.inline.classes.0.name"),
            ({"classes": [{"name": "a\nb"}]}, "control or separator"),
            ({"classes": [{"name": "a" * 201}]}, "at most 200"),
            ({"classes": [{"name": "a", "kind": "blob"}]}, "vocabulary.inline.classes.0.kind"),
            ({"classes": [{"name": "a", "path": "/etc/passwd"}]}, "vocabulary.inline.classes.0.path: Extra inputs"),
            ({"classes": [{"name": "a"}], "embeddings": "vocabulary.npy"}, "vocabulary.inline.embeddings: Extra"),
            ({"classes": [{"name": "a", "embedding": [1, 0]}, {"name": "b"}]}, "for every class or for none"),
            ({"classes": [{"name": "a", "embedding": [0, 0]}]}, "all zeros"),
            ({"classes": [{"name": "a", "embedding": [1e39, 0]}]}, "does not fit float32"),  # finite, not as float32
            ({"classes": [{"name": "a", "embedding": [1e20, 1e20]}]}, "does not fit float32"),  # its length overflows
            ({"classes": [{"name": "a", "embedding": [1e-30, 0]}]}, "does not fit float32"),  # underflows to zero
            ({"classes": [{"name": "a", "embedding": ["x"]}]}, "vocabulary.inline.classes.0.embedding.0"),
            ({"classes": [{"name": f"c{i}"} for i in range(MAX_VOCABULARY_CLASSES + 1)]}, "at most 1000"),
            (["scannet20"], "expected a built-in label-set name or an inline"),
            (7, "expected a built-in label-set name or an inline"),
        ],
    )
    def test_refused_with_the_field(
        self, client: TestClient, auth: dict[str, str], scene: dict[str, Any], settings: Settings,
        vocabulary: Any, expected: str,
    ) -> None:  # fmt: skip
        response = _post(client, auth, scene["id"], vocabulary)
        assert response.status_code == 422, response.text
        assert expected in _problems(response)
        assert "passwd" not in response.text
        assert _job_count(settings) == 0

    @pytest.mark.parametrize("number", ["NaN", "Infinity", "-Infinity", "1e999"])
    def test_non_finite_embedding(
        self, client: TestClient, auth: dict[str, str], scene: dict[str, Any], settings: Settings, number: str
    ) -> None:
        vocabulary = f'{{"classes": [{{"name": "a", "embedding": [1, {number}]}}]}}'
        raw = f'{{"scene_id": "{scene["id"]}", "vocabulary": {vocabulary}}}'
        response = client.post("/v1/jobs", content=raw, headers={**auth, "Content-Type": "application/json"})
        assert response.status_code == 422, response.text
        assert "vocabulary.inline.classes.0.embedding.1: Input should be a finite number" in _problems(response)
        assert _job_count(settings) == 0


# The class names of the labels are what this test reads, not their quality: a two-iteration appearance fit and a
# one-step language field keep the real pipeline short (both have their own tests; every stage still runs).
FAST = {"appearance": {"iterations": 2}, "language_field": {"epochs": 1, "min_steps": 1}}


@pytest.mark.slow
class TestRealPipeline:
    def test_inline_vocabulary_end_to_end(self, make_settings: Any, tmp_path: Path, synth_tiny: Path) -> None:
        """The real pipeline on a tiny synthetic scene, with the bundle's classes renamed and given inline
        (names, kinds and the bundle's own embeddings): the job succeeds and its instances and vocabulary.json
        carry the inline names."""
        from panogs_core.pipeline.config import PipelineConfig
        from panogs_core.pipeline.run import STAGES, run_pipeline

        folder = synth_tiny  # only read
        own = json.loads((folder / "vocabulary.json").read_text())["classes"]
        embeddings = np.load(folder / "vocabulary.npy").astype(float).tolist()
        classes = [{"name": f"my {c['name']}", "kind": c["kind"], "embedding": e} for c, e in zip(own, embeddings)]
        archive = Path(shutil.make_archive(str(tmp_path / "scene"), "zip", folder)).read_bytes()
        settings = make_settings("sqlite", stand_in=None)
        with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
            auth = new_key(settings)
            scene = make_scene(client, auth, archive)
            response = client.post(
                "/v1/jobs",
                json={"scene_id": scene["id"], "vocabulary": {"classes": classes}, "config": FAST},
                headers=auth,
            )
            assert response.status_code == 202, response.text
            job_id = response.json()["id"]
            state = _run_worker(settings, job_id, run_pipeline, PipelineConfig.from_dict, STAGES)
            job = client.get(f"/v1/jobs/{job_id}", headers=auth).json()
            assert state == JobState.SUCCEEDED, job["error"]
            names = {c["name"] for c in classes}
            instances = client.get(f"/v1/jobs/{job_id}/instances", headers=auth).json()["data"]
            assert instances
            assert {i["class_name"] for i in instances} <= names
            written = client.get(f"/v1/jobs/{job_id}/artifacts/vocabulary.json", headers=auth).json()
            assert [c["name"] for c in written["classes"]] == [c["name"] for c in classes]
            report = client.get(f"/v1/jobs/{job_id}/artifacts/report.json", headers=auth).json()
            assert report["vocabulary"] == "inline"
