"""``panogs serve`` and ``panogs keys``; added to the ``panogs`` CLI by ``add_service_commands``.

``panogs serve`` with no configuration is the embedded deployment: it upgrades the SQLite database under
``./panogs-data`` (or ``PANOGS_DATA_DIR``), starts one worker (``panogs worker``, from the ``worker`` package) as
a child process on the filesystem broker, and serves the API with uvicorn in this process. Ctrl-C stops both: the
worker hands a running job back to the queue at its next progress step (it resumes from its last finished stage
on the next start). The worker is another process, started by its command line: this module never imports it.

Also runnable as ``python -m service.cli serve|keys``.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import os
import signal
import subprocess
import sys
import threading
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the settings import pydantic: imported inside the commands, so `panogs --help` stays quick
    from service.settings import Settings

WORKER_STOP_GRACE_S = 20.0  # after Ctrl-C, how long the worker may take to hand its job back
WORKER_RESTART_DELAY_S = 2.0  # a worker that died is replaced after this (not in a tight loop)
PARENT_PID_ENV = "PANOGS_SERVE_PID"  # set by serve for its worker, which stops when serve is gone
# What the embedded worker runs: the `panogs worker` command of the panogs entry point.
WORKER_COMMAND = ("-m", "panogs_core.cli", "worker")
# The modules a worker needs beyond the API's; an API-only install (`panogs[service]`) has none of them.
WORKER_MODULES = ("torch", "open3d")

logger = logging.getLogger("panogs.serve")


def add_service_commands(subparsers: Any) -> None:
    """Add ``serve`` and ``keys`` to an argparse subparsers object."""
    p = subparsers.add_parser("serve", help="run the API (and, embedded, a worker): the batch service")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--data-dir", help="embedded data folder (PANOGS_DATA_DIR; default ./panogs-data)")
    p.add_argument("--no-worker", action="store_true", help="API only (the scaled deployment runs workers apart)")
    p.add_argument("--api-processes", type=int, default=1, help="uvicorn worker processes")
    p.set_defaults(func=cmd_serve)

    p = subparsers.add_parser("keys", help="administer API keys (each key is a tenant)")
    p.add_argument("--data-dir", help="embedded data folder (PANOGS_DATA_DIR)")
    keys = p.add_subparsers(dest="keys_command", required=True)
    k = keys.add_parser("create", help="create a key and print it (it is shown only once)")
    k.add_argument("--name", required=True, help="who the key is for")
    k.set_defaults(func=cmd_keys_create)
    k = keys.add_parser("list", help="list keys (never their secrets)")
    k.set_defaults(func=cmd_keys_list)
    k = keys.add_parser("revoke", help="revoke a key by id or prefix")
    k.add_argument("key", help="key id or prefix")
    k.set_defaults(func=cmd_keys_revoke)

    from service.viewer.cli import add_viewer_commands

    add_viewer_commands(subparsers)


def settings_from_args(args: argparse.Namespace) -> Settings:
    """The settings, with ``--data-dir`` (when given) in force here and in the children this process starts."""
    from pydantic import ValidationError

    from service.settings import get_settings

    if getattr(args, "data_dir", None):
        os.environ["PANOGS_DATA_DIR"] = args.data_dir  # children (worker, uvicorn) read the same
        get_settings.cache_clear()
    try:
        return get_settings()
    except ValidationError as exc:
        # One line per wrong setting, naming it: in a container this is all the operator's log shows of why the
        # API never became healthy (a traceback buried it before).
        lines = [f"{'.'.join(str(p) for p in e['loc']) or 'settings'}: {e['msg']}" for e in exc.errors()]
        raise SystemExit("panogs: the settings are not valid:\n  " + "\n  ".join(lines)) from None


def _prepare_database(settings: Any) -> None:
    from service.db.migrate import upgrade

    settings.ensure_dirs()
    if settings.auto_migrate:
        upgrade(settings.database)


def _out(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def missing_worker_modules() -> list[str]:
    """The modules of ``WORKER_MODULES`` that this install lacks (looked up, not imported)."""
    return [name for name in WORKER_MODULES if importlib.util.find_spec(name) is None]


def cmd_serve(args: argparse.Namespace) -> int:
    """Migrate, start the worker child (unless --no-worker), serve the API until Ctrl-C."""
    import uvicorn

    missing = [] if args.no_worker else missing_worker_modules()
    if missing:
        # Fail now, not at the first job: an API-only install cannot run the embedded worker.
        sys.stderr.write(
            f"panogs serve: the embedded worker needs {', '.join(missing)}, which this install lacks; install the "
            "worker (pip install 'panogs[worker]') or run the API alone with `panogs serve --no-worker`\n"
        )
        return 2
    settings = settings_from_args(args)
    logging.basicConfig(level=settings.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    _prepare_database(settings)
    worker = None if args.no_worker else WorkerSupervisor(on_exit=_requeue_jobs_of(settings))
    if worker is not None:
        worker.start()
    # The API's own array work is small (queries over a few hundred instances): one BLAS thread per call is
    # fastest, while several spin against each other on a busy machine (measured: 1.4 ms against 8 ms per
    # query). Set after the worker started, which keeps its threads for the pipeline.
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(name, "1")
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # docker stop: same clean path as Ctrl-C
    try:
        uvicorn.run(
            "service.api_app:create_app",
            factory=True,
            host=args.host,
            port=args.port,
            workers=args.api_processes if args.api_processes > 1 else None,
            log_level=settings.log_level.lower(),
        )
    except KeyboardInterrupt:
        pass
    finally:
        if worker is not None:
            worker.stop()
    return 0


def _requeue_jobs_of(settings: Any) -> Any:
    """What the supervisor calls with a dead worker's pid: its running job goes back to the queue at once."""

    def requeue(pid: int) -> None:
        from service.db.session import get_session_factory
        from service.reaper import requeue_dead_worker

        try:
            requeue_dead_worker(get_session_factory(settings.database), pid)
        except Exception:  # the heartbeat timeout still catches the job; the supervisor must keep going
            logger.exception("could not re-queue the jobs of worker %d", pid)

    return requeue


