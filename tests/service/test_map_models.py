"""The operator's 2D models in the service: entries in the settings, named (never as paths) by jobs, checked by the
API, resolved and checked by the worker before the pipeline runs, and the text tower of a features entry answering
free text on a scene whose features it computed.

The model folders are tiny random CLIP and SAM models saved with ``save_pretrained`` (tests/core's builders), so
the folders go through exactly the checks a real checkpoint's folder does.
"""

from __future__ import annotations

import importlib.util
import shutil
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
import scripted_pipeline as scripted
from bundle_copies import without_maps
from fastapi.testclient import TestClient
from pydantic import ValidationError
from svc_helpers import RecordingSender, make_scene, mark_succeeded, new_key
from tiny_models import TINY_MAPS

from service.api_app import create_app
from service.db.models import Job, JobState, Scene
from service.db.session import get_session_factory, session_scope
from service.settings import Settings
from service.storage import Storage
from worker import leased, runner

REPO = Path(__file__).resolve().parents[2]


def _builders() -> ModuleType:
    """The builders of the tiny models the core tests load (``tiny_clip`` / ``tiny_sam``): tests/support's module
    where it exists, else the core test module that defined them first."""
    try:
        import tiny_models  # type: ignore[import-not-found,unused-ignore]
    except ImportError:
        pass
    else:
        return tiny_models
    spec = importlib.util.spec_from_file_location("maps2d_builders", REPO / "tests/core/test_maps2d_models.py")
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def folders(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A tiny SAM, a tiny CLIP (8-d, the tiny bundle's width) and another CLIP of other weights."""
    pytest.importorskip("transformers")
    build = _builders()
    root = tmp_path_factory.mktemp("map-models")
    return {
        "sam": build.tiny_sam(root / "sam"),
        "clip": build.tiny_clip(root / "clip", projection_dim=8),
        "other-clip": build.tiny_clip(root / "other-clip", seed=1, projection_dim=8),
    }


def _entries(folders: dict[str, Path]) -> dict[str, Any]:
    return {
        "slimsam": {"kind": "masks", "path": str(folders["sam"])},
        "clip-b16": {"kind": "features", "path": str(folders["clip"])},
    }


def _post(client: TestClient, auth: dict[str, str], scene_id: str, maps: Any = None, **extra: Any) -> Any:
    body = {"scene_id": scene_id, **({"maps": maps} if maps is not None else {}), **extra}
    return client.post("/v1/jobs", json=body, headers=auth)


def _message(response: Any) -> str:
    body = response.json()
    return " | ".join([body["message"], *(body.get("problems") or [])])


def _scene_lacks(settings: Settings, scene_id: str, **lacks: bool) -> None:
    """Record that a scene's bundle lacks maps, as the scene step does for a bundle of colour and depth alone."""
    with session_scope(get_session_factory(settings.database)) as session:
        row = session.get(Scene, uuid.UUID(scene_id))
        assert row is not None
        row.has_feature_maps = not lacks.get("features", False)
        row.has_mask_maps = not lacks.get("masks", False)
        session.commit()


class TestSettings:
    def test_entries_parsed_from_the_environment(self, monkeypatch: pytest.MonkeyPatch) -> None:
        monkeypatch.setenv(
            "PANOGS_MAP_MODELS",
            '{"slimsam": {"kind": "masks", "path": "/models/slimsam-77"}, '
            '"clip-b16": {"kind": "features", "path": "/models/clip-vit-base-patch16"}}',
        )
        settings = Settings(_env_file=None)  # type: ignore[call-arg]
        assert settings.map_models["slimsam"].path == "/models/slimsam-77"
        assert settings.map_model_names("masks") == ["slimsam"]
        assert settings.map_model_names("features") == ["clip-b16"]

    def test_empty_means_none(self, monkeypatch: pytest.MonkeyPatch) -> None:
        monkeypatch.setenv("PANOGS_MAP_MODELS", "")  # what compose passes when it is unset
        monkeypatch.setenv("PANOGS_MAPS_QUEUE", "")
        settings = Settings(_env_file=None)  # type: ignore[call-arg]
        assert settings.map_models == {}
        assert settings.maps_queue is None

    @pytest.mark.parametrize(
        ("value", "needles"),
        [
            ('{"slimsam": {"kind": "mask", "path": "/m"}}', ["slimsam", "kind", "'masks' or 'features'"]),
            ('{"clip": {"kind": "features", "path": "models/clip"}}', ["'clip'", "not absolute", "models/clip"]),
            ('{"clip": {"kind": "features"}}', ["clip", "path", "Field required"]),
            ('{"clip": {"kind": "features", "path": "/m", "url": "x"}}', ["clip", "url"]),
            ('{"../x": {"kind": "features", "path": "/m"}}', ["'../x'", "entry name"]),
            ('{"clip": ', ["not JSON"]),
        ],
    )
    def test_refused_naming_the_entry(self, monkeypatch: pytest.MonkeyPatch, value: str, needles: list[str]) -> None:
        monkeypatch.setenv("PANOGS_MAP_MODELS", value)
        with pytest.raises(ValidationError) as caught:
            Settings(_env_file=None)  # type: ignore[call-arg]
        for needle in needles:
            assert needle in str(caught.value)

    def test_maps_queue_is_a_declared_queue(self, monkeypatch: pytest.MonkeyPatch) -> None:
        monkeypatch.setenv("PANOGS_MAPS_QUEUE", "maps")
        with pytest.raises(ValidationError, match="maps_queue"):
            Settings(_env_file=None)  # type: ignore[call-arg]


ENTRIES = {
    "slimsam": {"kind": "masks", "path": "/models/slimsam"},
    "sam-vit-h": {"kind": "masks", "path": "/models/sam-vit-h"},
    "clip-b16": {"kind": "features", "path": "/models/clip-b16"},
}


@pytest.fixture
def declared(make_settings: Callable[..., Settings]) -> Settings:
    return make_settings("postgres", map_models=ENTRIES)


@pytest.fixture
def api(declared: Settings, sender: RecordingSender) -> Iterator[TestClient]:
    with TestClient(create_app(declared, sender=sender, run_reaper=False)) as c:
        yield c


def test_the_entries_are_listed_by_kind_without_their_folders(make_settings: Callable[..., Settings]) -> None:
    """``GET /v1/map-models``: what the app's upload form offers; names only, and only to a signed-in tenant."""
    for entries, listed in ((ENTRIES, {"masks": ["sam-vit-h", "slimsam"], "features": ["clip-b16"]}), ({}, None)):
        settings = make_settings("sqlite", map_models=entries)
        with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
            assert client.get("/v1/map-models").status_code == 401
            response = client.get("/v1/map-models", headers=new_key(settings))
        assert response.status_code == 200, response.text
        assert response.json() == (listed or {"masks": [], "features": []})
        assert "/models" not in response.text


class TestJobsNameEntries:
    def test_unknown_entry_lists_the_known_ones_of_its_kind(
        self, api: TestClient, declared: Settings, tiny_zip: bytes
    ) -> None:
        auth = new_key(declared)
        scene = make_scene(api, auth, tiny_zip)
        response = _post(api, auth, scene["id"], {"masks": "sam2-large"})
        assert response.status_code == 422, response.text
        message = _message(response)
        assert "maps.masks: 'sam2-large'" in message
        assert "'sam-vit-h', 'slimsam'" in message
        assert "clip-b16" not in message  # a features entry is no masks model
        assert "/models" not in response.text  # the folders stay the operator's
        wrong_kind = _post(api, auth, scene["id"], {"features": "slimsam"})
        assert wrong_kind.status_code == 422
        assert "known: 'clip-b16'" in _message(wrong_kind)

    def test_a_path_is_no_entry(self, api: TestClient, declared: Settings, tiny_zip: bytes) -> None:
        auth = new_key(declared)
        scene = make_scene(api, auth, tiny_zip)
        for name in ("/models/slimsam", "../slimsam", str(REPO)):
            response = _post(api, auth, scene["id"], {"masks": name})
            assert response.status_code == 422, response.text
        with session_scope(get_session_factory(declared.database)) as session:
            assert session.query(Job).count() == 0

    def test_stored_shown_and_queued(
        self, make_settings: Callable[..., Settings], sender: RecordingSender, tiny_zip: bytes
    ) -> None:
        settings = make_settings("postgres", map_models=ENTRIES, maps_queue="gpu")
        with TestClient(create_app(settings, sender=sender, run_reaper=False)) as client:
            auth = new_key(settings)
            scene = make_scene(client, auth, tiny_zip)
            _scene_lacks(settings, scene["id"], features=True)
            named = _post(client, auth, scene["id"], {"features": "clip-b16"})
            assert named.status_code == 202, named.text
            assert named.json()["maps"] == {"masks": None, "features": "clip-b16"}
            whole = make_scene(client, auth, tiny_zip)
            plain = _post(client, auth, whole["id"])
            assert plain.json()["maps"] is None
        with session_scope(get_session_factory(settings.database)) as session:
            row = session.get(Job, uuid.UUID(named.json()["id"]))
            assert row is not None
            assert row.maps == {"masks": None, "features": "clip-b16"}
        queues = {args[0]: queue for _name, args, queue in sender.calls}
        assert queues == {named.json()["id"]: "gpu", plain.json()["id"]: "cpu"}

    @pytest.mark.parametrize(("lacks", "kind"), [("features", "features"), ("masks", "masks")])
    def test_scene_without_maps_needs_an_entry(
        self, api: TestClient, declared: Settings, tiny_zip: bytes, lacks: str, kind: str
    ) -> None:
        auth = new_key(declared)
        scene = make_scene(api, auth, tiny_zip)
        assert scene["has_feature_maps"]
        assert scene["has_mask_maps"]
        _scene_lacks(declared, scene["id"], **{lacks: True})
        response = _post(api, auth, scene["id"])
        assert response.status_code == 422, response.text
        message = _message(response)
        assert f"maps.{kind}:" in message
        assert "has no " + ("language feature maps" if kind == "features" else "instance mask maps") in message
        assert ("'clip-b16'" if kind == "features" else "'sam-vit-h', 'slimsam'") in message
        other = "masks" if kind == "features" else "features"
        assert f"maps.{other}:" not in message  # the kind the bundle has needs nothing
        flag = "has_feature_maps" if kind == "features" else "has_mask_maps"
        assert api.get(f"/v1/scenes/{scene['id']}", headers=auth).json()[flag] is False
        entry = "clip-b16" if kind == "features" else "slimsam"
        assert _post(api, auth, scene["id"], {kind: entry}).status_code == 202

    def test_forced_tiles_with_maps_are_refused(self, api: TestClient, declared: Settings, tiny_zip: bytes) -> None:
        auth = new_key(declared)
        scene = make_scene(api, auth, tiny_zip)
        _scene_lacks(declared, scene["id"], masks=True)
        response = _post(api, auth, scene["id"], {"masks": "slimsam"}, tiling={"tiles": "2x2"})
        assert response.status_code == 422
        assert "runs its scene whole" in _message(response)
        assert _post(api, auth, scene["id"], {"masks": "slimsam"}, tiling={"tiles": "auto"}).status_code == 202

    def test_idempotency_tells_the_maps_apart(self, api: TestClient, declared: Settings, tiny_zip: bytes) -> None:
        auth = new_key(declared)
        scene = make_scene(api, auth, tiny_zip)
        _scene_lacks(declared, scene["id"], masks=True)
        first = _post(api, {**auth, "Idempotency-Key": "k1"}, scene["id"], {"masks": "slimsam"})
        assert first.status_code == 202
        again = _post(api, {**auth, "Idempotency-Key": "k1"}, scene["id"], {"masks": "slimsam"})
        assert again.json()["id"] == first.json()["id"]
        other = _post(api, {**auth, "Idempotency-Key": "k1"}, scene["id"], {"masks": "sam-vit-h"})
        assert other.status_code == 422
        assert "already used with a different request" in _message(other)

    def test_a_kind_the_bundle_brings_names_no_model(
        self, api: TestClient, declared: Settings, tiny_zip: bytes
    ) -> None:
        auth = new_key(declared)
        scene = make_scene(api, auth, tiny_zip)
        _scene_lacks(declared, scene["id"], masks=True)
        response = _post(api, auth, scene["id"], {"masks": "slimsam", "features": "clip-b16"})
        assert response.status_code == 422, response.text
        message = _message(response)
        assert "maps.features:" in message
        assert "brings its own language feature maps" in message
        assert "maps.masks:" not in message


@pytest.mark.slow
def test_inline_embeddings_take_the_features_models_width(
    make_settings: Callable[..., Settings], tiny_zip: bytes, folders: dict[str, Path]
) -> None:
    """A scene without feature maps has no width of its own (0): inline embeddings are checked against the width
    of the features model the job names (8 for the tiny CLIP), read from its folder's config."""
    settings = make_settings("postgres", map_models=_entries(folders))
    with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
        auth = new_key(settings)
        scene = make_scene(client, auth, tiny_zip)
        _scene_lacks(settings, scene["id"], features=True)

        def inline(width: int) -> dict[str, Any]:
            return {"classes": [{"name": "chair", "embedding": [1.0] + [0.0] * (width - 1)}]}

        wrong = _post(client, auth, scene["id"], {"features": "clip-b16"}, vocabulary=inline(3))
        assert wrong.status_code == 422, wrong.text
        assert "3 values per class" in _message(wrong)
        assert "'clip-b16' writes 8-d features" in _message(wrong)
        right = _post(client, auth, scene["id"], {"features": "clip-b16"}, vocabulary=inline(8))
        assert right.status_code == 202, right.text


# The worker ---------------------------------------------------------------------------------------------------


class PipelineSpy:
    """The scripted pipeline, recording the ``map_models`` keyword the worker hands it."""

    def __init__(self) -> None:
        self.seen: list[Any] = []

    def __call__(self, *args: Any, map_models: Any = None, **kw: Any) -> Any:
        self.seen.append(map_models)
        return scripted.run_pipeline(*args, **kw)


@dataclass(frozen=True)
class _MapModelsShape:
    """The keyword's dataclass as the core declares it, for a tree where the core's wiring has not landed."""

    masks: str | None = None
    features: str | None = None
    allow_download: bool = False


@pytest.fixture
def map_models_class(monkeypatch: pytest.MonkeyPatch) -> type:
    from panogs_core.stages import maps2d

    if not hasattr(maps2d, "MapModels"):
        monkeypatch.setattr(maps2d, "MapModels", _MapModelsShape, raising=False)
    return type(maps2d.MapModels(masks="/x"))  # type: ignore[attr-defined]


def _run_worker(settings: Settings, job_id: str, pipeline: Any) -> JobState | None:
    env = leased.JobEnv(
        settings=settings, session_factory=get_session_factory(settings.database), storage=Storage(settings.storage),
        pipeline=pipeline, make_config=scripted.make_config, stages=scripted.STAGES,
    )  # fmt: skip
    return runner.execute_job(uuid.UUID(job_id), lease="t-1", worker="test", env=env)


@pytest.fixture
def quick_stages(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PANOGS_SCRIPTED_STAGE_S", "0.01")


@pytest.mark.slow
@pytest.mark.usefixtures("quick_stages")
class TestWorker:
    def _job(self, settings: Settings, tiny_zip: bytes, maps: dict[str, str]) -> str:
        """A job naming ``maps`` on a scene whose bundle lacks those kinds."""
        with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
            auth = new_key(settings)
            scene = make_scene(client, auth, tiny_zip)
            _scene_lacks(settings, scene["id"], **dict.fromkeys(maps, True))
            response = _post(client, auth, scene["id"], maps)
            assert response.status_code == 202, response.text
            return str(response.json()["id"])

    def _row(self, settings: Settings, job_id: str) -> Job:
        with session_scope(get_session_factory(settings.database)) as session:
            row = session.get(Job, uuid.UUID(job_id))
            assert row is not None
            session.expunge(row)
            return row

    def test_entries_resolve_to_the_workers_folders(
        self, make_settings: Callable[..., Settings], tiny_zip: bytes, folders: dict[str, Path], map_models_class: type
    ) -> None:
        settings = make_settings("postgres", map_models=_entries(folders))
        job_id = self._job(settings, tiny_zip, {"masks": "slimsam", "features": "clip-b16"})
        spy = PipelineSpy()
        assert _run_worker(settings, job_id, spy) == JobState.SUCCEEDED
        (got,) = spy.seen
        assert isinstance(got, map_models_class)
        assert (got.masks, got.features) == (str(folders["sam"]), str(folders["clip"]))
        assert got.allow_download is False  # an operator's entry is a folder: nothing is fetched

    def test_a_job_naming_none_gets_no_keyword(
        self, make_settings: Callable[..., Settings], tiny_zip: bytes, folders: dict[str, Path]
    ) -> None:
        settings = make_settings("postgres", map_models=_entries(folders))
        job_id = self._job(settings, tiny_zip, {})
        spy = PipelineSpy()
        assert _run_worker(settings, job_id, spy) == JobState.SUCCEEDED
        assert spy.seen == [None]

    @pytest.mark.parametrize(
        ("breakage", "needle"),
        [("weights", "no weights"), ("config", "no config.json"), ("folder", "not a folder")],
    )
    def test_a_broken_folder_fails_the_job_before_the_pipeline(
        self,
        make_settings: Callable[..., Settings],
        tiny_zip: bytes,
        folders: dict[str, Path],
        tmp_path: Path,
        breakage: str,
        needle: str,
    ) -> None:
        broken = tmp_path / "clip-broken"
        shutil.copytree(folders["clip"], broken)
        if breakage == "weights":
            for weights in broken.glob("*.safetensors"):
                weights.unlink()
        elif breakage == "config":
            (broken / "config.json").unlink()
        else:
            shutil.rmtree(broken)
        entries = {**_entries(folders), "clip-broken": {"kind": "features", "path": str(broken)}}
        settings = make_settings("postgres", map_models=entries)
        job_id = self._job(settings, tiny_zip, {"masks": "slimsam", "features": "clip-broken"})
        spy = PipelineSpy()
        assert _run_worker(settings, job_id, spy) == JobState.FAILED
        assert spy.seen == []  # no stage ran, so no frame was read
        row = self._row(settings, job_id)
        assert row.error_type == "ModelLoadError"
        assert "map model entry 'clip-broken' (features model)" in (row.error_message or "")
        assert needle in (row.error_message or "")

    def test_an_entry_the_worker_lacks_fails_the_job(
        self, make_settings: Callable[..., Settings], tiny_zip: bytes, folders: dict[str, Path]
    ) -> None:
        settings = make_settings("postgres", map_models=_entries(folders))
        job_id = self._job(settings, tiny_zip, {"masks": "slimsam"})
        worker_settings = settings.model_copy(update={"map_models": {}})
        spy = PipelineSpy()
        assert _run_worker(worker_settings, job_id, spy) == JobState.FAILED
        assert spy.seen == []
        row = self._row(settings, job_id)
        assert row.error_type == "ModelLoadError"
        assert "'slimsam'" in (row.error_message or "")
        assert "PANOGS_MAP_MODELS" in (row.error_message or "")


# Free text ----------------------------------------------------------------------------------------------------

CLASSES = [("wall", "stuff"), ("chair", "thing"), ("table", "thing")]


def _write_run(out_dir: Path, embeddings: np.ndarray, space: str) -> None:
    """A finished run's folder in ``space``: two instances per class, features near their class's embedding."""
    import json

    rng = np.random.default_rng(0)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows, feats = [], []
    for k in range(2 * len(CLASSES)):
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
    vocabulary = {"classes": [{"name": n, "kind": k} for n, k in CLASSES], "embeddings": "vocabulary.npy"}
    (out_dir / "vocabulary.json").write_text(json.dumps({**vocabulary, "space": space}))
    (out_dir / "report.json").write_text(json.dumps({"stages": []}))


QUERY: dict[str, Any] = {"text": "something to sit on", "top_k": 6, "candidates": 6, "min_score": 0.0}


@pytest.mark.slow
class TestFreeText:
    def _answer(self, settings: Settings, tiny_zip: bytes, space: str, embeddings: np.ndarray) -> tuple[Any, Path]:
        app = create_app(settings, sender=RecordingSender(), run_reaper=False)
        with TestClient(app) as client:
            auth = new_key(settings)
            scene = make_scene(client, auth, tiny_zip)
            job = client.post("/v1/jobs", json={"scene_id": scene["id"]}, headers=auth).json()
            out = Storage(settings.storage).job_dir(uuid.UUID(job["id"]))
            _write_run(out, embeddings, space)
            mark_succeeded(settings, uuid.UUID(job["id"]))
            return client.post(f"/v1/jobs/{job['id']}/query", json=QUERY, headers=auth), out  # then closed

    def test_embedded_by_the_entry_whose_folder_computed_the_space(
        self, make_settings: Callable[..., Settings], tiny_zip: bytes, folders: dict[str, Path]
    ) -> None:
        from panogs_core.io.run_folder import load_result
        from panogs_core.language.model_identity import clip_space
        from panogs_core.language.query import rank_instances
        from panogs_core.language.text_encoders import encode_labels, get_text_encoder

        space = clip_space(folders["clip"])
        tower = get_text_encoder(space, model_path=str(folders["clip"]))
        embeddings = encode_labels(tower, [n for n, _ in CLASSES])
        # The other CLIP entry is listed first: the match is by identity, not by order or by kind alone.
        entries = {
            "a-other": {"kind": "features", "path": str(folders["other-clip"])},
            **_entries(folders),
        }
        settings = make_settings("postgres", map_models=entries)
        response, out = self._answer(settings, tiny_zip, space, embeddings)
        assert response.status_code == 200, response.text
        body = response.json()
        assert body["query_kind"] == "text"
        loaded = load_result(out)
        options = {k: v for k, v in QUERY.items() if k != "text"}
        expected = rank_instances(
            loaded.instances, loaded.vocabulary, QUERY["text"], feature_space=space, encoder=tower, **options
        )
        want = {h.instance_id: h.score for h in [*expected.hits, *expected.candidates]}
        got = {h["instance_id"]: h["score"] for h in [*body["hits"], *body["candidates"]]}
        assert got.keys() == want.keys()
        np.testing.assert_allclose([got[k] for k in want], list(want.values()), atol=1e-5)
        other = get_text_encoder(clip_space(folders["other-clip"]), model_path=str(folders["other-clip"]))
        assert not np.allclose(other.encode([QUERY["text"]]), tower.encode([QUERY["text"]]), atol=1e-3)

    def test_no_entry_of_the_space_is_a_clear_422_never_another_encoder(
        self, make_settings: Callable[..., Settings], tiny_zip: bytes, folders: dict[str, Path]
    ) -> None:
        from panogs_core.language.model_identity import clip_space

        space = clip_space(folders["clip"])
        embeddings = np.eye(3, 8, dtype=np.float32)
        entries = {"a-other": {"kind": "features", "path": str(folders["other-clip"])}}
        settings = make_settings("postgres", map_models=entries)
        response, _out = self._answer(settings, tiny_zip, space, embeddings)
        assert response.status_code == 422, response.text
        message = response.json()["message"]
        assert space in message
        assert "no features entry of PANOGS_MAP_MODELS" in message
        assert "a-other: " + clip_space(folders["other-clip"]) in message
        # The text model setting holding other weights is refused too, by the encoder's own check.
        settings = make_settings("postgres", map_models=entries, text_model_path=str(folders["other-clip"]))
        response, _out = self._answer(settings, tiny_zip, space, embeddings)
        assert response.status_code == 422, response.text
        assert "holds other weights" in response.json()["message"]


# End to end -----------------------------------------------------------------------------------------------------

# The tiny models' settings (tiny_models.TINY_MAPS: every mask kept, small grids), no appearance fit.
E2E_CONFIG = {
    "maps2d": {**TINY_MAPS, "device": "cpu"},
    "appearance": {"enabled": False},
    "language_field": {"epochs": 1, "min_steps": 1},
}


@pytest.mark.slow
def test_a_bundle_of_colour_and_depth_to_labels_and_a_text_query(
    make_settings: Callable[..., Settings], synth_tiny: Path, folders: dict[str, Path], tmp_path: Path
) -> None:
    """Upload posed RGB-D alone, create a job naming the operator's entries, run the real pipeline in the worker:
    the 2D maps are computed (a stage with its timing), the job has instances, and free text is embedded by the
    features entry's text tower."""
    from panogs_core.stages import maps2d

    if not hasattr(maps2d, "MapModels"):
        pytest.skip("the core's 2D-maps stage is not wired into run_pipeline in this tree")
    from panogs_core.language.model_identity import clip_space
    from panogs_core.pipeline.config import PipelineConfig
    from panogs_core.pipeline.run import STAGES, run_pipeline

    capture = without_maps(synth_tiny, tmp_path / "capture")
    archive = Path(shutil.make_archive(str(capture), "zip", capture)).read_bytes()
    settings = make_settings("sqlite", stand_in=None, map_models=_entries(folders))
    with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
        auth = new_key(settings)
        scene = make_scene(client, auth, archive)
        assert (scene["has_feature_maps"], scene["has_mask_maps"]) == (False, False)
        refused = _post(client, auth, scene["id"], vocabulary="scannet20", config=E2E_CONFIG)
        assert refused.status_code == 422
        assert "maps.masks:" in _message(refused)
        assert "maps.features:" in _message(refused)
        maps = {"masks": "slimsam", "features": "clip-b16"}
        response = _post(client, auth, scene["id"], maps, vocabulary="scannet20", config=E2E_CONFIG)
        assert response.status_code == 202, response.text
        job_id = response.json()["id"]
        env = leased.JobEnv(
            settings=settings, session_factory=get_session_factory(settings.database),
            storage=Storage(settings.storage), pipeline=run_pipeline, make_config=PipelineConfig.from_dict,
            stages=tuple(STAGES),
        )  # fmt: skip
        state = runner.execute_job(uuid.UUID(job_id), lease="t-1", worker="test", env=env)
        job = client.get(f"/v1/jobs/{job_id}", headers=auth).json()
        assert state == JobState.SUCCEEDED, job["error"]
        assert "maps_2d" in job["stage_timings"]
        assert job["stage_cached"]["maps_2d"] is False
        assert client.get(f"/v1/jobs/{job_id}/instances", headers=auth).json()["data"]
        report = client.get(f"/v1/jobs/{job_id}/artifacts/report.json", headers=auth).json()
        assert report["feature_space"] == clip_space(folders["clip"])
        body = {"text": "a soft chair", "min_score": 0.0}
        answer = client.post(f"/v1/jobs/{job_id}/query", json=body, headers=auth)
        assert answer.status_code == 200, answer.text
        assert answer.json()["query_kind"] == "text"
