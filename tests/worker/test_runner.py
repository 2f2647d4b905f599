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
from service.db.models import FitState, JobState
from service.settings import Settings
from worker import leased, runner

Env = Callable[..., leased.JobEnv]
MakeJob = Callable[..., uuid.UUID]


def _run(env: leased.JobEnv, job_id: uuid.UUID, lease: str = "task-1") -> JobState | None:
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
        assert stages[-1] == "appearance"  # the fit, after the results
        progress = [p for _, p in seen]
        assert progress == sorted(progress)
        assert 0.0 < progress[len(progress) // 2] < 1.0

    def test_heartbeat_inside_a_silent_stage(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        job_id = make_job()
        beats: list[Any] = []

        def silent(bundle: Path, out_dir: Path, config: Any, **kw: Any) -> Any:
            kw["on_progress"]("validate", 0, 1)
            # No progress calls: only the heartbeat thread writes. Wait for three distinct beats (every 0.05 s)
            # within a deadline, not a fixed sleep: on a loaded machine a beat may come late, never not at all.
            deadline = time.monotonic() + 10.0
            while len(set(beats)) < 3 and time.monotonic() < deadline:
                time.sleep(0.05)
                beats.append(read_job(settings, job_id).heartbeat_at)
            return scripted.ScriptedResult(out_dir=out_dir, instances=[])

        assert _run(make_env(silent), job_id) == JobState.SUCCEEDED
        assert len(set(beats)) >= 3


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
        assert stages_run == ["clustering", "labeling", "export", "appearance"]  # the first three were reused
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

        assert leased.with_db_retry(flaky, deadline_s=5, what="test") == "ok"
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
            leased.with_db_retry(duplicate, deadline_s=5, what="test")
        assert len(calls) == 2, "tried once, not retried"

    def test_gives_up_with_a_transient_error(self) -> None:
        def down() -> None:
            raise OperationalError("SELECT 1", {}, Exception("connection refused"))

        with pytest.raises(leased.TransientError, match="database unavailable while trying to test"):
            leased.with_db_retry(down, deadline_s=0.3, what="test")

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


RESULT_FILES = {"panoptic.ply", "labels.npz", "instances.json", "report.json"}


class TestResultsBeforeTheFit:
    """The results are recorded when the pipeline has written them; the fit goes on and ends on its own."""

    def _watch_the_fit(self, settings: Settings, on_fit: Callable[[Any, int], None]) -> Callable[..., Any]:
        def pipeline(bundle: Path, out_dir: Path, config: Any, **kw: Any) -> Any:
            outer = kw["on_progress"]

            def progress(stage: str, done: int, total: int) -> None:
                outer(stage, done, total)
                if stage == "appearance":
                    on_fit(read_job(settings, out_dir.name and uuid.UUID(out_dir.name)), done)

            return scripted.run_pipeline(bundle, out_dir, config, **{**kw, "on_progress": progress})

        return pipeline

    def test_the_results_are_recorded_before_the_fit_ends(
        self, make_env: Env, make_job: MakeJob, settings: Settings
    ) -> None:
        job_id = make_job()
        during: list[Any] = []
        pipeline = self._watch_the_fit(settings, lambda job, done: during.append(job) if done == 3 else None)
        assert _run(make_env(pipeline), job_id) == JobState.SUCCEEDED
        job = during[0]
        assert job.state == JobState.RUNNING
        assert job.results_at is not None
        assert job.fit_state == FitState.RUNNING
        assert 0.0 < job.fit_progress < 1.0, "the fit's own progress is written while it runs"
        assert {a.name for a in job.artifacts} == RESULT_FILES, "gaussians.ply waits for the fit"
        done = read_job(settings, job_id)
        assert done.fit_state == FitState.SUCCEEDED
        assert done.fit_progress == 1.0
        assert done.results_at == job.results_at
        assert {a.name for a in done.artifacts} == {*RESULT_FILES, "gaussians.ply"}

    def test_a_fit_that_fails_leaves_the_results(self, make_env: Env, make_job: MakeJob, settings: Settings) -> None:
        job_id = make_job(config={"stage_s": 0.01, "fail_at": "appearance"})
        assert _run(make_env(), job_id) == JobState.SUCCEEDED
        job = read_job(settings, job_id)
        assert job.results_at is not None
        assert job.fit_state == FitState.FAILED
        assert "scripted failure" in (job.fit_error or "")
        assert job.error_type is None, "the job's labels succeeded"
        assert {a.name for a in job.artifacts} == RESULT_FILES

    def test_a_cancel_during_the_fit_keeps_the_results(
        self, make_env: Env, make_job: MakeJob, settings: Settings
    ) -> None:
        job_id = make_job()

        def cancel(job: Any, done: int) -> None:
            if done == 1:
                update_job(settings, job_id, cancel_requested=True)

        assert _run(make_env(self._watch_the_fit(settings, cancel)), job_id) == JobState.CANCELED
        job = read_job(settings, job_id)
        assert job.results_at is not None
        assert job.fit_state == FitState.CANCELED
        assert {a.name for a in job.artifacts} == RESULT_FILES

    def test_a_time_limit_in_the_fit_fails_the_job_and_keeps_the_results(
        self, make_env: Env, make_job: MakeJob, settings: Settings
    ) -> None:
        # The stages take 0.1 s, the fit far more than the limit: a loaded host still gets its results before it.
        job_id = make_job(config={"stage_s": 0.01, "fit_s": 30.0})
        results_at: list[float] = []

        def pipeline(bundle: Path, out_dir: Path, config: Any, **kw: Any) -> Any:
            on_results = kw["on_results"]

            def record(result: Any) -> None:
                on_results(result)
                results_at.append(time.monotonic())

            return scripted.run_pipeline(bundle, out_dir, config, **{**kw, "on_results": record})

        limited = settings.model_copy(update={"job_time_limit_s": 3.0})
        assert _run(make_env(pipeline, settings_=limited), job_id) == JobState.FAILED
        job = read_job(settings, job_id)
        assert results_at, "the results came before the limit"
        assert job.error_type == "TimeLimitExceeded"
        assert job.fit_state == FitState.FAILED
        assert {a.name for a in job.artifacts} == RESULT_FILES

    def test_a_worker_lost_for_good_during_the_fit_fails_the_fit(
        self, make_env: Env, make_job: MakeJob, settings: Settings
    ) -> None:
        from service.db import crud
        from service.db.session import get_session_factory, session_scope

        job_id = make_job()
        update_job(settings, job_id, state=JobState.RUNNING, lease="gone", heartbeat_at=utcnow() - timedelta(hours=1),
                   results_at=utcnow(), fit_state=FitState.RUNNING, fit_progress=0.4)  # fmt: skip
        with session_scope(get_session_factory(settings.database)) as session:
            job = session.get(runner.Job, job_id)
            assert crud.fail_lost(session, job, utcnow(), "WorkerLost", "lost")
        job = read_job(settings, job_id)
        assert job.state == JobState.FAILED
        assert job.fit_state == FitState.FAILED
        assert job.results_at is not None


def test_fit_outcome_reads_the_pipeline_result() -> None:
    class Result:
        def __init__(self, appearance: dict[str, Any]) -> None:
            self.appearance = appearance

    assert runner.fit_outcome(Result({"state": "failed", "error": "NumericalError: NaN"})) == (
        FitState.FAILED,
        "NumericalError: NaN",
    )
    assert runner.fit_outcome(object()) == (FitState.SUCCEEDED, None)
    assert runner.fit_outcome(Result({"state": "skipped"})) == (FitState.SKIPPED, None)


def test_a_wait_on_a_shared_checkpoint_moves_the_jobs_stage_only_from_the_pipelines_thread() -> None:
    """A stage made beside the field (docs/architecture.md, "The stage table") that waits on another job's
    checkpoint must not move the job's stage (it would flip between the field and that stage); it still stops."""
    from worker.runner import _waiting

    class Tracker:
        def __init__(self) -> None:
            self.calls: list[tuple[str, str]] = []

        def on_progress(self, stage: str, done: int, total: int) -> None:
            self.calls.append(("progress", stage))

        def raise_stops(self) -> None:
            self.calls.append(("stops", threading.current_thread().name))
            raise InputError("stopped")  # what a lost lease or a shutdown raises, here any error

    tracker = Tracker()
    on_wait = _waiting(tracker)  # type: ignore[arg-type]
    on_wait("masks")
    raised: list[BaseException] = []

    def beside() -> None:
        try:
            on_wait("masks")
        except InputError as exc:
            raised.append(exc)

    thread = threading.Thread(target=beside, name="beside-language_field")
    thread.start()
    thread.join()
    assert tracker.calls == [("progress", "masks"), ("stops", "beside-language_field")]
    assert len(raised) == 1
