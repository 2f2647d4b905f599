"""execute_job with the scripted pipeline on SQLite: progress, timings, artifacts, cancel, failures, resume,
leases."""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scripted_pipeline as scripted
from declared_run import write_declared_files
from sqlalchemy import create_engine, text
from sqlalchemy.exc import IntegrityError, OperationalError
from wk_helpers import read_job, update_job

from panogs_core.errors import InputError
from panogs_core.io.run_folder import DOWNLOADABLE
from service.db.base import utcnow
from service.db.models import JobState
from service.settings import Settings
from worker import runner

Env = Callable[..., runner.JobEnv]
MakeJob = Callable[..., uuid.UUID]


def _run(env: runner.JobEnv, job_id: uuid.UUID, lease: str = "task-1") -> JobState | None:
    return runner.execute_job(job_id, lease=lease, worker="test", env=env)


class TestSuccess:
    def test_records_everything(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        job_id = make_job()
        assert _run(make_env(), job_id) == JobState.SUCCEEDED
        job = read_job(settings, job_id)
        assert job.state == JobState.SUCCEEDED
        assert job.progress == 1.0
        assert job.stage is None
        assert set(job.stage_timings) == set(scripted.STAGES)
        assert job.attempts == 1
        assert job.started_at is not None
        assert job.finished_at is not None
        names = {a.name for a in job.artifacts}
        assert names == {"panoptic.ply", "gaussians.ply", "labels.npz", "instances.json", "report.json"}
        ply = next(a for a in job.artifacts if a.name == "panoptic.ply")
        assert ply.size_bytes == (settings.storage / ply.path).stat().st_size
        assert len(ply.sha256) == 64

    def test_artifacts_are_the_declared_downloads(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        """Given every file the run folder declares, the worker records exactly those the API serves."""
        job_id = make_job()

        def every_file(bundle: Path, out_dir: Path, config: Any, **kw: Any) -> Any:
            write_declared_files(out_dir)
            return scripted.ScriptedResult(out_dir=out_dir, instances=[])

        assert _run(make_env(every_file), job_id) == JobState.SUCCEEDED
        recorded = {a.name: a.media_type for a in read_job(settings, job_id).artifacts}
        assert recorded == {name: spec.media_type for name, spec in DOWNLOADABLE.items()}

    def test_progress_written_while_running(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        job_id = make_job()
        seen: list[tuple[str | None, float]] = []

        def pipeline(bundle: Path, out_dir: Path, config: Any, **kw: Any) -> Any:
            def spy(stage: str, done: int, total: int) -> None:
                kw["on_progress"](stage, done, total)
                job = read_job(settings, job_id)
                seen.append((job.stage, job.progress))

            return scripted.run_pipeline(bundle, out_dir, config, **{**kw, "on_progress": spy})

        assert _run(make_env(pipeline), job_id) == JobState.SUCCEEDED
        stages = [s for s, _ in seen]
        assert stages[0] == "validate"
        assert stages[-1] == "export"
        progress = [p for _, p in seen]
        assert progress == sorted(progress)
        assert 0.0 < progress[len(progress) // 2] < 1.0

    def test_heartbeat_inside_a_silent_stage(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        job_id = make_job()
        beats: list[Any] = []

        def silent(bundle: Path, out_dir: Path, config: Any, **kw: Any) -> Any:
            kw["on_progress"]("validate", 0, 1)
            for _ in range(3):
                time.sleep(0.15)  # no progress calls: only the heartbeat thread writes
                beats.append(read_job(settings, job_id).heartbeat_at)
            return scripted.ScriptedResult(out_dir=out_dir, instances=[])

        assert _run(make_env(silent), job_id) == JobState.SUCCEEDED
        assert len(set(beats)) == 3


class TestStops:
    def test_cancel_inside_a_stage(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        job_id = make_job(config={"stage_s": 0.3})
        threading.Timer(0.5, update_job, args=(settings, job_id), kwargs={"cancel_requested": True}).start()
        assert _run(make_env(), job_id) == JobState.CANCELED
        job = read_job(settings, job_id)
        assert job.state == JobState.CANCELED
        assert job.error_type is None
        assert "validate" in job.stage_timings  # the stages that finished keep their times
        assert job.artifacts == []

    def test_canceled_before_start(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        job_id = make_job(cancel_requested=True)
        assert _run(make_env(), job_id) is None
        assert read_job(settings, job_id).state == JobState.CANCELED

    def test_domain_error_fails_the_job(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        job_id = make_job(config={"stage_s": 0.01, "fail_at": "fusion"})
        assert _run(make_env(), job_id) == JobState.FAILED
        job = read_job(settings, job_id)
        assert job.error_type == "NumericalError"
        assert "fusion: scripted failure" in (job.error_message or "")

    def test_bad_config_fails_the_job(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        job_id = make_job(config={"typo": 1})
        assert _run(make_env(), job_id) == JobState.FAILED
        job = read_job(settings, job_id)
        assert job.error_type == "ConfigError"
        assert "typo" in (job.error_message or "")

    def test_time_limit(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        limited = settings.model_copy(update={"job_time_limit_s": 0.2})
        job_id = make_job(config={"stage_s": 0.2})
        assert _run(make_env(settings_=limited), job_id) == JobState.FAILED
        job = read_job(settings, job_id)
        assert job.error_type == "TimeLimitExceeded"
        assert "0.2 s" in (job.error_message or "")

    def test_shutdown_hands_the_job_back(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        job_id = make_job(config={"stage_s": 0.2})
        env = make_env()
        threading.Timer(0.3, env.shutdown.set).start()
        assert _run(env, job_id) == JobState.QUEUED
        job = read_job(settings, job_id)
        assert job.state == JobState.QUEUED
        assert job.lease is None
        assert job.enqueued_at is None  # the reaper publishes it again
        assert job.attempts == 0
        assert "validate" in job.stage_timings


class TestClaimsAndResume:
    def test_resume_after_a_lost_worker(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        job_id = make_job(config={"stage_s": 0.05})

        def dies_at_clustering(bundle: Path, out_dir: Path, config: Any, **kw: Any) -> Any:
            def progress(stage: str, done: int, total: int) -> None:
                if stage == "clustering":
                    raise SystemExit("killed")  # stands in for kill -9: nothing is recorded
                kw["on_progress"](stage, done, total)

            return scripted.run_pipeline(bundle, out_dir, config, **{**kw, "on_progress": progress})

        with pytest.raises(SystemExit):
            _run(make_env(dies_at_clustering), job_id, lease="first")
        first = read_job(settings, job_id)
        assert first.state == JobState.RUNNING
        assert first.stage == "fusion"
        # Another worker cannot take it while the heartbeat is fresh ...
        assert _run(make_env(), job_id, lease="second") is None
        # ... but can once it has gone silent, and resumes from the checkpoints.
        update_job(settings, job_id, heartbeat_at=utcnow() - timedelta(seconds=10))
        stages_run: list[str] = []

        def record(bundle: Path, out_dir: Path, config: Any, **kw: Any) -> Any:
            result = scripted.run_pipeline(bundle, out_dir, config, **kw)
            stages_run.extend(result.timings)
            return result

        assert _run(make_env(record), job_id, lease="second") == JobState.SUCCEEDED
        assert stages_run == ["clustering", "labeling", "export"]  # the first three were reused
        job = read_job(settings, job_id)
        assert job.attempts == 2
        assert job.stage_timings["validate"] == first.stage_timings["validate"]

    def test_redelivery_of_the_same_task_resumes(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        job_id = make_job()
        update_job(settings, job_id, state=JobState.RUNNING, lease="task-1", heartbeat_at=utcnow(), attempts=1)
        assert _run(make_env(), job_id, lease="task-1") == JobState.SUCCEEDED

    def test_lease_lost_stops_without_writing(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        job_id = make_job(config={"stage_s": 0.2})
        threading.Timer(0.3, update_job, args=(settings, job_id), kwargs={"lease": "usurper"}).start()
        assert _run(make_env(), job_id, lease="mine") is None
        job = read_job(settings, job_id)
        assert job.state == JobState.RUNNING
        assert job.lease == "usurper"

    def test_finished_jobs_are_left_alone(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        job_id = make_job(state=JobState.SUCCEEDED)
        assert _run(make_env(), job_id) is None
        assert _run(make_env(), uuid.uuid4()) is None

    def test_too_many_attempts(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        stale = utcnow() - timedelta(seconds=10)
        job_id = make_job(state=JobState.RUNNING, lease="old", heartbeat_at=stale, attempts=settings.max_attempts)
        assert _run(make_env(), job_id) == JobState.FAILED
        job = read_job(settings, job_id)
        assert job.error_type == "WorkerLost"
        assert "lost each time" in (job.error_message or "")


class TestTransient:
    def test_retry_until_the_database_is_back(self) -> None:
        calls = []

        def flaky() -> str:
            calls.append(1)
            if len(calls) < 3:
                raise OperationalError("SELECT 1", {}, Exception("connection refused"))
            return "ok"

        assert runner.with_db_retry(flaky, deadline_s=5, what="test") == "ok"
        assert len(calls) == 3

    def test_only_an_outage_is_waited_out(self, tmp_path: Path) -> None:
        """A real integrity error is raised at once: waiting cannot make a duplicate key unique."""
        engine = create_engine(f"sqlite:///{tmp_path / 'dup.db'}")
        with engine.begin() as conn:
            conn.execute(text("CREATE TABLE t (x INTEGER PRIMARY KEY)"))
        calls = []

        def duplicate() -> None:
            calls.append(1)
            with engine.begin() as conn:
                conn.execute(text("INSERT INTO t VALUES (1)"))

        duplicate()
        with pytest.raises(IntegrityError):
            runner.with_db_retry(duplicate, deadline_s=5, what="test")
        assert len(calls) == 2, "tried once, not retried"

    def test_gives_up_with_a_transient_error(self) -> None:
        def down() -> None:
            raise OperationalError("SELECT 1", {}, Exception("connection refused"))

        with pytest.raises(runner.TransientError, match="database unavailable while trying to test"):
            runner.with_db_retry(down, deadline_s=0.3, what="test")

    def test_merge_timings_keeps_computed_times_of_cached_stages(self) -> None:
        class Stat:
            def __init__(self, name: str, wall_s: float, cached: bool) -> None:
                self.name, self.wall_s, self.cached = name, wall_s, cached

        merged = runner.merge_timings({"a": 5.0}, [Stat("a", 0.01, True), Stat("b", 2.0, False)])
        assert merged == {"a": 5.0, "b": 2.0}
        assert runner.merge_timings({}, {"a": 1}) == {"a": 1.0}


class TestVocabulary:
    """What the pipeline is handed as the job's label set: names as names, inline classes parsed, no paths."""

    def _seen(self, make_env: Env, job_id: uuid.UUID) -> tuple[JobState | None, list[Any]]:
        seen: list[Any] = []

        def spy(bundle: Path, out_dir: Path, config: Any, **kw: Any) -> Any:
            seen.append(kw["vocabulary"])
            return scripted.run_pipeline(bundle, out_dir, config, **kw)

        return _run(make_env(spy), job_id), seen

    def test_inline_names_without_embeddings(self, make_env: Env, make_job: MakeJob) -> None:
        classes = [{"name": "lamp", "kind": "thing"}, {"name": "rug", "kind": "stuff"}]
        state, seen = self._seen(make_env, make_job(vocabulary_classes=classes))
        assert state == JobState.SUCCEEDED
        (vocabulary,) = seen
        assert (vocabulary.names, vocabulary.kinds, vocabulary.embeddings) == (
            ("lamp", "rug"),
            ("thing", "stuff"),
            None,
        )

    def test_inline_with_embeddings(self, make_env: Env, make_job: MakeJob) -> None:
        job_id = make_job(vocabulary_classes=[{"name": "lamp", "kind": "thing"}], vocabulary_embeddings=[[0, 3, 4]])
        state, seen = self._seen(make_env, job_id)
        assert state == JobState.SUCCEEDED
        np.testing.assert_allclose(seen[0].embeddings, [[0.0, 0.6, 0.8]], atol=1e-6)  # unit rows, float32

    def test_builtin_name_is_passed_as_a_name(self, make_env: Env, make_job: MakeJob) -> None:
        state, seen = self._seen(make_env, make_job(vocabulary="matterport21"))
        assert state == JobState.SUCCEEDED
        assert seen == ["matterport21"]

    @pytest.mark.parametrize("stored", ["/etc/passwd", "vocabulary.json", "../scenes/x/bundle/vocabulary.json"])
    def test_a_stored_path_fails_the_job_unread(
        self, make_env: Env, make_job: MakeJob, settings: Settings, stored: str
    ) -> None:
        job_id = make_job(vocabulary=stored)
        state, seen = self._seen(make_env, job_id)
        assert state == JobState.FAILED
        assert seen == []
        job = read_job(settings, job_id)
        assert job.error_type == "InputError"
        assert job.error_message is not None
        assert "unknown built-in label set" in job.error_message
        assert stored not in job.error_message
        assert "passwd" not in job.error_message
        assert "vocabulary.json" not in job.error_message

    def test_broken_inline_classes_fail_the_job(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        job_id = make_job(vocabulary_classes=[{"name": "a"}, {"name": "A"}])  # only a hand-written row can do this
        state, seen = self._seen(make_env, job_id)
        assert state == JobState.FAILED
        assert seen == []
        assert "duplicate class names" in (read_job(settings, job_id).error_message or "")


class TestErrorMessages:
    def test_a_failed_job_names_no_host_path(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        """The pipeline's messages name files by absolute path (the CLI user wants that); the job's owner reads
        them relative to the bundle or the output folder, with no trace of where the host keeps its files."""
        job_id = make_job()

        def fails(bundle: Path, out_dir: Path, config: Any, **kw: Any) -> Any:
            raise InputError(f"{bundle / 'scene.json'}: broken; see {out_dir / 'stages'} and {settings.storage}")

        assert _run(make_env(fails), job_id) == JobState.FAILED
        message = read_job(settings, job_id).error_message or ""
        assert message == "scene.json: broken; see stages and ."
        assert str(settings.data_dir) not in message
