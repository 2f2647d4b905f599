"""A TCP proxy that can cut a link (database or broker outages), and the process helpers of service_harness.

The API and the workers are started with exactly the commands docker-compose.yml runs (``compose_command``),
with ``panogs`` replaced by ``python -m panogs_core.cli`` (the same entry point, without needing the console
script).
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from service_harness import REPO, Procs, compose_command, free_port, wait_for

__all__ = ["REPO", "Procs", "TcpProxy", "compose_command", "free_port", "job_row", "wait_for", "worker_of"]


def job_row(database_url: str, job_id: str) -> dict[str, Any]:
    """The job's ``worker``, ``attempts`` and ``state`` as the database holds them (not as the API shows them)."""
    from sqlalchemy import create_engine, text

    engine = create_engine(database_url)
    with engine.connect() as conn:
        row = conn.execute(text("SELECT worker, attempts, state FROM job WHERE id = :id"), {"id": job_id})
        out = dict(row.mappings().one())
    engine.dispose()
    return out


def worker_of(procs: Procs, database_url: str, job_id: str) -> str:
    """The name of the worker process running the job (its pid ends the job's ``worker``)."""
    pid = int(job_row(database_url, job_id)["worker"].rsplit("/", 1)[1])
    return next(name for name, p in procs.procs.items() if p.pid == pid)


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
