"""Stage checkpoints shared by a scene's jobs, by key: a re-run that changes a late stage's settings fetches the
earlier stages, one job computes a key while another waits on its lease, a dead holder's lease is taken over,
the bytes count in the scene's size, and deleting the scene deletes them."""

from __future__ import annotations

import json
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import scripted_pipeline as scripted

from service.db.models import Job, JobState, Scene
from service.db.session import get_session_factory, session_scope
from service.jobs import to_public
from service.lifecycle import delete_scene
from service.settings import Settings
from service.storage import Storage, TreePush
from worker import leased, runner
from worker.shared_checkpoints import SceneCheckpoints

Env = Callable[..., leased.JobEnv]


def _second_job(settings: Settings, first: uuid.UUID, config: dict[str, Any]) -> uuid.UUID:
    with session_scope(get_session_factory(settings.database)) as session:
        job = session.get(Job, first)
        assert job is not None
        again = Job(api_key_id=job.api_key_id, scene_id=job.scene_id, state=JobState.QUEUED, queue="cpu",
                    request_hash="h2", stage_timings={}, config=config)  # fmt: skip
        session.add(again)
        session.commit()
        return again.id


def _shown_cached(settings: Settings, job_id: uuid.UUID) -> dict[str, bool]:
    """``stage_cached`` of the job's status as the API answers it."""
    with session_scope(get_session_factory(settings.database)) as session:
        job = session.get(Job, job_id)
        assert job is not None
        return to_public(job).stage_cached


def _scene(settings: Settings, job_id: uuid.UUID) -> Scene:
    with session_scope(get_session_factory(settings.database)) as session:
        job = session.get(Job, job_id)
        assert job is not None
        scene = session.get(Scene, job.scene_id)
        assert scene is not None
        return scene


def test_a_rerun_with_other_clustering_settings_reuses_the_earlier_stages(
    make_env: Env, make_job: Callable[..., uuid.UUID], settings: Settings
) -> None:
    first = make_job(config={"stage_s": 0.01, "settings": {"clustering": 1}})
    env = make_env()
    assert runner.execute_job(first, lease="a", worker="w", env=env) is JobState.SUCCEEDED
    size_after_first = _scene(settings, first).size_bytes
    assert size_after_first > 0  # the stored checkpoints count in the scene's size
    second = _second_job(settings, first, {"stage_s": 0.01, "settings": {"clustering": 2}})
    assert runner.execute_job(second, lease="b", worker="w", env=env) is JobState.SUCCEEDED
    reused = scripted.CACHED[str(env.storage.job_dir(second))]
    assert reused == {"validate", "primitives", "fusion"}  # clustering and every later stage computed again
    assert _shown_cached(settings, first) == dict.fromkeys(scripted.STAGES, False)  # the first computed each
    shown = _shown_cached(settings, second)  # the job's status says which stages came from the first job
    assert shown == {stage: stage in reused for stage in scripted.STAGES}
    assert _scene(settings, first).size_bytes > size_after_first  # the new keys' checkpoints
    storage = Storage(settings.storage)
    scene_id = _scene(settings, first).id
    stored = [o.key for o in storage.objects.list_objects(f"scenes/{scene_id}/stages/")]
    assert sum(k.startswith(f"scenes/{scene_id}/stages/clustering/") for k in stored) == 2  # one per key
    assert not [k for k in stored if k.endswith(".lease")]  # every lease released
    for job_id in (first, second):  # one copy: the job's checkpoint and the scene's are two names of the same bytes
        fusion = env.storage.job_dir(job_id) / "stages" / "fusion.done"
        (kept,) = [k for k in stored if k.startswith(f"scenes/{scene_id}/stages/fusion/")]
        assert fusion.stat().st_ino == storage.objects.path(kept).stat().st_ino  # type: ignore[attr-defined]
    with session_scope(get_session_factory(settings.database)) as session:
        scene = session.get(Scene, scene_id)
        assert scene is not None
        delete_scene(session, storage, scene)
    assert list(storage.objects.list_objects(f"scenes/{scene_id}/")) == []


def _shared(settings: Settings, scene_id: uuid.UUID, owner: str, **kw: Any) -> SceneCheckpoints:
    return SceneCheckpoints(
        Storage(settings.storage), scene_id, owner, lease_s=kw.pop("lease_s", 5.0), poll_s=0.05, **kw
    )


