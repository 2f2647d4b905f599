"""Helpers for tests and benchmarks of the service: throwaway PostgreSQL databases, Redis key prefixes, and
the service run as real processes with the commands docker-compose.yml runs. A test helper, not shipped: the
tests find it through ``pythonpath`` (pyproject.toml), a benchmark puts ``tests/support`` on ``sys.path``.

Each test session gets its own database (``panogs_test_<random>``) and its own Redis key prefix, so that it
never touches anyone else's data on a shared server, and removes them when it ends.

When PostgreSQL or Redis cannot be reached, :func:`require_service` skips the tests that need it on a developer's
machine, and fails them under CI (``CI=true``), naming the service and how to start it: a CI run must not pass
without testing the service.
"""

from __future__ import annotations

import os
import secrets
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml
from sqlalchemy import create_engine, make_url, text

REPO = Path(__file__).resolve().parents[2]
SUPPORT = Path(__file__).resolve().parent  # this folder: the test doubles a started worker imports
DEFAULT_PG_ADMIN_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
DEFAULT_REDIS_URL = "redis://127.0.0.1:6379/0"
# The servers the tests use: from the environment (a database this user may create databases from, a Redis), else
# the local defaults.
PG_ADMIN_URL = os.environ.get("PANOGS_TEST_PG_ADMIN_URL", DEFAULT_PG_ADMIN_URL)
REDIS_URL = os.environ.get("PANOGS_TEST_REDIS_URL", DEFAULT_REDIS_URL)
# The heartbeat timeout of the service the process tests start: a killed worker's job is re-queued after it, and
# the storage and database outages they make (2 s) stay well inside it.
HEARTBEAT_TIMEOUT_S = 5.0
SCRIPTED_PIPELINE = "scripted_pipeline"  # the test double of the pipeline (pipeline_stand_in.py)

# How to start each service on a Debian machine like CI's (the commands .ci/run runs).
START_POSTGRES = "pg_ctlcluster --skip-systemctl-redirect $(ls /etc/postgresql) main start"
START_REDIS = (
    "redis-server --daemonize yes --bind 127.0.0.1 -::1 --port 6379 --save '' --appendonly no "
    "--dir /var/lib/redis --logfile /var/log/redis/ci.log"
)


def under_ci() -> bool:
    """True in a CI run (CI=true, as CI systems and .ci/run set it)."""
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


def require_service(name: str, url: str, reachable: bool, start: str) -> None:
    """Skip (on a developer's machine) or fail (under CI) when the service ``name`` at ``url`` is unreachable."""
    if reachable:
        return
    message = f"{name} is not reachable at {url}; start it with: {start}"
    if under_ci():
        pytest.fail(f"CI=true and {message}", pytrace=False)
    pytest.skip(message)


def require_postgres(admin_url: str = DEFAULT_PG_ADMIN_URL) -> None:
    """:func:`require_service` for PostgreSQL."""
    require_service("PostgreSQL", admin_url, postgres_reachable(admin_url), START_POSTGRES)


def require_redis(url: str = DEFAULT_REDIS_URL) -> None:
    """:func:`require_service` for Redis."""
    require_service("Redis", url, redis_reachable(url), START_REDIS)


