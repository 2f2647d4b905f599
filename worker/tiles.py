"""Tiled jobs on workers: the plan and fan-out in the job's own task, one task per tile, one merge (docs/service.md,
"Tiled jobs").

- **Plan**: a job whose ``tiling`` asks for tiles (``auto`` or ``NxM``) is planned by its first task
  (``panogs_core.tiling.runner.plan_run``: bounded memory, no feature map read). A plan that leaves the scene
  whole returns to the untiled path unchanged; a tiled one is saved as ``tiles/plan.json`` in the job's folder, and
  one ``job_tile`` row per tile (``queued``) plus one for the merge (``pending``) are written in the transaction
  that moves the job to stage ``tiles``; then one task per tile is published (an outbox: the reaper publishes
  what the broker missed).
- **Tiles**: each runs the core's ``run_tile`` (stages 1-8, no appearance fit) in ``tiles/<tile name>/`` of the
  job's folder, under the tile row's lease with heartbeats, resuming from its own checkpoints when a lost tile is
  run again. With object storage the task fetches only the plan and its own folder and stores its folder back.
- **Fan-in**: the tile that completes last moves the merge from ``pending`` to ``queued`` in the transaction that
  records it done (``crud.finish_tile``) and publishes it; the merge writes the scene's files with the core's
  ``merge_run`` and ends the job with its artifacts, once (``crud.finish_merge``: a guarded state move).
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

from sqlalchemy import select
from sqlalchemy.exc import DBAPIError

from panogs_core.errors import PanoGSError
from panogs_core.types import Vocabulary
from service.db import crud
from service.db.base import utcnow
from service.db.models import FitState, Job, JobState, JobTile, TileKind, TileState
from service.db.session import session_scope
from service.queue import Sender, celery_sender, dispatch_tile
from service.storage.objects import StorageError, StorageUnavailable
from worker import runner
from worker.runner import (
    CancelRequested,
    Interrupted,
    JobEnv,
    LeaseLost,
    TimeLimitExceeded,
    Tracker,
    TransientError,
    stopping_on_storage_errors,
    with_db_retry,
    without_host_paths,
)

logger = logging.getLogger(__name__)

TILES_OFF = "off"
# The merge's weight in the job's progress, as a share of all tiles' estimated bytes (ours: the merge reads labels
# and primitives only, a few percent of a tile's work on the benchmarks' buildings).
MERGE_SHARE = 0.05
TILES_KEY = "tiles/"  # the tiles' folders and the plan, under the job's folder (panogs_core.tiling.runner)


def tiles_asked(job: Job) -> str | tuple[int, int]:
    """What the job asked of the planner: ``off`` (no ``tiling``, the default), ``auto`` or ``(nx, ny)``."""
    from panogs_core.tiling.choice import parse_tiles

    tiling = job.tiling or {}
    return parse_tiles(str(tiling.get("tiles", TILES_OFF)))


def tiling_config(job: Job) -> Any:
    """The planner's settings of the job: ``TilingConfig`` with the job's ``tiling`` fields but ``tiles``."""
    from panogs_core.tiling.plan import TilingConfig

    return TilingConfig(**{k: v for k, v in (job.tiling or {}).items() if k != "tiles" and v is not None})


_SENDERS: dict[int, Sender] = {}  # one Celery app per worker process and settings, built by its first publish


def _sender(env: JobEnv) -> Sender:
    if env.sender is not None:
        return cast(Sender, env.sender)
    key = id(env.settings)
    if key not in _SENDERS:
        _SENDERS[key] = celery_sender(env.settings)
    return _SENDERS[key]


def plan_and_fan_out(job: Job, tracker: Tracker, env: JobEnv, bundle_dir: Path, out_dir: Path, config: Any) -> bool:
    """Plan the job; when the plan tiles the scene, record its tiles and publish them and return True (the job's
    task is done); False when the scene stays whole (the caller runs it as an untiled job).

    Raises:
        LeaseLost: another task holds the job now.
        InputError: tiles were forced on a bundle without geometry.
    """
    from panogs_core.io.bundle import open_bundle
    from panogs_core.tiling.runner import plan_run
    from panogs_core.tiling.tile import plan_path

    scene = open_bundle(bundle_dir)
    with tracker.beating():
        plan, _points, stats = plan_run(scene, config, tiles_asked(job), tiling_config(job), tracker.on_progress)
    if not plan.tiled:
        logger.info("job %s: the plan leaves the scene whole (%s)", job.id, plan.reason)
        return False
    path = plan_path(out_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    plan.save(path)
    tracker.push_outputs()
    rows = [
        JobTile(
            id=uuid.uuid4(),
            job_id=job.id,
            tile_index=t.index,
            kind=TileKind.TILE,
            name=t.name,
            state=TileState.QUEUED,
            weight=float(t.estimated_bytes),
            progress=0.0,
            attempts=0,
        )
        for t in plan.tiles
    ]
    merge_weight = MERGE_SHARE * sum(r.weight for r in rows)
    rows.append(
        JobTile(
            id=uuid.uuid4(),
            job_id=job.id,
            tile_index=len(rows),
            kind=TileKind.MERGE,
            name="merge",
            state=TileState.PENDING,
            weight=merge_weight,
            progress=0.0,
            attempts=0,
        )
    )
    ids = [r.id for r in rows[:-1]]

    def write() -> bool:
        with session_scope(env.session_factory) as session:
            return crud.fan_out(session, job.id, tracker.lease, rows, stage_timings={"plan": round(stats.wall_s, 3)})

    if not with_db_retry(write, deadline_s=env.settings.transient_retry_s, what="record the job's tiles"):
        raise LeaseLost(f"job {job.id}: another worker holds it now")
    logger.info("job %s: %d tiles (%s); publishing them", job.id, len(plan.tiles), plan.reason)
    for ident in ids:
        dispatch_tile(env.session_factory, _sender(env), ident, TileKind.TILE, job.queue)
    return True


@dataclass
class TileTracker(Tracker):
    """A job's tracker (progress, heartbeats, cancel, shutdown, time limit) writing to a tile's row."""

    tile_id: uuid.UUID | None = None

    def fraction(self, stage: str, done: int, total: int) -> float:
        base = stage.rsplit(" ", 1)[-1]  # run_tile names its stages "tile <k>/<K> <stage>"
        if base == "merge":
            return min(max(done / total, 0.0), 1.0) if total > 0 else 0.0
        return super().fraction(base, done, total)

    def write(self, **values: Any) -> None:
        kept = {k: values[k] for k in ("stage", "progress") if k in values}
        if "stage" in kept:
            kept["stage"] = str(kept["stage"]).rsplit(" ", 1)[-1][:64]
        assert self.tile_id is not None
        try:
            with session_scope(self.env.session_factory) as session:
                held = crud.update_tile_running(session, self.tile_id, self.job_id, self.lease, **kept)
                cancel = crud.cancel_requested(session, self.job_id)
        except DBAPIError as exc:
            logger.warning("tile %s: progress not recorded, database unavailable (%r)", self.tile_id, exc.orig)
            return
        if not held:
            self.lost = True
            raise LeaseLost(f"tile {self.tile_id}: another worker holds it now, or its job ended")
        if cancel:
            raise CancelRequested("canceled at the owner's request")


def execute_part(tile_id: uuid.UUID, *, lease: str, worker: str, env: JobEnv) -> TileState | None:
    """Run the tile or merge ``tile_id`` under ``lease``; the state it ended in, or None when it was not ours.

    Raises:
        TransientError: the database or the object storage stayed away; retry the task later.
    """
    deadline = env.settings.transient_retry_s
    row = with_db_retry(lambda: _claim(tile_id, lease, worker, env), deadline_s=deadline, what="claim the tile")
    if row is None:
        return None
    if row.attempts > env.settings.max_attempts:
        message = f"{row.kind} {row.name} was started {row.attempts - 1} times and its worker was lost each time"
        _end_job(row, lease, env, JobState.FAILED, "WorkerLost", message)
        return TileState.FAILED
    with session_scope(env.session_factory) as session:
        job = session.get(Job, row.job_id)
        scene = crud.get_scene(session, job.scene_id) if job is not None else None
        try:
            vocabulary = runner.job_vocabulary(session, job) if job is not None else None
        except PanoGSError as exc:
            _end_job(row, lease, env, JobState.FAILED, type(exc).__name__, str(exc))
            return TileState.FAILED
    if job is None or scene is None:
        _end_job(row, lease, env, JobState.FAILED, "SceneMissing", "the job's scene no longer exists")
        return TileState.FAILED
    logger.info("job %s: %s %s running (attempt %d, worker %s)", job.id, row.kind, row.name, row.attempts, worker)
    tracker = TileTracker(job_id=job.id, lease=lease, env=env, timings={}, tile_id=row.id)
    try:
        with _workspace(env, job, scene.bundle_path, row) as (bundle_dir, out_dir, push):
            tracker.push = push
            return _run_in(job, row, tracker, env, vocabulary, bundle_dir, out_dir)
    except StorageUnavailable as exc:
        with_db_retry(lambda: _release(row, lease, env), deadline_s=deadline, what="hand the tile back")
        logger.warning("job %s: %s %s: object storage unavailable, handed back: %s", job.id, row.kind, row.name, exc)
        raise TransientError(f"object storage unavailable: {exc}") from exc
    except StorageError as exc:
        _end_job(row, lease, env, JobState.FAILED, "StorageError", without_host_paths(str(exc), env)[:10_000])
        return TileState.FAILED


def _claim(tile_id: uuid.UUID, lease: str, worker: str, env: JobEnv) -> JobTile | None:
    with session_scope(env.session_factory) as session:
        stale = crud.stale_cutoff(env.settings.heartbeat_timeout_s)
        row = crud.claim_tile(session, tile_id, lease, worker, stale)
        if row is not None:
            session.expunge(row)
            return row
        current = session.get(JobTile, tile_id)
        job = session.get(Job, current.job_id) if current is not None else None
        if job is not None and job.cancel_requested and not job.state.is_terminal:
            crud.end_tiled_job(session, job.id, JobState.CANCELED)  # asked to stop while no tile ran
        logger.info("tile %s: not claimed (%s)", tile_id, current.state if current else "no such tile")
        return None


def _release(row: JobTile, lease: str, env: JobEnv) -> None:
    with session_scope(env.session_factory) as session:
        crud.release_tile(session, row.id, lease)


def _end_job(
    row: JobTile, lease: str, env: JobEnv, state: JobState, error_type: str | None, message: str | None
) -> None:
    def write() -> bool:
        with session_scope(env.session_factory) as session:
            return crud.end_tiled_job(session, row.job_id, state, tile_id=row.id, lease=lease, error_type=error_type,
                                      message=message)  # fmt: skip

    if with_db_retry(write, deadline_s=env.settings.transient_retry_s, what=f"record the job as {state}"):
        logger.info("job %s: %s (%s %s)", row.job_id, state, row.kind, row.name)


@contextmanager
def _workspace(env: JobEnv, job: Job, bundle_path: str, row: JobTile) -> Iterator[tuple[Path, Path, Any]]:
    """The scene's bundle and the job's folder, as :func:`worker.runner._workspace` gives a job's: in place with the
    local backend; else a scratch folder with the plan and the tile's own folder (a merge: every tile's folder)
    fetched from the job's objects, and a push that stores back what the task writes."""
    from service.storage import TreePush

    storage = env.storage
    if storage.is_local:
        yield storage.path(bundle_path), storage.job_dir(job.id), None
        return
    prefix = storage.job_prefix(job.id)
    with ExitStack() as stack:
        scratch = stack.enter_context(storage.scratch(f"{row.kind}-{job.id}"))
        bundle_dir = runner.bundle_in(stack, env, job, bundle_path, scratch)
        out_dir = scratch / "out"
        if row.kind == TileKind.MERGE:
            storage.fetch_tree(prefix + TILES_KEY, out_dir / TILES_KEY)
            push = TreePush(storage, out_dir, prefix)
        else:
            storage.objects.get_file(prefix + TILES_KEY + "plan.json", out_dir / TILES_KEY / "plan.json")
            own = out_dir / TILES_KEY / row.name
            own.mkdir(parents=True, exist_ok=True)
            storage.fetch_tree(f"{prefix}{TILES_KEY}{row.name}/", own)
            push = TreePush(storage, own, f"{prefix}{TILES_KEY}{row.name}/")
        push.mark_present()
        yield bundle_dir, out_dir, push


