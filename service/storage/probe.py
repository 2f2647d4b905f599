"""Whether the object storage answers, as ``/readyz`` asks it: one cheap call (a read of a small object the probe
keeps, :func:`read_probe_object`) within a short timeout, its answer reused for a few seconds so that a load
balancer polling readiness does not become the store's load, and at most one probe in flight (a store that hangs
holds one thread, not one per poll)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout

from service.storage.objects import ObjectNotFound, ObjectStorage, StorageError

PROBE_KEY = "readyz/probe"  # a few bytes, written by the first probe that finds none
PROBE_BODY = b"panogs readiness probe\n"


def read_probe_object(objects: ObjectStorage) -> None:
    """Read the probe's object, writing it first where it is absent; raise when its bytes do not come back.

    A read, not a ``stat``: after a restart SeaweedFS answers a ``HEAD`` from its metadata seconds before it can
    serve stored bytes, and a download in that window failed with ``InternalError`` while ``/readyz`` said ready.
    """
    try:
        body = objects.get_bytes(PROBE_KEY)
    except ObjectNotFound:
        objects.put_bytes(PROBE_KEY, PROBE_BODY)
        body = objects.get_bytes(PROBE_KEY)
    if body != PROBE_BODY:
        raise StorageError(f"{PROBE_KEY} read back {len(body)} other bytes")


class StorageProbe:
    """``status()``: ``"ok"`` or ``"unavailable: <why>"``, from ``check()`` run at most every ``cache_s``."""

    def __init__(self, check: Callable[[], object], *, timeout_s: float, cache_s: float) -> None:
        self._check = check
        self._timeout_s = timeout_s
        self._cache_s = cache_s
        self._lock = threading.Lock()
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="storage-probe")
        self._running: Future[object] | None = None
        self._answer: tuple[float, str] | None = None

    def status(self) -> str:
        """The store's state, probed now or within the last ``cache_s`` seconds."""
        with self._lock:
            if self._answer is not None and time.monotonic() - self._answer[0] < self._cache_s:
                return self._answer[1]
            if self._running is None or self._running.done():
                self._running = self._pool.submit(self._check)
            running = self._running
        try:
            running.result(timeout=self._timeout_s)
            answer = "ok"
        except FutureTimeout:
            answer = f"unavailable: no answer within {self._timeout_s:g} s"
        except Exception as exc:  # any failure means not ready; its class goes into the answer, not its text
            answer = f"unavailable: {type(exc).__name__}"
        with self._lock:
            self._answer = (time.monotonic(), answer)
        return answer

    def close(self) -> None:
        """Stop the probe's thread (a probe in flight finishes on its own)."""
        self._pool.shutdown(wait=False, cancel_futures=True)
