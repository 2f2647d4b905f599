"""The Celery apps: the broker's reliability settings, the worker's registered task and the settings it runs with,
and that the worker imports no torch before it forks."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import pytest

from service.broker import QueueName, TaskName, create_celery_app
from service.settings import Settings
from worker import tasks
from worker.celery_app import create_worker_app

REPO = Path(__file__).resolve().parents[2]


def test_reliability_settings(tmp_path: Path) -> None:
    settings = Settings(_env_file=None, data_dir=tmp_path, broker_url="redis://127.0.0.1:6379/0",  # type: ignore[call-arg]
                        broker_key_prefix="p:", job_queue="gpu")  # fmt: skip
    conf = create_celery_app(settings).conf
    assert conf.task_acks_late is True
    assert conf.task_reject_on_worker_lost is True
    assert conf.worker_prefetch_multiplier == 1
    assert conf.task_create_missing_queues is False
    assert {q.name for q in conf.task_queues} == {q.value for q in QueueName}
    assert conf.task_routes[TaskName.RUN_JOB.value] == {"queue": "gpu"}
    assert conf.broker_transport_options["visibility_timeout"] > settings.job_time_limit_s
    assert conf.broker_transport_options["global_keyprefix"] == "p:"
    assert conf.result_backend is None


def test_embedded_broker_app_writes_nothing(tmp_path: Path) -> None:
    """Building an app configures it; the folders are made by the commands that start (``ensure_dirs``)."""
    settings = Settings(_env_file=None, data_dir=tmp_path / "data")  # type: ignore[call-arg]
    app = create_celery_app(settings)
    assert app.conf.broker_url.startswith("filesystem://")
    options = app.conf.broker_transport_options
    assert options["data_folder_in"] == options["data_folder_out"]
    assert Path(options["data_folder_in"]).is_relative_to(tmp_path / "data")
    assert not (tmp_path / "data").exists()
    settings.ensure_dirs()
    assert Path(options["data_folder_in"]).is_dir()


def test_worker_app_runs_jobs_with_the_settings_it_was_given(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Explicit settings win over the environment, and the job environment is built by the first task only."""
    monkeypatch.setenv("PANOGS_JOB_QUEUE", "not-this-queue")  # what the environment would say
    settings = Settings(_env_file=None, data_dir=tmp_path / "data", job_queue="gpu")  # type: ignore[call-arg]
    built: list[Settings] = []
    monkeypatch.setattr(tasks, "build_job_env", lambda s, _shutdown: built.append(s) or "env")
    monkeypatch.setattr(tasks, "run_job", lambda env, job_id, **_kw: f"{env}:{job_id}")
    app = create_worker_app(settings)
    assert built == [], "the app was built, but no task ran yet"
    task = app.tasks[TaskName.RUN_JOB.value]
    assert task.acks_late is True
    assert task.apply(args=["job-1"]).get() == "env:job-1"
    assert task.apply(args=["job-2"]).get() == "env:job-2"
    assert built == [settings], "one environment per process, from the settings passed to the app"


def test_lazy_job_env_is_built_once_under_concurrency(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    settings = Settings(_env_file=None, data_dir=tmp_path)  # type: ignore[call-arg]
    calls: list[int] = []
    monkeypatch.setattr(tasks, "build_job_env", lambda _s, _e: calls.append(1) or object())
    envs = tasks.LazyJobEnv(settings, threading.Event())
    results: list[object] = []
    threads = [threading.Thread(target=lambda: results.append(envs.get())) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1
    assert len({id(r) for r in results}) == 1


def test_worker_modules_do_not_import_torch(tmp_path: Path) -> None:
    """A prefork parent that imported torch deadlocks its children: building the worker app must not pull it
    in (the CUDA check and the pipeline are loaded by the first task)."""
    code = (
        "import sys, worker.tasks, worker.celery_app, worker.runner, worker.cli, worker.device\n"
        "from service.settings import Settings\n"
        "worker.celery_app.create_worker_app(Settings(_env_file=None, data_dir=sys.argv[1]))\n"
        "print('torch' in sys.modules)"
    )
    argv = [sys.executable, "-c", code, str(tmp_path / "data")]
    done = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "False"