def _run_in(
    job: Job,
    row: JobTile,
    tracker: TileTracker,
    env: JobEnv,
    vocabulary: str | Vocabulary | None,
    bundle_dir: Path,
    out_dir: Path,
) -> TileState | None:
    try:
        with tracker.beating():
            if row.kind == TileKind.MERGE:
                return _merge(job, row, tracker, env, vocabulary, bundle_dir, out_dir)
            return _tile(job, row, tracker, env, vocabulary, bundle_dir, out_dir)
    except StorageError:
        raise
    except runner.StorageStop as exc:
        raise exc.error from exc
    except LeaseLost:
        logger.warning("job %s: %s %s stopped, another worker holds it or the job ended", job.id, row.kind, row.name)
        return None
    except Interrupted:
        tracker.push_outputs(best_effort=True)
        with_db_retry(lambda: _release(row, tracker.lease, env), deadline_s=env.settings.transient_retry_s,
                      what="hand the tile back")  # fmt: skip
        return TileState.QUEUED
    except CancelRequested as exc:
        _end_job(row, tracker.lease, env, JobState.CANCELED, None, str(exc))
        return TileState.CANCELED
    except (TimeLimitExceeded, PanoGSError) as exc:
        logger.info("job %s: %s %s failed: %s: %s", job.id, row.kind, row.name, type(exc).__name__, exc)
        message = without_host_paths(str(exc), env, bundle_dir, out_dir)[:10_000]
        _end_job(row, tracker.lease, env, JobState.FAILED, type(exc).__name__, message)
        return TileState.FAILED


