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
from dataclasses import dataclass
from typing import Any, cast

from sqlalchemy import select
from sqlalchemy.orm import Session

from panogs_core.errors import InputError, PanoGSError
from panogs_core.tiling.choice import TILES_OFF
from panogs_core.types import Vocabulary
from service.db import crud
from service.db.base import utcnow
from service.db.models import FitState, Job, JobState, JobTile, TileKind, TileState
from service.db.session import session_scope
from service.jobs import tile_cap, tile_cap_rule
from service.queue import Sender, celery_sender, dispatch_tile
from service.settings import Settings
from service.storage.workspace import Workspace
from worker.job_io import collect_artifacts, job_vocabulary
from worker.leased import (
    CancelRequested,
    JobEnv,
    LeaseLost,
    Tracker,
    claim_retried,
    in_workspace,
    run_leased,
    stage_fraction,
    stopping_on_storage_errors,
    within,
    without_host_paths,
    workspace_plan,
    write_retried,
)
from worker.shared_checkpoints import archive_input_hash

logger = logging.getLogger(__name__)

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


def check_planned_tiles(settings: Settings, num_frames: int, planned: int) -> None:
    """Fail an ``auto`` job whose plan has more tiles than an ``NxM`` job may ask for (``service.jobs.tile_cap``).

    The API caps ``NxM`` when the job is created; an ``auto`` job's count is known only here, after the plan, and a
    small ``memory_target_bytes`` can make it as fine as the planner allows (one job holding the worker for tens
    of minutes while other tenants wait).

    Raises:
        InputError: the plan has more tiles than the cap; the message names the cap and the setting to raise.
    """
    cap = tile_cap(settings, num_frames)
    if planned > cap:
        raise InputError(
            f"tiling: the automatic plan splits the scene ({num_frames} frames) into {planned} tiles; a job may have "
            f"{tile_cap_rule(settings, cap)}; raise tiling.memory_target_bytes for fewer, larger tiles"
        )


def plan_and_fan_out(job: Job, tracker: Tracker, work: Workspace, config: Any) -> bool:
    """Plan the job; when the plan tiles the scene, record its tiles and publish them and return True (the job's
    task is done); False when the scene stays whole (the caller runs it as an untiled job).

    Raises:
        LeaseLost: another task holds the job now.
        InputError: tiles were forced on a bundle without geometry.
    """
    from panogs_core.io.bundle import open_bundle
    from panogs_core.tiling.runner import plan_run
    from panogs_core.tiling.tile import plan_path

    env = tracker.env
    scene = open_bundle(work.bundle)
    with tracker.beating():
        plan, _points, stats = plan_run(scene, config, tiles_asked(job), tiling_config(job), tracker.on_progress)
    if not plan.tiled:
        logger.info("job %s: the plan leaves the scene whole (%s)", job.id, plan.reason)
        return False
    check_planned_tiles(env.settings, len(scene.frames), len(plan.tiles))
    path = plan_path(work.out)
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

    def write(session: Session) -> bool:
        return crud.fan_out(session, job.id, tracker.lease, rows, stage_timings={"plan": round(stats.wall_s, 3)})

    if not write_retried(env, "record the job's tiles", write):
        raise LeaseLost(f"job {job.id}: another worker holds it now")
    logger.info("job %s: %d tiles (%s); publishing them", job.id, len(plan.tiles), plan.reason)
    for ident in ids:
        dispatch_tile(env.session_factory, _sender(env), ident, TileKind.TILE, job.queue)
    return True


class TileRow:
    """A tile's (or merge's) row, as its tracker writes it: its stage and progress, and the job's progress with them."""

    ended = "its job ended"

    def __init__(self, tile_id: uuid.UUID, job_id: uuid.UUID) -> None:
        self.tile_id, self.job_id = tile_id, job_id
        self.label = f"tile {tile_id}"

    def fraction(self, stages: tuple[str, ...], stage: str, done: int, total: int) -> float:
        base = stage.rsplit(" ", 1)[-1]  # run_tile names its stages "tile <k>/<K> <stage>"
        return within(done, total) if base == "merge" else stage_fraction(stages, base, done, total)

    def write(self, session: Session, lease: str, values: dict[str, Any]) -> bool:
        kept = {k: values[k] for k in ("stage", "progress") if k in values}
        if "stage" in kept:
            kept["stage"] = str(kept["stage"]).rsplit(" ", 1)[-1][:64]
        return crud.update_tile_running(session, self.tile_id, self.job_id, lease, **kept)