def test_a_second_job_waits_for_the_key_another_computes(settings: Settings, tmp_path: Path) -> None:
    scene_id = uuid.uuid4()
    computing = _shared(settings, scene_id, "first")
    waiting_polls: list[str] = []
    waiting = _shared(settings, scene_id, "second", on_wait=waiting_polls.append)
    assert computing.fetch("fusion", "k1", tmp_path / "a.npz") is False  # nobody has it: this one computes it
    made = tmp_path / "made.npz"
    made.write_bytes(b"the checkpoint")

    def finish_later() -> None:
        time.sleep(0.4)
        computing.store("fusion", "k1", made)

    thread = threading.Thread(target=finish_later)
    thread.start()
    assert waiting.fetch("fusion", "k1", tmp_path / "b.npz") is True  # waited, then fetched: computed once
    thread.join()
    assert (tmp_path / "b.npz").read_bytes() == b"the checkpoint"
    assert waiting_polls  # it went through the job's progress callback while it waited
    assert waiting.reused == ["fusion"]


def test_a_dead_holders_lease_is_taken_over(settings: Settings, tmp_path: Path) -> None:
    scene_id = uuid.uuid4()
    dead = _shared(settings, scene_id, "dead", lease_s=0.3)
    assert dead.fetch("fusion", "k1", tmp_path / "a.npz") is False  # then its worker is killed: no store, no release
    time.sleep(0.5)
    other = _shared(settings, scene_id, "other", lease_s=0.3)
    assert other.fetch("fusion", "k1", tmp_path / "b.npz") is False  # the stale lease is its now: it computes
    assert not (tmp_path / "b.npz").exists()  # nothing half-written was read


def test_the_bundle_hash_is_kept_once_and_read_only_when_made_by_the_same_rule(settings: Settings) -> None:
    from panogs_core.pipeline.input_hash import HASH_RULE

    scene_id = uuid.uuid4()
    first, later = _shared(settings, scene_id, "first"), _shared(settings, scene_id, "later")
    assert later.known_input_hash() is None  # nothing kept yet: the job hashes the bundle
    first.keep_input_hash("a" * 64)
    later.keep_input_hash("b" * 64)  # the first writer's stays (every job of the scene computes the same)
    assert later.known_input_hash() == "a" * 64
    objects = Storage(settings.storage).objects
    key = f"scenes/{scene_id}/stages/input.json"
    for kept in ({"rule": "sha1:other", "sha256": "a" * 64}, {"rule": HASH_RULE, "sha256": "../x"}, "junk"):
        objects.delete(key)
        objects.put_bytes(key, json.dumps(kept).encode())
        assert later.known_input_hash() is None, kept  # another rule's hash, or not a hash: computed again


def test_an_uploaded_scenes_jobs_start_from_its_archives_hash_and_a_kept_hash_comes_first(settings: Settings) -> None:
    """A scene made from an upload knows its archive's SHA-256: every job of it, the first included, has the keys'
    hash without reading the bundle; a hash a job kept (the scene's checkpoints are filed under it) stays first."""
    from panogs_core.pipeline.input_hash import HASH_RULE
    from worker.shared_checkpoints import archive_input_hash

    scene_id, archive = uuid.uuid4(), "0123456789abcdef" * 4
    first = _shared(settings, scene_id, "first", archive_sha256=archive)
    derived = first.known_input_hash()
    assert derived == archive_input_hash(archive)
    assert derived is not None
    assert len(derived) == 64
    assert derived != archive  # its own rule's value, not the archive's
    assert archive_input_hash("f" * 64) != derived  # another archive, another hash
    assert _shared(settings, scene_id, "later", archive_sha256=archive).known_input_hash() == derived
    assert _shared(settings, scene_id, "odd", archive_sha256="../x").known_input_hash() is None  # not a SHA-256
    objects = Storage(settings.storage).objects
    objects.put_bytes(
        f"scenes/{scene_id}/stages/input.json", json.dumps({"rule": HASH_RULE, "sha256": "c" * 64}).encode()
    )
    assert first.known_input_hash() == "c" * 64