def _scene_and_plan(bundle_dir: Path, out_dir: Path) -> tuple[Any, Any, Any]:
    from panogs_core.io.bundle import open_bundle
    from panogs_core.tiling.plan import TilePlan
    from panogs_core.tiling.tile import plan_path

    scene = open_bundle(bundle_dir)
    plan = TilePlan.load(plan_path(out_dir))
    geometry = scene.read_geometry()
    if geometry is None:
        raise PanoGSError("the tiled job's bundle has no geometry.ply")
    return scene, plan, geometry.points


def _tile(
    job: Job,
    row: JobTile,
    tracker: TileTracker,
    env: JobEnv,
    vocabulary: str | Vocabulary | None,
    bundle_dir: Path,
    out_dir: Path,
) -> TileState | None:
    from panogs_core.pipeline.run import resolve_scene_vocabulary
    from panogs_core.tiling.runner import tile_config
    from panogs_core.tiling.tile import release_memory, run_tile

    scene, plan, points = _scene_and_plan(bundle_dir, out_dir)
    tile = plan.tiles[row.tile_index]
    cfg = tile_config(env.make_config(job.config or {}))
    vocab = resolve_scene_vocabulary(scene, vocabulary)
    progress = stopping_on_storage_errors(tracker.on_progress)
    report, stats = run_tile(scene, plan, tile, points, cfg, vocab, out_dir, progress, True)
    del scene, points
    release_memory()
    tracker.push_outputs()

    def write() -> tuple[bool, uuid.UUID | None]:
        with session_scope(env.session_factory) as session:
            return crud.finish_tile(session, row.id, job.id, tracker.lease, stage=None, wall_s=round(stats.wall_s, 3),
                                    peak_rss_mb=round(stats.peak_rss_mb, 1), report=report)  # fmt: skip

    tracker.stop.set()  # no heartbeat after the row is finished
    done, merge_id = with_db_retry(write, deadline_s=env.settings.transient_retry_s, what="record the tile done")
    if not done:
        raise LeaseLost(f"tile {row.id}: another worker holds it now, or its job ended")
    logger.info("job %s: tile %s done in %.1f s, peak %.0f MB", job.id, row.name, stats.wall_s, stats.peak_rss_mb)
    if merge_id is not None:
        logger.info("job %s: the last tile is done; publishing the merge", job.id)
        dispatch_tile(env.session_factory, _sender(env), merge_id, TileKind.MERGE, job.queue)
    return TileState.SUCCEEDED


