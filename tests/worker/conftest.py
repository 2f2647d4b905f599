"""Fixtures of the worker tests: a migrated SQLite database, storage in tmp_path, a job to run, a JobEnv
builder."""

from __future__ import annotations

import shutil
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import scripted_pipeline as scripted

from service.db.migrate import upgrade
from service.db.models import ApiKey, Job, JobState, Scene
from service.db.session import get_engine, get_session_factory, session_scope
from service.settings import Settings
from service.storage import Storage
from worker import leased


@pytest.fixture(scope="session")
def sqlite_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("template") / "panogs.db"
    upgrade(f"sqlite:///{path}")
    get_engine.cache_clear()
    return path


@pytest.fixture
def settings(tmp_path: Path, sqlite_template: Path) -> Settings:
    (tmp_path / "data").mkdir()
    shutil.copy(sqlite_template, tmp_path / "data" / "panogs.db")
    return Settings(  # type: ignore[call-arg]
        _env_file=None, data_dir=tmp_path / "data", progress_interval_s=0, heartbeat_interval_s=0.05,
        heartbeat_timeout_s=2, transient_retry_s=1,
    )  # fmt: skip


@pytest.fixture
def make_env(settings: Settings) -> Callable[..., leased.JobEnv]:
    def make(pipeline: Any = scripted.run_pipeline, settings_: Settings | None = None, **kw: Any) -> leased.JobEnv:
        s = settings_ or settings
        return leased.JobEnv(
            settings=s, session_factory=get_session_factory(s.database), storage=Storage(s.storage),
            pipeline=pipeline, make_config=scripted.make_config, stages=scripted.STAGES, **kw,
        )  # fmt: skip

    return make


@pytest.fixture
def make_job(settings: Settings) -> Callable[..., uuid.UUID]:
    """Insert a tenant, a scene (an empty bundle folder) and a queued job; returns the job id."""

    def make(**values: Any) -> uuid.UUID:
        storage = Storage(settings.storage)
        with session_scope(get_session_factory(settings.database)) as session:
            key = ApiKey(name="t", prefix=uuid.uuid4().hex[:12], key_hash="0" * 64)
            session.add(key)
            session.flush()
            scene_id = uuid.uuid4()
            bundle = storage.scene_dir(scene_id) / "bundle"
            bundle.mkdir(parents=True)
            session.add(Scene(id=scene_id, api_key_id=key.id, name="s", feature_dim=8, feature_space="x",
                              num_frames=1, has_vocabulary=False, has_ground_truth=False,
                              bundle_path=storage.rel(bundle)))  # fmt: skip
            session.flush()  # no relationship orders the inserts: the scene row must exist first
            values = {"config": {"stage_s": 0.01}, **values}
            job = Job(
                api_key_id=key.id, scene_id=scene_id, state=values.pop("state", JobState.QUEUED), queue="cpu",
                request_hash="h", stage_timings={}, **values,
            )  # fmt: skip
            session.add(job)
            session.commit()
            return job.id

    return make
