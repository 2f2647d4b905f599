"""Running the service as real processes for end-to-end and fault tests, and a TCP proxy that can cut a link.

The API and the workers are started with exactly the commands docker-compose.yml runs (``compose_command``),
with ``panogs`` replaced by ``python -m service.cli`` (the same entry point, without needing the console
script).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import yaml

REPO = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def compose_command(service: str) -> list[str]:
    """The command a docker-compose service runs, as an argv for this machine."""
    spec = yaml.safe_load((REPO / "docker-compose.yml").read_text())["services"][service]["command"]
    argv = list(spec) if isinstance(spec, list) else spec.split()
    assert argv[0] == "panogs", f"{service}: expected a panogs command, found {argv}"
    return [sys.executable, "-m", "service.cli", *argv[1:]]


class Procs:
    """Started processes, stopped (then killed) at the end; logs under ``log_dir``."""

    def __init__(self, env: dict[str, str], log_dir: Path) -> None:
        self.env = {**os.environ, **env, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
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


class TcpProxy:
    """Forwards 127.0.0.1:<port> to a target; ``cut()`` drops every connection and refuses new ones."""

    def __init__(self, target_port: int) -> None:
        self.target = ("127.0.0.1", target_port)
        self.port = free_port()
        self._up = threading.Event()
        self._up.set()
        self._conns: list[socket.socket] = []
        self._lock = threading.Lock()
        self._server = socket.create_server(("127.0.0.1", self.port))
        self._server.settimeout(0.2)
        self._stop = threading.Event()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            if not self._up.is_set():
                client.close()
                continue
            try:
                upstream = socket.create_connection(self.target, timeout=5)
            except OSError:
                client.close()
                continue
            with self._lock:
                self._conns += [client, upstream]
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    def _pipe(self, src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                s.close()

    def cut(self) -> None:
        """Drop all connections; refuse new ones until :meth:`restore`."""
        self._up.clear()
        with self._lock:
            conns, self._conns = self._conns, []
        for s in conns:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()

    def restore(self) -> None:
        self._up.set()

    def close(self) -> None:
        self._stop.set()
        self.cut()
        self._server.close()

    @contextmanager
    def outage(self, seconds: float) -> Iterator[None]:
        """Cut the link for ``seconds`` while the body runs (the body starts right after the cut)."""
        self.cut()
        timer = threading.Timer(seconds, self.restore)
        timer.start()
        try:
            yield
        finally:
            timer.join()
