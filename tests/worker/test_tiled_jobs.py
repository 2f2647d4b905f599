"""Tiled jobs on workers (docs/service.md, "Tiled jobs"): the job's task plans and publishes one task per tile, a
lost tile is re-queued by the reaper and finished, the tile that completes last publishes the merge, the merge ends
the job once, and the result is the CLI's tiled run, byte for byte. The real pipeline on a small synthetic
building, SQLite and the local storage; the broker is a recorder of the published messages."""

from __future__ import annotations

import json
import shutil
import uuid
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest
from shared_runs import BUILDING_NO_FIT, BUILDING_SPACE
from sqlalchemy import select, update
from torch_threads import one_torch_thread  # noqa: F401  (autouse fixture: the language field on a shared host)

from panogs_core.errors import PanoGSError
from panogs_core.pipeline.run import STAGES, run_pipeline
from panogs_core.tiling.plan import TilePlan
from panogs_core.tiling.tile import plan_path, tile_input_hash
from service import jobs
from service.broker import TaskName
from service.db import crud
from service.db.base import utcnow
from service.db.models import ApiKey, Artifact, Job, JobState, JobTile, Scene, TileKind, TileState
from service.db.session import get_session_factory, session_scope
from service.reaper import sweep
from service.settings import Settings
from service.storage import Storage
from worker import leased, runner, tasks, tiles
from worker.shared_checkpoints import archive_input_hash

pytestmark = pytest.mark.slow

SPACE = BUILDING_SPACE  # the label-set space needs no text encoder
NO_FIT = BUILDING_NO_FIT  # as the session's runs of the building (shared_runs.py)
COMPARED = ("labels.npz", "instances.json", "instance_features.npy", "panoptic.ply")


