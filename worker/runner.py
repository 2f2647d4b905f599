"""Run one job: claim it, run the pipeline with progress, heartbeats and cancellation, record the outcome.

``execute_job`` knows nothing of Celery: tests call it with a scripted pipeline and a SQLite database.

What a leased task is (errors, environment, database retries, progress tracker, heartbeat, workspace, how a
stop becomes an outcome) is ``worker/leased.py``'s, shared with the tile runner; this module keeps the job's own:

- **Claim**: a job is run by the task holding its ``lease``; every write is guarded by it (``service.db.leases``).
- **Progress**: the tracker writes the job's stage, overall progress, per-stage timings and the fit's progress.
- **Cancellation** is cooperative: the callback raises :class:`panogs_core.errors.Cancelled`, which stages let
  through, between and inside stages.
- **Resume**: the pipeline runs with ``resume=True`` in the job's own folder, so a job claimed again after its
  worker died reuses the checkpoints of the stages that finished.
- **2D maps**: a job that names the operator's models gets their folders from this worker's settings, checked
  (files present, identities read) before the pipeline starts, so a broken folder fails the job before any frame,
  naming the entry (:func:`job_map_models`). Such a job runs its scene whole (its maps serve every tile).
- **Vocabulary**: the pipeline gets a built-in label-set name or the job's inline classes, never a string that
  could name a file (:func:`worker.leased.job_vocabulary`, docs/service.md "Which request fields reach the host").
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import func, update
from sqlalchemy.orm import Session

from panogs_core.errors import PanoGSError
from panogs_core.io.run_folder import GAUSSIANS_PLY
from panogs_core.tiling.choice import TILES_OFF
from panogs_core.types import Vocabulary
from service import jobs
from service.db import crud
from service.db.base import utcnow
from service.db.models import FitState, Job, JobState, Scene
from service.db.session import session_scope
from service.errors import InvalidInput
from service.map_models import KINDS, computes_maps, entry_folders

if TYPE_CHECKING:
    from panogs_core.stages.maps2d import MapModels
from service.settings import Settings
from service.storage.workspace import Workspace
from worker import tiles
from worker.job_io import collect_artifacts, job_vocabulary
from worker.leased import (
    CancelRequested,
    JobEnv,
    LeaseLost,
    PipelineFn,
    Tracker,
    bundle_cache,
    claim_retried,
    in_workspace,
    run_leased,
    stage_fraction,
    stopping_on_storage_errors,
    without_host_paths,
    workspace_plan,
    write_retried,
)
from worker.shared_checkpoints import SceneCheckpoints

logger = logging.getLogger(__name__)

# The file the appearance fit finishes (served once the fit is done).
FITTED_FILES = frozenset({GAUSSIANS_PLY.name})


class _CheckpointsThroughStops:
    """The scene's checkpoints as the pipeline sees them: their storage errors are ``StorageStop``."""

    def __init__(self, shared: SceneCheckpoints) -> None:
        self.fetch = stopping_on_storage_errors(shared.fetch)
        self.store = stopping_on_storage_errors(shared.store)
        self.known_input_hash = stopping_on_storage_errors(shared.known_input_hash)
        self.keep_input_hash = stopping_on_storage_errors(shared.keep_input_hash)


def load_pipeline() -> tuple[PipelineFn, tuple[str, ...], Callable[[dict[str, Any]], Any]]:
    """The core's pipeline, its stage names and the config factory the API checks a job's overrides with.

    Imports the pipeline, torch with it: a task calls this, never a prefork parent. Tests put a stand-in pipeline
    here (tests/support/pipeline_stand_in.py); no setting can.
    """
    from panogs_core.pipeline.run import STAGES, run_pipeline

    return run_pipeline, tuple(STAGES), jobs.pipeline_config


class JobRow:
    """A job's own row, as its tracker writes it: every progress column."""

    ended = "it was finished"

    def __init__(self, job_id: uuid.UUID) -> None:
        self.job_id = job_id
        self.label = f"job {job_id}"

    def fraction(self, stages: tuple[str, ...], stage: str, done: int, total: int) -> float:
        return stage_fraction(stages, stage, done, total)

    def write(self, session: Session, lease: str, values: dict[str, Any]) -> bool:
        return crud.update_running(session, self.job_id, lease, **values)


