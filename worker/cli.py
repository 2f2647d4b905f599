"""``panogs worker``: a Celery worker for jobs, added to the ``panogs`` CLI by ``add_worker_commands``.

Also runnable as ``python -m worker.cli worker``. ``panogs serve`` starts one as a child process (the embedded
deployment) and passes its own pid in ``PANOGS_SERVE_PID``, so that the child stops when serve is gone.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
import time
from typing import TYPE_CHECKING, Any

from service.cli import PARENT_PID_ENV, settings_from_args

if TYPE_CHECKING:  # imported inside the command, so that `panogs --help` does not load pydantic
    from service.settings import Settings

logger = logging.getLogger("panogs.worker")


def add_worker_commands(subparsers: Any) -> None:
    """Add ``worker`` to an argparse subparsers object."""
    p = subparsers.add_parser("worker", help="run a Celery worker for jobs")
    p.add_argument("--data-dir", help="embedded data folder (PANOGS_DATA_DIR)")
    p.add_argument("--queues", help="comma-separated queues (PANOGS_WORKER_QUEUES; default cpu)")
    p.add_argument("--loglevel", default="INFO")
    p.set_defaults(func=cmd_worker)


def worker_argv(settings: Settings, queues: str | None, loglevel: str) -> list[str]:
    """The Celery worker command line for ``settings``."""
    return [
        "worker",
        f"--loglevel={loglevel}",
        f"--queues={queues or settings.worker_queues}",
        f"--pool={settings.worker_pool}",
        f"--concurrency={settings.worker_concurrency}",
        "--prefetch-multiplier=1",
        f"--hostname=panogs-{os.getpid()}@%h",
        "--without-gossip",
        "--without-mingle",
    ]


def _stop_when_orphaned(parent_pid: int) -> None:
    """In the embedded worker: warm-shutdown once ``serve`` is gone, even if it was killed with SIGKILL."""
    while os.getppid() == parent_pid:
        time.sleep(1.0)
    logger.warning("serve (pid %d) is gone; stopping this worker", parent_pid)
    os.kill(os.getpid(), signal.SIGTERM)


def limit_threads(settings: Settings) -> int:
    """Size the OpenMP and BLAS pools of this process and of the job processes it forks, with a passive wait
    policy (panogs_core/threads.py); returns the thread count. Runs before anything imports numpy or torch: the
    pools read these variables once, when their library loads."""
    from panogs_core.threads import apply_thread_environment, loaded_too_early

    threads = settings.worker_thread_count
    apply_thread_environment(os.environ, threads)
    early = loaded_too_early()
    if early:  # a bug of this command's imports, not the operator's: say so rather than run with full pools
        logger.warning("%s loaded before the thread limits were set; their pools ignore them", ", ".join(early))
    return threads


def cmd_worker(args: argparse.Namespace) -> int:
    """Run a Celery worker in this process until stopped."""
    settings = settings_from_args(args)
    limit_threads(settings)  # before the Celery app's imports (numpy among them)
    from worker.celery_app import create_worker_app

    settings.ensure_dirs()
    parent = os.environ.get(PARENT_PID_ENV)
    if parent:
        threading.Thread(target=_stop_when_orphaned, args=(int(parent),), daemon=True).start()
    create_worker_app(settings).worker_main(worker_argv(settings, args.queues, args.loglevel))
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m worker.cli``: the worker command on its own."""
    parser = argparse.ArgumentParser(prog="panogs", description="panogs job worker")
    add_worker_commands(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
