"""A storage outage inside the pipeline, on a real S3 server (a SeaweedFS of this module, killed and restarted): the
job goes back to the queue and its next attempt finishes it, also when the outage falls in the appearance fit,
which records any other error as its own failure and lets the results stand."""

from __future__ import annotations

import dataclasses
import secrets
import shutil
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import scripted_pipeline as scripted
from seaweedfs import SeaweedFS, seaweedfs

from service.db.models import FitState, Job, JobState
from service.db.session import get_session_factory, session_scope
from service.jobs import to_public
from service.settings import Settings
from service.storage.backends import open_storage
from worker import leased, runner

Env = Callable[..., leased.JobEnv]


@pytest.fixture(scope="module")
def s3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SeaweedFS]:
    with seaweedfs(tmp_path_factory.mktemp("seaweedfs")) as server:
        yield server


@pytest.fixture
def settings(tmp_path: Path, sqlite_template: Path, s3: SeaweedFS) -> Settings:
    """The worker tests' settings with the objects in S3 (no storage folder of the worker)."""
    (tmp_path / "data").mkdir()
    shutil.copy(sqlite_template, tmp_path / "data" / "panogs.db")
    return Settings(  # type: ignore[call-arg]
        _env_file=None, data_dir=tmp_path / "data", progress_interval_s=0, heartbeat_interval_s=0.05,
        heartbeat_timeout_s=2, transient_retry_s=1, storage_url=s3.url(f"outage-{secrets.token_hex(4)}"),
        s3_endpoint_url=s3.endpoint, s3_access_key_id=s3.access_key, s3_secret_access_key=s3.secret_key,
    )  # fmt: skip


def _outage_at(stage: str, s3: SeaweedFS) -> Callable[..., Any]:
    """The scripted pipeline with S3 killed as ``stage`` begins and restarted as soon as a storage call of the job
    has failed for it (a progress step, which stores the stage before, or a shared checkpoint's fetch or store):
    the error then goes on through the pipeline with the storage back, as after a short outage."""

    def restarting(fn: Callable[..., Any]) -> Callable[..., Any]:
        def call(*args: Any, **kwargs: Any) -> Any:
            try:
                return fn(*args, **kwargs)
            except Exception:
                if s3.proc is None:
                    s3.start()
                raise

        return call

    def pipeline(*args: Any, on_progress: Callable[[str, int, int], None], shared: Any, **kw: Any) -> Any:
        def progress(name: str, done: int, total: int) -> None:
            if name == stage and not killed:
                killed.append(name)
                s3.kill()
            restarting(on_progress)(name, done, total)

        checkpoints = SimpleNamespace(fetch=restarting(shared.fetch), store=restarting(shared.store))
        return scripted.run_pipeline(*args, on_progress=progress, shared=checkpoints, **kw)

    killed: list[str] = []
    return pipeline


def _job(settings: Settings, job_id: uuid.UUID) -> Job:
    with session_scope(get_session_factory(settings.database)) as session:
        job = session.get(Job, job_id)
        assert job is not None
        session.expunge(job)
        return job


@pytest.mark.parametrize("stage", ["appearance", "clustering"])
def test_an_outage_retries_the_job_which_then_finishes(
    make_env: Env, make_job: Callable[..., uuid.UUID], settings: Settings, s3: SeaweedFS, stage: str
) -> None:
    job_id = make_job()
    env = dataclasses.replace(make_env(pipeline=_outage_at(stage, s3)), storage=open_storage(settings))
    with pytest.raises(leased.TransientError, match="object storage unavailable"):
        runner.execute_job(job_id, lease="a", worker="w", env=env)  # Celery retries the task with backoff
    handed_back = _job(settings, job_id)
    assert handed_back.state is JobState.QUEUED
    assert handed_back.fit_state is not FitState.FAILED  # the outage is not the fit's failure
    assert runner.execute_job(job_id, lease="b", worker="w", env=env) is JobState.SUCCEEDED
    done = _job(settings, job_id)
    assert done.fit_state is FitState.SUCCEEDED, done.fit_error
    assert done.fit_error is None
    # The retry took the stages the first attempt stored from the scene's store: still this job's own, not cached.
    assert to_public(done).stage_cached == dict.fromkeys(scripted.STAGES, False)