@dataclass(frozen=True)
class JobEnding:
    """How a job ends otherwise than by its own success."""

    job_id: uuid.UUID
    tracker: Tracker

    def hand_back(self) -> None:
        self.tracker.close_stage(time.monotonic())
        with session_scope(self.tracker.env.session_factory) as session:
            crud.release_job(session, self.job_id, self.tracker.lease, **self.tracker.stage_values())

    def handed_back(self) -> JobState:
        return JobState.QUEUED

    def canceled(self, exc: CancelRequested) -> JobState | None:
        tracker = self.tracker
        tracker.close_stage(time.monotonic())
        fit = {"fit_state": FitState.CANCELED, "fit_error": str(exc)} if tracker.results_ready else {}
        return _finish(self.job_id, tracker.lease, tracker.env, JobState.CANCELED, **tracker.stage_values(), **fit)

    def failed(self, error_type: str, message: str, *, in_run: bool) -> JobState | None:
        """Record the job failed with ``error_type: message`` and the stage times so far (a fit under way fails
        with it, with the error, when the run raised it)."""
        tracker = self.tracker
        tracker.close_stage(time.monotonic())
        fit = {"fit_state": FitState.FAILED, "fit_error": f"{error_type}: {message}"}
        return _finish(
            self.job_id,
            tracker.lease,
            tracker.env,
            JobState.FAILED,
            **tracker.stage_values(),
            error_type=error_type,
            error_message=message,
            **(fit if in_run and tracker.results_ready else {}),
        )


def execute_job(job_id: uuid.UUID, *, lease: str, worker: str, env: JobEnv) -> JobState | None:
    """Run job ``job_id`` under ``lease``; returns the state it ended in, or None when it was not ours to run.

    Raises:
        TransientError: the database or the object storage stayed away; retry the task later.
    """
    claim = claim_retried(
        env, "the job", lambda: _claim(job_id, lease, worker, env), lambda job: (job.attempts, "the job")
    )
    job = claim.row
    if job is None:
        return None
    if claim.worn_out is not None:
        _finish(job_id, lease, env, JobState.FAILED, error_type="WorkerLost", error_message=claim.worn_out)
        return JobState.FAILED
    logger.info("job %s: running (attempt %d, worker %s)", job_id, job.attempts, worker)
    timings, cached = dict(job.stage_timings or {}), list(job.cached_stages or [])
    tracker = Tracker(
        row=JobRow(job_id),
        lease=lease,
        env=env,
        timings=timings,
        cached=cached,
        computed_before=frozenset(timings) - set(cached),
    )
    return _run(job, tracker, env)


def _claim(job_id: uuid.UUID, lease: str, worker: str, env: JobEnv) -> Job | None:
    with session_scope(env.session_factory) as session:
        stale = crud.stale_cutoff(env.settings.heartbeat_timeout_s)
        job = crud.claim_job(session, job_id, lease, worker, stale)
        if job is None:
            current = session.get(Job, job_id)
            if current is not None and current.cancel_requested and not current.state.is_terminal:
                crud.cancel_unclaimed(session, job_id)
            logger.info("job %s: not claimed (%s)", job_id, current.state if current else "no such job")
        return job


def _run(job: Job, tracker: Tracker, env: JobEnv) -> JobState | None:
    try:
        with session_scope(env.session_factory) as session:
            scene = crud.get_scene(session, job.scene_id)
            vocabulary = job_vocabulary(session, job)
    except PanoGSError as exc:
        return _finish(
            job.id, tracker.lease, env, JobState.FAILED, error_type=type(exc).__name__, error_message=str(exc)
        )
    if scene is None:
        return _finish(
            job.id,
            tracker.lease,
            env,
            JobState.FAILED,
            error_type="SceneMissing",
            error_message=f"scene {job.scene_id} no longer exists",
        )
    plan = workspace_plan(env, "job", job.scene_id, scene.bundle_path)
    ending = JobEnding(job.id, tracker)
    archive_sha256 = scene.bundle_sha256

    def body(work: Workspace) -> JobState | None:
        try:
            return run_leased(tracker, ending, work, lambda: _run_in(job, tracker, vocabulary, work, archive_sha256))
        finally:
            if tracker.shared is not None:
                tracker.shared.release_all()  # a stage that never stored its key: the next taker computes it

    return in_workspace(tracker, ending, plan, body)