class Recorder:
    """The broker as the worker sees it: records what was published."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, list[str]]] = []

    def send_task(self, name: str, args: list[str] | None = None, queue: str | None = None) -> object:
        self.sent.append((name, list(args or [])))
        return None


@pytest.fixture(scope="module")
def building(tiny_building: Path) -> Path:
    """Two tiny rooms side by side, joined by a doorway (about 17k points, 28 frames; the session's: only read)."""
    return tiny_building


def _env(settings: Settings, sender: Recorder) -> leased.JobEnv:
    return leased.JobEnv(
        settings=settings, session_factory=get_session_factory(settings.database), storage=Storage(settings.storage),
        pipeline=run_pipeline, make_config=jobs.pipeline_config, stages=tuple(STAGES), sender=sender,
    )  # fmt: skip


def _job(settings: Settings, building: Path, tiling: dict[str, Any], archive_sha256: str | None = None) -> uuid.UUID:
    storage = Storage(settings.storage)
    with session_scope(get_session_factory(settings.database)) as session:
        key = ApiKey(name="t", prefix=uuid.uuid4().hex[:12], key_hash="0" * 64)
        session.add(key)
        session.flush()
        scene_id = uuid.uuid4()
        bundle = storage.scene_dir(scene_id) / "bundle"
        shutil.copytree(building, bundle)
        session.add(Scene(id=scene_id, api_key_id=key.id, name="b", feature_dim=512, feature_space=SPACE,
                          num_frames=28, has_vocabulary=True, has_ground_truth=True,
                          bundle_path=storage.rel(bundle), bundle_sha256=archive_sha256))  # fmt: skip
        session.flush()
        job = Job(api_key_id=key.id, scene_id=scene_id, state=JobState.QUEUED, queue="cpu", request_hash="h",
                  stage_timings={}, config=NO_FIT, tiling=tiling)  # fmt: skip
        session.add(job)
        session.commit()
        return job.id


def _rows(env: leased.JobEnv, job_id: uuid.UUID) -> list[JobTile]:
    with session_scope(env.session_factory) as session:
        rows = list(session.scalars(select(JobTile).where(JobTile.job_id == job_id).order_by(JobTile.tile_index)))
        session.expunge_all()
        return rows


def _job_row(env: leased.JobEnv, job_id: uuid.UUID) -> Job:
    with session_scope(env.session_factory) as session:
        job = session.get(Job, job_id)
        assert job is not None
        session.expunge(job)
        return job


def test_tiled_job_fans_out_survives_a_lost_tile_and_merges_once(
    settings: Settings, building: Path, tiny_building_tiled_run: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from panogs_core.pipeline import checkpoints
    from panogs_core.tiling import tile as tile_module

    def never(scene: object) -> str:
        raise AssertionError("a tile or the merge of an uploaded scene hashed its files")

    # The scene came from an upload: its tiles' hashes and the merged report's are made from its archive's.
    monkeypatch.setattr(checkpoints, "hash_bundle", never)
    monkeypatch.setattr(tile_module, "hash_bundle", never)
    sender = Recorder()
    env = _env(settings, sender)
    archive = "ab" * 32  # the scene came from an upload: the merged report's hash is made from its archive's
    job_id = _job(settings, building, {"tiles": "2x1"}, archive_sha256=archive)

    assert runner.execute_job(job_id, lease="job-1", worker="w/1", env=env) == JobState.RUNNING
    rows = _rows(env, job_id)
    assert [(r.kind, r.state) for r in rows] == [
        (TileKind.TILE, TileState.QUEUED), (TileKind.TILE, TileState.QUEUED), (TileKind.MERGE, TileState.PENDING),
    ]  # fmt: skip
    tile0, tile1, merge = rows
    assert sender.sent == [(TaskName.RUN_TILE, [str(tile0.id)]), (TaskName.RUN_TILE, [str(tile1.id)])]
    assert all(r.enqueued_at is not None for r in rows[:2])
    assert _job_row(env, job_id).stage == "tiles"
    # A second delivery of the job's message does not plan again: the tiles run the job now.
    assert runner.execute_job(job_id, lease="job-2", worker="w/2", env=env) is None
    assert [r.id for r in _rows(env, job_id)] == [r.id for r in rows]

    # A worker claims tile 0 and dies (kill -9: no more heartbeats); the reaper re-queues and re-publishes it.
    with session_scope(env.session_factory) as session:
        assert crud.claim_tile(session, tile0.id, "dead", "w/dead", crud.stale_cutoff(60)) is not None
        session.execute(
            update(JobTile).where(JobTile.id == tile0.id).values(heartbeat_at=utcnow() - timedelta(hours=1))
        )
        session.commit()
    sender.sent.clear()
    counts = sweep(settings, env.session_factory, sender, env.storage, housekeeping=False)
    assert counts["requeued"] == 1
    assert sender.sent == [(TaskName.RUN_TILE, [str(tile0.id)])]

    assert tiles.execute_part(tile1.id, lease="t1", worker="w/1", env=env) == TileState.SUCCEEDED
    assert sender.sent == [(TaskName.RUN_TILE, [str(tile0.id)])]  # one tile left: no merge yet
    halfway = _job_row(env, job_id).progress
    assert 0.3 < halfway < 0.7  # tile 1's share of the weights, the merge's and tile 0's still to come
    assert tiles.execute_part(tile0.id, lease="t0", worker="w/2", env=env) == TileState.SUCCEEDED
    assert sender.sent[1:] == [(TaskName.MERGE_TILES, [str(merge.id)])]  # the last tile published the merge
    with session_scope(env.session_factory) as session:  # the dead worker's lease writes nothing any more
        assert not crud.update_tile_running(session, tile0.id, job_id, "dead", progress=0.5)
    assert _rows(env, job_id)[0].attempts == 2

    assert tiles.execute_part(merge.id, lease="m1", worker="w/1", env=env) == TileState.SUCCEEDED
    assert tiles.execute_part(merge.id, lease="m2", worker="w/2", env=env) is None  # a duplicate message: no merge
    job = _job_row(env, job_id)
    assert job.state == JobState.SUCCEEDED
    assert job.progress == 1.0
    assert set(job.stage_timings) == {"plan", "tile 0", "tile 1", "merge"}
    final = _rows(env, job_id)
    assert [r.state for r in final] == [TileState.SUCCEEDED] * 3
    assert all(r.wall_s and r.wall_s > 0 and r.peak_rss_mb and r.peak_rss_mb > 0 for r in final)
    with session_scope(env.session_factory) as session:
        names = set(session.scalars(select(Artifact.name).where(Artifact.job_id == job_id)))
    assert {"instances.json", "labels.npz", "report.json"} <= names

    # The API's view: the tiles, then the merge, each with its state and progress.
    public = jobs.to_public(job, final)  # type: ignore[arg-type]  (a model row reads as the poll's plain row)
    assert [(t.index, t.kind, t.state, t.progress) for t in public.tiles] == [
        (0, "tile", "succeeded", 1.0), (1, "tile", "succeeded", 1.0), (2, "merge", "succeeded", 1.0),
    ]  # fmt: skip

    # The same plan, tiles and merge in one process (the CLI's path) write the same files: ``panogs run --tiles
    # 2x1`` without the fit, the session's run (tests/conftest.py).
    out = env.storage.job_dir(job_id)
    cli = tiny_building_tiled_run
    for name in COMPARED:
        assert (out / name).read_bytes() == (cli / name).read_bytes(), name
    report = json.loads((out / "report.json").read_text())
    assert [t["name"] for t in report["tiling"]["tiles"]] == [r.name for r in final[:2]]
    assert report["input_sha256"] == archive_input_hash(archive)
    plan = TilePlan.load(plan_path(out))
    for spec in plan.tiles:  # each tile's run was keyed from the scene's hash and where the tile lies
        tile_report = json.loads((out / "tiles" / spec.name / "report.json").read_text())
        assert tile_report["input_sha256"] == tile_input_hash(archive_input_hash(archive), plan, spec)


def test_a_failed_tile_fails_the_job_and_stops_its_siblings(settings: Settings, building: Path) -> None:
    sender = Recorder()
    env = _env(settings, sender)
    job_id = _job(settings, building, {"tiles": "2x1"})
    assert runner.execute_job(job_id, lease="job-1", worker="w/1", env=env) == JobState.RUNNING
    tile0, tile1, _merge = _rows(env, job_id)
    shutil.rmtree(env.storage.job_dir(job_id) / "tiles")  # the plan is gone: the tile cannot run
    with pytest.raises(FileNotFoundError):
        tasks.run_part(env, str(tile0.id), lease="t0", worker="w/1")  # the task boundary records the crash
    job = _job_row(env, job_id)
    assert job.state == JobState.FAILED
    assert job.error_type == "InternalError"
    assert "plan.json" in (job.error_message or "")
    assert [r.state for r in _rows(env, job_id)] == [TileState.FAILED, TileState.CANCELED, TileState.CANCELED]
    assert tiles.execute_part(tile1.id, lease="t1", worker="w/1", env=env) is None  # its job ended: not claimed
    assert not any(name == TaskName.MERGE_TILES for name, _ in sender.sent)


def test_a_plan_that_leaves_the_scene_whole_runs_the_job_as_before(
    settings: Settings, building: Path, tiny_building_plain_run: Path
) -> None:
    sender = Recorder()
    env = _env(settings, sender)
    job_id = _job(settings, building, {"tiles": "auto"})  # two tiny rooms: far under the limit, not tiled
    assert runner.execute_job(job_id, lease="job-1", worker="w/1", env=env) == JobState.SUCCEEDED
    assert _rows(env, job_id) == []
    assert sender.sent == []
    plain = tiny_building_plain_run  # run_pipeline(building, ..., NO_FIT), the session's (tests/conftest.py)
    out = env.storage.job_dir(job_id)
    for name in COMPARED:
        assert (out / name).read_bytes() == (plain / name).read_bytes(), name
    assert "tiling" not in json.loads((out / "report.json").read_text())


def test_an_auto_plan_over_the_tile_cap_fails_the_job_naming_the_cap(settings: Settings, building: Path) -> None:
    # A memory target just above a run's fixed cost makes the planner split as finely as it can; the API cannot
    # know the count of an auto job, so the worker refuses the plan before it publishes a tile.
    capped = settings.model_copy(update={"max_tiles_per_job": 2})
    sender = Recorder()
    env = _env(capped, sender)
    job_id = _job(capped, building, {"tiles": "auto", "memory_target_bytes": 0.81e9, "whole_limit_bytes": 1e6})
    assert runner.execute_job(job_id, lease="job-1", worker="w/1", env=env) == JobState.FAILED
    job = _job_row(env, job_id)
    assert job.error_type == "InputError"
    message = job.error_message or ""
    assert "tiles; a job may have at most 2" in message
    assert "PANOGS_MAX_TILES_PER_JOB" in message
    assert _rows(env, job_id) == []
    assert sender.sent == []


def test_tile_cap_check_passes_a_plan_within_the_cap(settings: Settings) -> None:
    tiles.check_planned_tiles(settings, num_frames=28, planned=8)  # the cap is one per frame, at least 8
    with pytest.raises(PanoGSError, match="into 9 tiles; a job may have at most 8"):
        tiles.check_planned_tiles(settings, num_frames=3, planned=9)