@dataclass(frozen=True)
class TileEnding:
    """How a tile or merge ends otherwise than by its own success: a cancel or a failure ends its whole job."""

    row: JobTile
    lease: str
    env: JobEnv

    def hand_back(self) -> None:
        with session_scope(self.env.session_factory) as session:
            crud.release_tile(session, self.row.id, self.lease)

    def handed_back(self) -> TileState:
        return TileState.QUEUED

    def canceled(self, exc: CancelRequested) -> TileState | None:
        _end_job(self.row, self.lease, self.env, JobState.CANCELED, None, str(exc))
        return TileState.CANCELED

    def failed(self, error_type: str, message: str, *, in_run: bool) -> TileState | None:
        _end_job(self.row, self.lease, self.env, JobState.FAILED, error_type, message)
        return TileState.FAILED


def execute_part(tile_id: uuid.UUID, *, lease: str, worker: str, env: JobEnv) -> TileState | None:
    """Run the tile or merge ``tile_id`` under ``lease``; the state it ended in, or None when it was not ours.

    Raises:
        TransientError: the database or the object storage stayed away; retry the task later.
    """
    claim = claim_retried(
        env,
        "the tile",
        lambda: _claim(tile_id, lease, worker, env),
        lambda tile: (tile.attempts, f"{tile.kind} {tile.name}"),
    )
    row = claim.row
    if row is None:
        return None
    ending = TileEnding(row, lease, env)
    if claim.worn_out is not None:
        return ending.failed("WorkerLost", claim.worn_out, in_run=False)
    with session_scope(env.session_factory) as session:
        job = session.get(Job, row.job_id)
        scene = crud.get_scene(session, job.scene_id) if job is not None else None
        try:
            vocabulary = job_vocabulary(session, job) if job is not None else None
        except PanoGSError as exc:
            return ending.failed(type(exc).__name__, str(exc), in_run=False)
    if job is None or scene is None:
        return ending.failed("SceneMissing", "the job's scene no longer exists", in_run=False)
    logger.info("job %s: %s %s running (attempt %d, worker %s)", job.id, row.kind, row.name, row.attempts, worker)
    tracker = Tracker(row=TileRow(row.id, job.id), lease=lease, env=env)
    if row.kind == TileKind.MERGE:  # every tile's folder; it writes the job's files
        paths: dict[str, Any] = {"fetch": (TILES_KEY,), "push": ""}
    else:  # the plan and its own folder, which it writes
        paths = {"fetch": (TILES_KEY + "plan.json", f"{TILES_KEY}{row.name}/"), "push": f"{TILES_KEY}{row.name}/"}
    plan = workspace_plan(env, row.kind, job.scene_id, scene.bundle_path, **paths)
    # A scene from an upload: its bundle's hash is made from the archive's (worker/shared_checkpoints.py), so no
    # tile and no merge reads the bundle's files to hash them; None for a scene made otherwise.
    scene_hash = None if scene.bundle_sha256 is None else archive_input_hash(scene.bundle_sha256)

    def body(work: Workspace) -> TileState | None:
        part = _Part(job, row, tracker, vocabulary, work, scene_hash)
        return run_leased(tracker, ending, work, lambda: _run_in(part))

    return in_workspace(tracker, ending, plan, body)


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


def _end_job(
    row: JobTile, lease: str, env: JobEnv, state: JobState, error_type: str | None, message: str | None
) -> None:
    def write(session: Session) -> bool:
        return crud.end_tiled_job(session, row.job_id, state, tile_id=row.id, lease=lease, error_type=error_type,
                                  message=message)  # fmt: skip

    if write_retried(env, f"record the job as {state}", write):
        logger.info("job %s: %s (%s %s)", row.job_id, state, row.kind, row.name)


@dataclass(frozen=True)
class _Part:
    """A tile or the merge of a tiled job, as one worker runs it."""

    job: Job
    row: JobTile
    tracker: Tracker  # beats for the row's lease
    vocabulary: str | Vocabulary | None  # the job's label set
    work: Workspace  # the part's folder, fetched from and pushed to the job's storage
    scene_hash: str | None  # the bundle's hash made from the upload's archive; None for a scene made otherwise