def _waiting(tracker: Tracker) -> Callable[[str], None]:
    """The shared checkpoints' ``on_wait(stage)`` for a job run on this thread: a wait on another job's checkpoint
    shows as the job's stage; from a stage made beside the field (another thread, docs/architecture.md "The stage
    table"), it only stops the job when it must, and the job's stage stays the one the run has reached."""
    pipeline_thread = threading.current_thread()

    def on_wait(stage: str) -> None:
        if threading.current_thread() is pipeline_thread:
            tracker.on_progress(stage, 0, 1)
        else:
            tracker.raise_stops()

    return on_wait


def _run_in(
    job: Job, tracker: Tracker, vocabulary: str | Vocabulary | None, work: Workspace, archive_sha256: str | None
) -> JobState | None:
    """Run the job's pipeline in ``work``; ``archive_sha256``: the scene's upload's, from which the stage keys start
    (``worker/shared_checkpoints.py``: no job hashes an uploaded bundle)."""
    env = tracker.env
    bundles = bundle_cache(env)
    shared = SceneCheckpoints(
        env.storage,
        job.scene_id,
        owner=f"job {job.id} lease {tracker.lease}",
        lease_s=env.settings.heartbeat_timeout_s,
        on_wait=_waiting(tracker),
        on_stored=lambda size: _count_scene_bytes(env, job.scene_id, size),
        local_copies=None if bundles is None else bundles.stages_folder(job.scene_id),
        archive_sha256=archive_sha256,
    )
    tracker.shared = shared
    work.push.skip = shared.kept  # a checkpoint the scene's store keeps is not stored again with the job
    config = env.make_config(job.config or {})
    map_models = job_map_models(job.maps, env.settings)
    if map_models is not None:
        extra: dict[str, Any] = {"map_models": map_models}
    elif tiles.tiles_asked(job) != TILES_OFF and tiles.plan_and_fan_out(job, tracker, work, config):
        return JobState.RUNNING  # its tiles' tasks run it now, and its merge ends it
    else:
        extra = {}  # a pipeline without the 2D-maps keyword (the tests' stand-ins) still runs jobs that name none
    with tracker.beating():
        result = env.pipeline(
            work.bundle,
            work.out,
            config,
            vocabulary=vocabulary,
            on_progress=stopping_on_storage_errors(tracker.on_progress),
            resume=True,
            on_results=stopping_on_storage_errors(lambda _result: _record_results(job.id, tracker, work.out)),
            shared=_CheckpointsThroughStops(shared),
            **extra,
        )
    tracker.push_outputs()
    return _succeeded(job, tracker, work, result)


def job_map_models(maps: dict[str, Any] | None, settings: Settings) -> MapModels | None:
    """The ``MapModels`` of a job's named entries (their folders from this worker's settings), or None when it
    names none; each folder is checked first (config and weights present, identity readable), without torch.

    Raises:
        ModelLoadError: an entry this worker does not hold, or whose folder cannot be loaded, naming the entry,
            its folder and what is missing.
    """
    if not computes_maps(maps):
        return None
    from panogs_core.stages.maps2d import MapModels, ModelLoadError, identify_models

    try:
        folders = entry_folders(settings, maps)
    except InvalidInput as exc:
        raise ModelLoadError(exc.message) from exc
    assert maps is not None
    for kind in KINDS:
        folder = folders[kind]
        if folder is None:
            continue
        try:
            identify_models(folder if kind == "masks" else None, folder if kind == "features" else None)
        except ModelLoadError as exc:
            raise ModelLoadError(f"map model entry {maps[kind]!r} ({kind} model): {exc}") from exc
    return MapModels(masks=folders["masks"], features=folders["features"])


def _succeeded(job: Job, tracker: Tracker, work: Workspace, result: Any) -> JobState | None:
    """Record the job succeeded with its artifacts, its stage times and how its fit ended."""
    env = tracker.env
    tracker.close_stage(time.monotonic())
    timings = merge_timings(tracker.timings, getattr(result, "timings", None))
    fit_state, fit_error = fit_outcome(result)
    if fit_error is not None:
        fit_error = without_host_paths(fit_error, env, work.bundle, work.out)[:10_000]
        logger.info("job %s: results ready, the Gaussian fit %s: %s", job.id, fit_state, fit_error)
    exclude = frozenset() if fit_state.scene_ready else FITTED_FILES  # an unfitted scene is not served
    artifacts = collect_artifacts(job.id, work.out, env.storage, exclude=exclude)
    return _finish(
        job.id,
        tracker.lease,
        env,
        JobState.SUCCEEDED,
        artifacts=artifacts,
        progress=1.0,
        stage=None,
        **{**tracker.stage_values(), "stage_timings": timings},
        results_at=func.coalesce(Job.results_at, utcnow()),  # a pipeline without on_results: now
        fit_state=fit_state,
        fit_progress=1.0 if fit_state.scene_ready else tracker.fit_progress,
        fit_error=fit_error,
    )


