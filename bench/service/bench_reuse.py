"""A scene's re-runs against its first run, through the worker with the scene's shared checkpoints, on the local
backend and on S3 (SeaweedFS on loopback), alternating.

Usage:
    python bench/service/bench_reuse.py [--bundle DIR] [--preset scannet-size] [--rounds 2] [--backends local s3]
        [--scenes uploaded unhashed] [--jobs first clustering labeling clustering-cold]

Each round and backend gets a scene of its own (so nothing is shared across them) on one bundle: ``--bundle``, or
the ``--preset`` room generated into ``--work`` when it is missing. On that scene the worker's
``runner.execute_job`` (what a Celery task runs: claim, fetch, the real pipeline, store, record) runs three jobs in
turn: the defaults (the first run: every stage computed, the appearance fit included), then only the clustering
thresholds changed, then only a labelling setting changed, then other clustering thresholds once the worker's
copies of the scene's checkpoints are removed (``clustering-cold``: a re-run on another worker that has the
bundle; with local files it is one more re-run). The database is the embedded SQLite of each backend's
data folder; the bundle is placed once per backend (hard links for local, uploaded for S3) and each scene points at
it. Prints per job its seconds, the stages taken from the scene's checkpoints, the seconds spent fetching those
checkpoints (``SceneCheckpoints.fetch``) and, on S3, fetching the bundle into the task's scratch folder, and its
seconds to the results (``results_at`` less ``started_at``: the labels served, before the appearance fit).

``--scenes``: an ``uploaded`` scene carries its archive's SHA-256, as a scene made from an upload does (the stage
keys start from it: no job hashes the bundle, ``worker/shared_checkpoints.py``); here a stand-in value, since the
bundle is placed as a folder. An ``unhashed`` scene has none, as one made otherwise: its first job hashes the bundle
before its first stage and keeps the hash. Both kinds alternate within a round.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
import uuid
from contextlib import ExitStack
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests" / "support"))

from seaweedfs import seaweedfs

from service import jobs
from service.db.migrate import upgrade
from service.db.models import ApiKey, Job, JobState, Scene
from service.db.session import get_session_factory, session_scope
from service.settings import Settings
from service.storage import Storage
from service.storage.backends import open_storage
from service.storage.local import LocalStorage
from worker import leased, runner, shared_checkpoints
from worker.bundle_cache import STAGES_SUFFIX
from worker.device import device_config_factory

BUNDLE_PREFIX = "bench-bundle"
JOBS = {
    "first": {},
    "clustering": {"clustering": {"thresholds": [0.9, 0.75, 0.6]}},
    "labeling": {"labeling": {"min_instance_points": 80}},
    # As "clustering" (other thresholds), on a worker that holds the bundle but none of the scene's checkpoint
    # copies: what a re-run on another worker reads from the store (S3 only: nothing is copied with local files).
    "clustering-cold": {"clustering": {"thresholds": [0.85, 0.7, 0.55]}},
}
COLD = "clustering-cold"
FETCHED_S: list[float] = []  # seconds of each checkpoint fetch of the job that runs


class TimedCheckpoints(shared_checkpoints.SceneCheckpoints):
    """The worker's shared checkpoints, each fetch timed (a fetch that finds nothing is timed too: it is a look)."""

    def fetch(self, stage: str, key: str, dest: Path) -> bool:
        start = time.perf_counter()
        try:
            return super().fetch(stage, key, dest)
        finally:
            FETCHED_S.append(time.perf_counter() - start)


def backend_settings(work: Path, backend: str, s3: Any) -> Settings:
    data = work / f"{backend}-data"
    data.mkdir(parents=True)
    extra: dict[str, Any] = {}
    if backend == "s3":
        extra = {
            "storage_url": s3.url("bench-reuse"),
            "s3_endpoint_url": s3.endpoint,
            "s3_access_key_id": s3.access_key,
            "s3_secret_access_key": s3.secret_key,
        }
    settings = Settings(_env_file=None, data_dir=data, **extra)  # type: ignore[call-arg]
    upgrade(settings.database)
    return settings