def _merge(
    job: Job,
    row: JobTile,
    tracker: TileTracker,
    env: JobEnv,
    vocabulary: str | Vocabulary | None,
    bundle_dir: Path,
    out_dir: Path,
) -> TileState | None:
    from panogs_core.pipeline.profiling import StageStats
    from panogs_core.pipeline.run import resolve_scene_vocabulary
    from panogs_core.tiling.runner import merge_run, write_report

    scene, plan, points = _scene_and_plan(bundle_dir, out_dir)
    vocab = resolve_scene_vocabulary(scene, vocabulary)
    with session_scope(env.session_factory) as session:
        tiles = [t for t in session.scalars(select(JobTile).where(JobTile.job_id == job.id)) if t.kind == "tile"]
        tiles.sort(key=lambda t: t.tile_index)
        reports = [dict(t.report or {}) for t in tiles]
        timings = [StageStats(name=f"tile {t.tile_index}", wall_s=t.wall_s or 0.0, peak_rss_mb=t.peak_rss_mb or 0.0)
                   for t in tiles]  # fmt: skip
        planned = float((job.stage_timings or {}).get("plan", 0.0))
    timings.insert(0, StageStats(name="plan", wall_s=planned))
    progress = stopping_on_storage_errors(tracker.on_progress)
    result, seam_joins = merge_run(scene, plan, points, vocab, out_dir, timings, progress)
    # The work of the job (the plan, every tile and the merge, on whichever workers), not the time since it began.
    result.total_s = sum(t.wall_s for t in result.timings)
    write_report(out_dir, scene, env.make_config(job.config or {}), vocabulary, plan, reports, seam_joins, result)
    tracker.push_outputs()
    merged = result.timings[-1]
    artifacts = runner.collect_artifacts(job.id, out_dir, env.storage)
    stage_timings = {"plan": planned, **{f"tile {t.tile_index}": t.wall_s or 0.0 for t in tiles},
                     "merge": round(merged.wall_s, 3)}  # fmt: skip
    now = utcnow()

    def write() -> bool:
        with session_scope(env.session_factory) as session:
            return crud.finish_merge(
                session, row.id, job.id, tracker.lease, artifacts,
                {"stage": None, "wall_s": round(merged.wall_s, 3), "peak_rss_mb": round(merged.peak_rss_mb, 1)},
                progress=1.0, stage=None, stage_timings=stage_timings, results_at=now, fit_state=FitState.SKIPPED,
                fit_progress=1.0, fit_error=None,
            )  # fmt: skip

    tracker.stop.set()
    if not with_db_retry(write, deadline_s=env.settings.transient_retry_s, what="record the merge"):
        raise LeaseLost(f"merge {row.id}: another worker holds it now, or its job ended")
    logger.info("job %s: merged %d tiles in %.1f s (%d seam joins)", job.id, len(tiles), merged.wall_s, seam_joins)
    return TileState.SUCCEEDED


def record_crash(tile_id: uuid.UUID, lease: str, exc: BaseException, env: JobEnv) -> None:
    """Fail a tiled job after an unexpected error in one of its tasks (best effort; the error is re-raised)."""
    message = without_host_paths(f"{type(exc).__name__}: {exc}", env)[:10_000]
    try:
        with session_scope(env.session_factory) as session:
            row = session.get(JobTile, tile_id)
            if row is not None and row.lease == lease:
                crud.end_tiled_job(session, row.job_id, JobState.FAILED, tile_id=tile_id, lease=lease,
                                   error_type="InternalError", message=message)  # fmt: skip
    except Exception:  # the original error matters more than this one
        logger.exception("tile %s: could not record the crash", tile_id)