def test_a_checkpoint_being_stored_is_not_pushed_with_the_job(settings: Settings, tmp_path: Path) -> None:
    """The pipeline renames a checkpoint into place and stores it from its writer thread while the next stage's
    progress pushes the job's folder: a push that falls between the rename and the end of the upload must not
    store a copy under the job's prefix."""
    scene_id, job_id = uuid.uuid4(), uuid.uuid4()
    out = tmp_path / "out"
    (out / "stages").mkdir(parents=True)
    shared = _shared(settings, scene_id, "job")
    storage = shared.storage
    push = TreePush(storage, out, storage.job_prefix(job_id))
    push.skip = shared.kept
    path = out / "stages" / "language_field.npz"
    assert shared.fetch("language_field", "k1", path) is False  # a miss: this job computes it
    pushed_while_storing: list[int] = []
    put_linked = storage.put_linked

    def slow_upload(key: str, source: Path) -> Any:
        pushed_while_storing.append(push.push())  # the next stage's progress, during the upload
        return put_linked(key, source)

    storage.put_linked = slow_upload  # type: ignore[method-assign]
    path.write_bytes(b"the field")  # renamed into place by the writer thread
    push.push()  # the progress step between the rename and the store
    shared.store("language_field", "k1", path)
    assert pushed_while_storing == [0]
    assert list(storage.objects.list_objects(storage.job_prefix(job_id))) == []
    assert [i.key for i in storage.objects.list_objects(f"scenes/{scene_id}/stages/")] == [
        f"scenes/{scene_id}/stages/language_field/k1.ckpt"
    ]


def test_a_checkpoint_never_stored_is_pushed_with_the_job(settings: Settings, tmp_path: Path) -> None:
    storage = Storage(settings.storage)
    job_id = uuid.uuid4()
    out = tmp_path / "out"
    out.mkdir()
    shared = _shared(settings, uuid.uuid4(), "job")
    push = TreePush(storage, out, storage.job_prefix(job_id))
    push.skip = shared.kept
    path = out / "fusion.npz"
    assert shared.fetch("fusion", "k1", path) is False
    path.write_bytes(b"fused")
    assert push.push() == 0  # on its way to the scene's store
    shared.release_all()  # the job stopped before storing it: the job's folder keeps it
    assert push.push() == len(b"fused")
    assert [i.key for i in storage.objects.list_objects(storage.job_prefix(job_id))] == [
        f"{storage.job_prefix(job_id)}fusion.npz"
    ]


def test_a_scenes_computed_2d_maps_are_computed_once_and_fetched_by_its_next_job(
    settings: Settings, synth_tiny: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The 2D maps are a folder, not a stage file: they travel through the scene's store as one archive, so the
    scene's next job (another run folder, another worker) loads no model and reads the same maps."""
    pytest.importorskip("transformers")
    from bundle_copies import without_maps
    from tiny_models import TINY_MAPS, tiny_clip, tiny_sam

    from panogs_core.io.bundle import open_bundle
    from panogs_core.stages.maps2d import MapModels, Maps2DConfig
    from panogs_core.stages.maps2d import runner as maps_runner
    from panogs_core.stages.maps2d.stage import with_computed_maps

    bundle = open_bundle(without_maps(synth_tiny, tmp_path / "capture"))
    cfg = Maps2DConfig(**TINY_MAPS, device="cpu")
    models = MapModels(masks=str(tiny_sam(tmp_path / "sam")), features=str(tiny_clip(tmp_path / "clip")))
    scene_id = uuid.uuid4()
    first = with_computed_maps(bundle, tmp_path / "job1" / "stages", cfg, models, lambda *_: None,
                               shared=_shared(settings, scene_id, "job1"))  # fmt: skip
    objects = Storage(settings.storage).objects
    stored = [o.key for o in objects.list_objects(f"scenes/{scene_id}/stages/")]
    assert len(stored) == 1
    assert stored[0].startswith(f"scenes/{scene_id}/stages/maps_2d/")

    def no_loading(*_args: object) -> None:
        raise AssertionError("the scene's maps were not fetched: a model was loaded")

    monkeypatch.setattr(maps_runner, "load_models", no_loading)
    second_store = _shared(settings, scene_id, "job2")
    reused: list[bool] = []
    second = with_computed_maps(bundle, tmp_path / "job2" / "stages", cfg, models, lambda *_: None,
                                shared=second_store, on_reused=lambda: reused.append(True))  # fmt: skip
    assert reused == [True]
    assert second_store.reused == ["maps_2d"]
    assert second.feature_space == first.feature_space
    for frame_a, frame_b in zip(first.frames, second.frames, strict=True):
        assert (first.read_masks(frame_a) == second.read_masks(frame_b)).all()
        assert (first.read_features(frame_a) == second.read_features(frame_b)).all()
    assert not list((tmp_path / "job2" / "stages" / "maps_2d").glob("*.tar"))  # unpacked, the archive gone