def place_bundle(settings: Settings, storage: Storage, bundle: Path) -> float:
    """The bundle under ``bench-bundle/`` of the storage; returns the seconds it took."""
    start = time.perf_counter()
    if isinstance(storage.objects, LocalStorage):  # a local store: hard links, not a copy of 2 GB
        subprocess.run(["cp", "-al", str(bundle), str(storage.root / BUNDLE_PREFIX)], check=True)
    else:
        storage.store_tree(bundle, BUNDLE_PREFIX + "/")
    return time.perf_counter() - start


def new_scene(settings: Settings, tenant: uuid.UUID, bundle: Path, kind: str) -> uuid.UUID:
    meta = json.loads((bundle / "scene.json").read_text())
    # A stand-in for an upload's archive SHA-256 (any 64 hex digits name the bytes for this bench's scenes).
    archive_sha256 = hashlib.sha256(f"bench archive {bundle}".encode()).hexdigest() if kind == "uploaded" else None
    features = meta.get("features", {})
    with session_scope(get_session_factory(settings.database)) as session:
        scene = Scene(
            api_key_id=tenant,
            name=f"bench {uuid.uuid4().hex[:6]}",
            feature_dim=int(features.get("dim", 0)),
            feature_space=str(features.get("space", "x")),
            num_frames=len(meta.get("frames", [])),
            has_vocabulary=True,
            has_ground_truth=True,
            bundle_path=BUNDLE_PREFIX,
            bundle_sha256=archive_sha256,
        )
        session.add(scene)
        session.commit()
        return scene.id


def new_tenant(settings: Settings) -> uuid.UUID:
    with session_scope(get_session_factory(settings.database)) as session:
        key = ApiKey(name="bench", prefix=uuid.uuid4().hex[:12], key_hash="0" * 64)
        session.add(key)
        session.commit()
        return key.id


def run_job(env: leased.JobEnv, tenant: uuid.UUID, scene: uuid.UUID, config: dict[str, Any]) -> dict[str, Any]:
    with session_scope(env.session_factory) as session:
        job = Job(
            api_key_id=tenant,
            scene_id=scene,
            state=JobState.QUEUED,
            queue="cpu",
            request_hash="b",
            stage_timings={},
            config=config,
        )
        session.add(job)
        session.commit()
        job_id = job.id
    FETCHED_S.clear()
    bundle_s: list[float] = []
    fetch_tree = env.storage.fetch_tree

    def timed_fetch_tree(prefix: str, folder: Path) -> int:
        start = time.perf_counter()
        try:
            return fetch_tree(prefix, folder)
        finally:
            if prefix.startswith(BUNDLE_PREFIX):
                bundle_s.append(time.perf_counter() - start)

    env.storage.fetch_tree = timed_fetch_tree  # type: ignore[method-assign]
    start = time.perf_counter()
    state = runner.execute_job(job_id, lease=uuid.uuid4().hex, worker="bench", env=env)
    seconds = time.perf_counter() - start
    env.storage.fetch_tree = fetch_tree  # type: ignore[method-assign]
    with session_scope(env.session_factory) as session:
        row = session.get(Job, job_id)
        assert row is not None
        public = jobs.to_public(row)
        started, results = row.started_at, row.results_at
    if state is not JobState.SUCCEEDED:
        raise RuntimeError(f"job {job_id} ended {state}: {public.error}")
    cached = [stage for stage, hit in public.stage_cached.items() if hit]
    return {
        "seconds": seconds,
        "results_s": (results - started).total_seconds() if started and results else None,
        "cached": cached,
        "fetch_s": sum(FETCHED_S),
        "bundle_s": sum(bundle_s),
        "fit": public.fit.state.value if public.fit else None,
    }


def forget_checkpoint_copies(env: leased.JobEnv, scene: uuid.UUID) -> None:
    """Remove this worker's copies of the scene's checkpoints (``worker/bundle_cache.py``), keeping its bundle."""
    shutil.rmtree(env.storage.root / "work" / "bundles" / f"{scene}{STAGES_SUFFIX}", ignore_errors=True)