@contextmanager
def temp_postgres(admin_url: str = DEFAULT_PG_ADMIN_URL) -> Iterator[str]:
    """Create an empty database next to ``admin_url``'s, yield its URL, drop it afterwards."""
    name = f"panogs_test_{secrets.token_hex(4)}"
    admin = create_engine(admin_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    try:
        yield make_url(admin_url).set(database=name).render_as_string(hide_password=False)
    finally:
        from service.db.session import get_engine

        get_engine.cache_clear()
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


def postgres_reachable(admin_url: str = DEFAULT_PG_ADMIN_URL) -> bool:
    """True when PostgreSQL answers at ``admin_url``."""
    engine = create_engine(admin_url, connect_args={"connect_timeout": 2})
    try:
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
        return True
    except Exception:  # any failure means not reachable
        return False
    finally:
        engine.dispose()


def new_redis_prefix() -> str:
    """A Redis key prefix of our own (kombu ``global_keyprefix``)."""
    return f"panogs_test_{secrets.token_hex(4)}:"


def drop_redis_prefix(url: str, prefix: str) -> int:
    """Delete every key under ``prefix``; returns how many."""
    import redis

    client = redis.Redis.from_url(url)
    try:
        keys = list(client.scan_iter(match=f"{prefix}*", count=500))
        if keys:
            client.delete(*keys)
        return len(keys)
    finally:
        client.close()


def redis_reachable(url: str = DEFAULT_REDIS_URL) -> bool:
    """True when Redis answers at ``url``."""
    import redis

    client = redis.Redis.from_url(url, socket_connect_timeout=2)
    try:
        return bool(client.ping())
    except Exception:  # any failure means not reachable
        return False
    finally:
        client.close()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def compose_command(service: str) -> list[str]:
    """The command a docker-compose service runs, as an argv for this machine (``panogs`` is the console script
    of ``panogs_core.cli``)."""
    spec = yaml.safe_load((REPO / "docker-compose.yml").read_text())["services"][service]["command"]
    argv = list(spec) if isinstance(spec, list) else spec.split()
    assert argv[0] == "panogs", f"{service}: expected a panogs command, found {argv}"
    return [sys.executable, "-m", "panogs_core.cli", *argv[1:]]


def python_path() -> str:
    """PYTHONPATH for a started process: the repository and the test doubles (``scripted_pipeline``), with the
    ``sitecustomize.py`` that puts one in place of the pipeline when ``PANOGS_TEST_PIPELINE`` names it."""
    return os.pathsep.join([str(REPO), str(SUPPORT)])


class Procs:
    """Started processes, stopped (then killed) at the end; logs under ``log_dir``."""

    def __init__(self, env: dict[str, str], log_dir: Path) -> None:
        self.env = {**os.environ, **env, "PYTHONPATH": python_path(), "PYTHONUNBUFFERED": "1"}
        self.log_dir = log_dir
        self.procs: dict[str, subprocess.Popen[bytes]] = {}

    def start(self, name: str, argv: list[str], **env: str) -> subprocess.Popen[bytes]:
        log = (self.log_dir / f"{name}.log").open("ab")
        proc = subprocess.Popen(argv, env={**self.env, **env}, cwd=self.log_dir, stdout=log,
        stderr=subprocess.STDOUT,
                                start_new_session=True)  # fmt: skip
        self.procs[name] = proc
        return proc

    def api(self, name: str = "api", port: int | None = None, **env: str) -> str:
        """Start the API with the compose command; returns its base URL once /healthz answers."""
        port = port or free_port()
        argv = compose_command("api")
        for flag, value in (("--host", "127.0.0.1"), ("--port", str(port))):
            argv[argv.index(flag) + 1] = value  # compose listens on 0.0.0.0:8000 in its container
        proc = self.start(name, argv, **env)
        url = f"http://127.0.0.1:{port}"

        def up() -> bool:
            assert proc.poll() is None, f"{name} exited:\n{self.tail(name)()}"
            return httpx.get(f"{url}/healthz", timeout=1).status_code == 200

        wait_for(up, 60, f"{name} to start", self.tail(name))
        return url

    def worker(self, name: str = "worker", **env: str) -> subprocess.Popen[bytes]:
        """Start a worker with the compose command."""
        return self.start(name, compose_command("worker"), **env)

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        proc = self.procs.pop(name)
        if proc.poll() is None:
            os.killpg(proc.pid, sig)
        proc.wait(timeout=30)

    def tail(self, name: str, lines: int = 40) -> Any:
        def text() -> str:
            path = self.log_dir / f"{name}.log"
            return "\n".join(path.read_text(errors="replace").splitlines()[-lines:]) if path.exists() else ""

        return text

    def kill_all(self) -> None:
        """SIGKILL every process group: for a teardown that checks nothing of the shutdown (an idle Celery
        worker's warm shutdown takes 4-5 s). A process that starts another session of its own (``panogs serve``
        does, for its worker) needs :meth:`stop_all`."""
        for name in list(self.procs):
            self.kill(name)

    def stop_all(self) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + 20
        for proc in self.procs.values():
            try:
                proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        self.procs.clear()


def wait_for(check: Any, timeout: float, what: str, context: Any = None, interval: float = 0.2) -> None:
    """Poll ``check()`` until true; fail with ``context()`` (e.g. a log tail) after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if check():
                return
        except (httpx.HTTPError, OSError):
            pass
        time.sleep(interval)
    detail = context() if context else ""
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}\n{detail}")