def _count_scene_bytes(env: JobEnv, scene_id: uuid.UUID, size: int) -> None:
    """A checkpoint stored under the scene counts in its size (the tenant's storage quota)."""

    def write(session: Session) -> None:
        session.execute(update(Scene).where(Scene.id == scene_id).values(size_bytes=Scene.size_bytes + size))
        session.commit()

    write_retried(env, "count a shared checkpoint", write)


def fit_outcome(result: Any) -> tuple[FitState, str | None]:
    """How the pipeline's appearance fit ended (``PipelineResult.appearance``: ``state``, ``error``).

    A pipeline that says nothing of a fit (one without it) counts as fitted: its outputs are final when it returns.
    """
    appearance = getattr(result, "appearance", None)
    if not isinstance(appearance, Mapping):
        return FitState.SUCCEEDED, None
    try:
        state = FitState(str(appearance.get("state", FitState.SUCCEEDED.value)))
    except ValueError:
        state = FitState.SUCCEEDED
    if state in (FitState.RUNNING, FitState.CANCELED):  # returned, so it did not stop; a running one never ended
        state = FitState.FAILED
    error = appearance.get("error")
    return state, (str(error) if error is not None else None)


def _record_results(job_id: uuid.UUID, tracker: Tracker, out_dir: Path) -> None:
    """The pipeline wrote its results (before the fit): record their artifacts and ``results_at``; the
    instances, queries and viewer scene answer from here on. Called in the pipeline's thread.

    Raises:
        LeaseLost: another task holds the job now.
    """
    env = tracker.env
    tracker.push_outputs()
    artifacts = collect_artifacts(job_id, out_dir, env.storage, exclude=FITTED_FILES)

    def write(session: Session) -> bool:
        return crud.record_results(session, job_id, tracker.lease, artifacts, **tracker.stage_values())

    if not write_retried(env, "record the job's results", write):
        tracker.lost = True
        raise LeaseLost(f"job {job_id}: another worker holds it now, or it was finished")
    tracker.results_ready = True
    logger.info("job %s: results ready (%d artifacts); the Gaussian fit goes on", job_id, len(artifacts))


def merge_timings(measured: dict[str, float], reported: Any) -> dict[str, float]:
    """The pipeline's own stage times over the runner's, except for stages it reused from a checkpoint.

    ``reported`` is ``PipelineResult.timings``: records with ``name``, ``wall_s`` and ``cached``, or a
    mapping of stage to seconds. A cached stage keeps the time of the attempt that computed it.
    """
    out = dict(measured)
    items = (
        reported.items() if isinstance(reported, Mapping) else [(getattr(r, "name", None), r) for r in (reported or [])]
    )
    for stage, value in items:
        seconds = getattr(value, "wall_s", value)
        if stage is None or not isinstance(seconds, int | float):
            continue
        if getattr(value, "cached", False) and stage in out:
            continue
        out[str(stage)] = round(float(seconds), 3)
    return out


def _finish(job_id: uuid.UUID, lease: str, env: JobEnv, state: JobState, **values: Any) -> JobState | None:
    def write(session: Session) -> bool:
        return crud.finish_job(session, job_id, lease, state, **values)

    if not write_retried(env, f"record the job as {state}", write):
        logger.warning("job %s: could not record %s, the job moved on without this worker", job_id, state)
        return None
    logger.info("job %s: %s", job_id, state)
    return state


def record_crash(job_id: uuid.UUID, lease: str, exc: BaseException, env: JobEnv) -> None:
    """Fail a job after an unexpected error at the task boundary (best effort; the error is re-raised
    there)."""
    message = without_host_paths(f"{type(exc).__name__}: {exc}", env)[:10_000]
    try:
        _finish(job_id, lease, env, JobState.FAILED, error_type="InternalError", error_message=message)
    except Exception:  # the original error matters more than this one
        logger.exception("job %s: could not record the crash", job_id)