def load_average() -> str:
    """The 1, 5 and 15 minute load averages (as ``uptime`` prints them)."""
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bundle", type=Path, default=None)
    ap.add_argument("--preset", default="scannet-size")
    ap.add_argument("--work", type=Path, default=Path("bench/results/reuse"))
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--backends", nargs="+", choices=["local", "s3"], default=["local", "s3"])
    ap.add_argument("--scenes", nargs="+", choices=["uploaded", "unhashed"], default=["uploaded", "unhashed"])
    ap.add_argument("--jobs", nargs="+", choices=list(JOBS), default=list(JOBS))
    args = ap.parse_args()
    bundle = args.bundle
    if bundle is None:
        bundle = args.work / f"{args.preset}-0"
        if not (bundle / "scene.json").exists():
            from panogs_core.synthetic import make_scene

            make_scene(bundle, preset=args.preset, difficulty="default", seed=0)
    run_dir = args.work / f"run-{time.strftime('%Y%m%d-%H%M%S')}"
    from panogs_core.pipeline.run import STAGES, run_pipeline

    runner.SceneCheckpoints = TimedCheckpoints  # type: ignore[misc]  # the worker's own, fetches timed
    rows: list[dict[str, Any]] = []
    with ExitStack() as stack:
        s3 = stack.enter_context(seaweedfs(run_dir / "seaweedfs")) if "s3" in args.backends else None
        envs: dict[str, tuple[leased.JobEnv, uuid.UUID]] = {}
        for backend in args.backends:
            settings = backend_settings(run_dir, backend, s3)
            storage = open_storage(settings)
            placed = place_bundle(settings, storage, bundle.resolve())
            print(f"{backend}: bundle placed in {placed:.1f} s", flush=True)
            env = leased.JobEnv(
                settings=settings,
                session_factory=get_session_factory(settings.database),
                storage=storage,
                pipeline=run_pipeline,
                make_config=device_config_factory(jobs.pipeline_config, False),
                stages=tuple(STAGES),
            )
            envs[backend] = (env, new_tenant(settings))
        for round_ in range(args.rounds):
            order = args.backends if round_ % 2 == 0 else list(reversed(args.backends))
            kinds = args.scenes if round_ % 2 == 0 else list(reversed(args.scenes))
            for backend, kind in [(backend, kind) for backend in order for kind in kinds]:
                env, tenant = envs[backend]
                scene = new_scene(env.settings, tenant, bundle, kind)
                for name in args.jobs:
                    config = JOBS[name]
                    if name == COLD:
                        forget_checkpoint_copies(env, scene)
                    load_before = load_average()
                    row = {
                        "round": round_ + 1,
                        "backend": backend,
                        "scene": kind,
                        "job": name,
                        "load": load_before,
                        **run_job(env, tenant, scene, config),
                    }
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    print(
        "\n| round | backend | scene | job | seconds | to the results s | of the first run | stages cached "
        "| checkpoint fetch s | bundle fetch s |"
    )
    print("|---|---|---|---|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        first = next(
            (
                r
                for r in rows
                if (r["round"], r["backend"], r["scene"], r["job"])
                == (row["round"], row["backend"], row["scene"], "first")
            ),
            None,
        )
        of_first = "" if first is None else f"{row['seconds'] / first['seconds']:.3f}"
        results = "" if row["results_s"] is None else f"{row['results_s']:.1f}"
        print(
            f"| {row['round']} | {row['backend']} | {row['scene']} | {row['job']} | {row['seconds']:.1f} | {results} | "
            f"{of_first} | {len(row['cached'])} | {row['fetch_s']:.2f} | "
            f"{row['bundle_s']:.1f} |"
        )
    (args.work / f"{run_dir.name}.json").write_text(json.dumps(rows, indent=1))
    if os.environ.get("BENCH_KEEP") != "1":  # the objects and run folders: gigabytes
        shutil.rmtree(run_dir, ignore_errors=True)


if __name__ == "__main__":
    main()