class WorkerSupervisor:
    """The embedded worker: a child process, restarted if it dies while ``serve`` runs, stopped in order.

    When the child dies, ``on_exit(pid)`` runs first (serve re-queues its running job at once: the worker is known
    dead, no need to wait for its heartbeat to time out)."""

    def __init__(self, on_exit: Any = None) -> None:
        self._on_exit = on_exit
        self._proc: subprocess.Popen[bytes] | None = None
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="panogs-worker-supervisor", daemon=True)

    def _spawn(self) -> None:
        command = [sys.executable, *WORKER_COMMAND]
        # Its own session: the terminal's Ctrl-C reaches only us, and we stop the worker in order.
        env = {**os.environ, PARENT_PID_ENV: str(os.getpid())}
        self._proc = subprocess.Popen(command, start_new_session=True, env=env)
        logger.info("worker started (pid %d)", self._proc.pid)

    def start(self) -> None:
        """Start the worker and watch it."""
        self._spawn()
        self._thread.start()

    def _watch(self) -> None:
        while not self._stopping.is_set():
            assert self._proc is not None
            code = self._proc.wait()
            if self._stopping.is_set():
                return
            if self._on_exit is not None:
                self._on_exit(self._proc.pid)
            if self._stopping.wait(WORKER_RESTART_DELAY_S):
                return
            logger.error("worker exited with %s; starting a new one (its job resumes)", code)
            self._spawn()

    def stop(self) -> None:
        """Warm shutdown (the running job is handed back at its next step), then kill after a grace period."""
        self._stopping.set()
        proc = self._proc
        if proc is None or proc.poll() is not None:
            return
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=WORKER_STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            logger.warning("worker did not stop within %.0f s; killing it", WORKER_STOP_GRACE_S)
            proc.kill()
            proc.wait()


def cmd_keys_create(args: argparse.Namespace) -> int:
    """Print a new key; only its hash is stored."""
    from service.auth import create_api_key
    from service.db.session import get_session_factory, session_scope

    settings = settings_from_args(args)
    _prepare_database(settings)
    with session_scope(get_session_factory(settings.database)) as session:
        row, key = create_api_key(session, args.name)
    sys.stderr.write(f"created key {row.id} (prefix {row.prefix}) for {row.name!r}; it is shown only once:\n")
    _out(key)
    return 0


def cmd_keys_list(args: argparse.Namespace) -> int:
    """A table of keys: id, prefix, name, created, revoked."""
    from service.auth import list_api_keys
    from service.db.session import get_session_factory, session_scope

    settings = settings_from_args(args)
    _prepare_database(settings)
    with session_scope(get_session_factory(settings.database)) as session:
        rows = list_api_keys(session)
        _out(f"{'id':<36}  {'prefix':<12}  {'created':<20}  {'revoked':<20}  name")
        for r in rows:
            revoked = r.revoked_at.strftime("%Y-%m-%d %H:%M:%S") if r.revoked_at else "-"
            _out(f"{r.id!s:<36}  {r.prefix:<12}  {r.created_at:%Y-%m-%d %H:%M:%S}  {revoked:<20}  {r.name}")
    return 0


def cmd_keys_revoke(args: argparse.Namespace) -> int:
    """Revoke a key (API processes stop accepting it within ``api_key_cache_s``)."""
    from service.auth import revoke_api_key
    from service.db.session import get_session_factory, session_scope

    settings = settings_from_args(args)
    _prepare_database(settings)
    with session_scope(get_session_factory(settings.database)) as session:
        row = revoke_api_key(session, args.key)
    if row is None:
        sys.stderr.write(f"no key with id or prefix {args.key!r}\n")
        return 1
    _out(f"revoked {row.id} ({row.prefix}, {row.name})")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m service.cli``: the service commands on their own."""
    parser = argparse.ArgumentParser(prog="panogs", description="panogs batch service")
    add_service_commands(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
