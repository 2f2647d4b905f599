"""The Celery app's reliability settings, and that the worker imports no torch before it forks."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from service.settings import Settings
from worker.celery_app import create_celery_app
from worker.names import QueueName, TaskName

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


def test_embedded_broker_needs_no_server(tmp_path: Path) -> None:
    settings = Settings(_env_file=None, data_dir=tmp_path)  # type: ignore[call-arg]
    app = create_celery_app(settings)
    assert app.conf.broker_url.startswith("filesystem://")
    options = app.conf.broker_transport_options
    assert Path(options["data_folder_in"]).is_dir()
    assert options["data_folder_in"] == options["data_folder_out"]


def test_worker_modules_do_not_import_torch() -> None:
    """A prefork parent that imported torch deadlocks its children: the task module must not pull it in."""
    code = "import sys, worker.tasks, worker.celery_app, worker.runner; print('torch' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "False"