def _run_in(part: _Part) -> TileState | None:
    with part.tracker.beating():
        return _merge(part) if part.row.kind == TileKind.MERGE else _tile(part)


def _scene_and_plan(work: Workspace) -> tuple[Any, Any, Any]:
    from panogs_core.io.bundle import open_bundle
    from panogs_core.tiling.plan import TilePlan
    from panogs_core.tiling.tile import plan_path

    scene = open_bundle(work.bundle)
    plan = TilePlan.load(plan_path(work.out))
    geometry = scene.read_geometry()
    if geometry is None:
        raise PanoGSError("the tiled job's bundle has no geometry.ply")
    return scene, plan, geometry.points


def _tile(part: _Part) -> TileState | None:
    from panogs_core.pipeline.run import resolve_scene_vocabulary
    from panogs_core.tiling.runner import tile_config
    from panogs_core.tiling.tile import release_memory, run_tile

    job, row, tracker, work = part.job, part.row, part.tracker, part.work
    env = tracker.env
    scene, plan, points = _scene_and_plan(work)
    tile = plan.tiles[row.tile_index]
    cfg = tile_config(env.make_config(job.config or {}))
    vocab = resolve_scene_vocabulary(scene, part.vocabulary)
    progress = stopping_on_storage_errors(tracker.on_progress)
    report, stats = run_tile(scene, plan, tile, points, cfg, vocab, work.out, progress, True, part.scene_hash)
    del scene, points
    release_memory()
    tracker.push_outputs()

    def write(session: Session) -> tuple[bool, uuid.UUID | None]:
        return crud.finish_tile(session, row.id, job.id, tracker.lease, stage=None, wall_s=round(stats.wall_s, 3),
                                peak_rss_mb=round(stats.peak_rss_mb, 1), report=report)  # fmt: skip

    tracker.stop.set()  # no heartbeat after the row is finished
    done, merge_id = write_retried(env, "record the tile done", write)
    if not done:
        raise LeaseLost(f"tile {row.id}: another worker holds it now, or its job ended")
    logger.info("job %s: tile %s done in %.1f s, peak %.0f MB", job.id, row.name, stats.wall_s, stats.peak_rss_mb)
    if merge_id is not None:
        logger.info("job %s: the last tile is done; publishing the merge", job.id)
        dispatch_tile(env.session_factory, _sender(env), merge_id, TileKind.MERGE, job.queue)
    return TileState.SUCCEEDED


def _merge(part: _Part) -> TileState | None:
    from panogs_core.pipeline.input_hash import hash_bundle
    from panogs_core.pipeline.profiling import StageStats
    from panogs_core.pipeline.run import resolve_scene_vocabulary
    from panogs_core.tiling.runner import merge_run, write_report

    job, row, tracker, work, vocabulary = part.job, part.row, part.tracker, part.work, part.vocabulary
    env = tracker.env
    scene, plan, points = _scene_and_plan(work)
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
    result, seam_joins = merge_run(scene, plan, points, vocab, work.out, timings, progress)
    # The work of the job (the plan, every tile and the merge, on whichever workers), not the time since it began.
    result.total_s = sum(t.wall_s for t in result.timings)
    write_report(work.out, scene, env.make_config(job.config or {}), vocabulary, plan, reports, seam_joins, result,
                 input_hash=part.scene_hash or hash_bundle(scene))  # fmt: skip
    tracker.push_outputs()
    merged = result.timings[-1]
    artifacts = collect_artifacts(job.id, work.out, env.storage)
    stage_timings = {"plan": planned, **{f"tile {t.tile_index}": t.wall_s or 0.0 for t in tiles},
                     "merge": round(merged.wall_s, 3)}  # fmt: skip
    now = utcnow()

    def write(session: Session) -> bool:
        return crud.finish_merge(
            session, row.id, job.id, tracker.lease, artifacts,
            {"stage": None, "wall_s": round(merged.wall_s, 3), "peak_rss_mb": round(merged.peak_rss_mb, 1)},
            progress=1.0, stage=None, stage_timings=stage_timings, results_at=now, fit_state=FitState.SKIPPED,
            fit_progress=1.0, fit_error=None,
        )  # fmt: skip

    tracker.stop.set()
    if not write_retried(env, "record the merge", write):
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
