"""An upload's bundle opened (extracted and validated) in a child process, a few at a time, within a CPU budget.

Validation reads every file of a bundle, and however bounded each check is, a hostile bundle can make their sum
long (a million empty PNG chunks cost 21 s per frame that names them; 5M face rows before a PLY's vertices 77 s).
Run in the API's request threads, that work held the interpreter's lock and the threads themselves: ``/healthz``
stalled for 20 s, and enough concurrent uploads could take every thread. So:

- each bundle is opened by :func:`panogs_core.io.bundle.open_bundle` in a child process forked from a server that
  has already imported the validator (``forkserver``: a few milliseconds a child, not an interpreter's start), so
  its CPU and memory are never the API process's;
- the child runs under a CPU budget: ``PANOGS_VALIDATION_CPU_S`` per GiB of archive (at least that much), which the
  validator checks itself before each file (a 422 naming the file it stopped at), and which the kernel enforces
  a little later (``RLIMIT_CPU``) in case one check runs long (a 422 naming the upload and the budget). A child
  still alive after several times its budget in wall time (a host too loaded to give it its CPU) is killed and
  the request is a 503: the upload is kept, to try again;
- the child's address space is capped (``PANOGS_VALIDATION_MEMORY_BYTES``, ``RLIMIT_AS``): an allocation past it
  fails in the child, a 422 naming the upload and the limit, and the host's memory is never at stake;
- at most ``PANOGS_VALIDATION_SLOTS`` bundles are opened at once per API process; the next request is a 503 with
  ``Retry-After`` at once, so waiting requests never hold the API's threads.
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import multiprocessing
import os
import resource
import signal
import threading
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from multiprocessing import forkserver, popen_forkserver, reduction, spawn, util
from multiprocessing.connection import Connection
from multiprocessing.context import ForkServerProcess, set_spawning_popen
from pathlib import Path
from typing import Any

from panogs_core.errors import BundleError
from service.errors import ServiceUnavailable

logger = logging.getLogger(__name__)

GIB = 1024**3
HARD_LIMIT_GRACE_S = 2  # the kernel's limit comes this much after the budget, so the validator's own check speaks
WALL_FACTOR = 4.0  # a child may take this many times its CPU budget in wall time (plus WALL_SLACK_S)
WALL_SLACK_S = 10.0
VALIDATION_RETRY_AFTER_S = 5
MAX_PROBLEMS_SENT = 1000  # problem lines the child sends back (the answer lists fewer; the rest is a count)
BUDGET_SETTING = "PANOGS_VALIDATION_CPU_S"
MEMORY_SETTING = "PANOGS_VALIDATION_MEMORY_BYTES"


@dataclass(frozen=True)
class OpenRequest:
    """What the child needs to open one bundle (picklable: it crosses to the child)."""

    archive: str
    workdir: str
    limits: Any  # panogs_core.io.bundle.BundleLimits (imported in the child's server, not here)
    max_bytes: int | None
    max_files: int | None


@dataclass(frozen=True)
class OpenedBundle:
    """What a scene's row needs of a valid bundle."""

    root: str
    name: str
    feature_dim: int
    feature_space: str
    num_frames: int
    has_vocabulary: bool
    has_ground_truth: bool
    has_feature_maps: bool
    has_mask_maps: bool


def cpu_budget_s(per_gib_s: float, archive_bytes: int) -> float:
    """The CPU seconds a bundle's opening may take: ``per_gib_s`` per GiB of archive, at least ``per_gib_s``
    (extraction and the framing checks grow with the bytes; the rest is bounded per file)."""
    return per_gib_s * max(1.0, archive_bytes / GIB)


def open_in_child(request: OpenRequest, conn: Connection) -> None:
    """The child's work: open the bundle and send back ``("ok", OpenedBundle)`` or ``("invalid", problems)``."""
    from panogs_core.io.bundle import open_bundle

    limits = {k: v for k, v in (("max_bytes", request.max_bytes), ("max_files", request.max_files)) if v is not None}
    try:
        bundle = open_bundle(request.archive, workdir=request.workdir, limits=request.limits, **limits)
    except MemoryError:  # over the address-space limit the parent set (RLIMIT_AS)
        conn.send(("memory", None))
        return
    except BundleError as exc:
        problems = list(exc.problems)
        if len(problems) > MAX_PROBLEMS_SENT:
            problems = [*problems[:MAX_PROBLEMS_SENT], f"... and {len(problems) - MAX_PROBLEMS_SENT:,} more problem(s)"]
        conn.send(("invalid", problems))
        return
    conn.send(
        (
            "ok",
            OpenedBundle(
                root=str(bundle.root),
                name=bundle.name,
                feature_dim=bundle.feature_dim,
                feature_space=bundle.feature_space,
                num_frames=len(bundle.frames),
                has_vocabulary=bundle.vocabulary is not None,
                has_ground_truth=bundle.has_ground_truth,
                has_feature_maps=bool(bundle.feature_frames),
                has_mask_maps=bool(bundle.mask_frames),
            ),
        )
    )


def _child_main(target: Callable[[OpenRequest, Connection], None], request: OpenRequest, conn: Connection) -> None:
    # One thread for whatever numpy does here: the child is one of several beside the API.
    os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    try:
        target(request, conn)
    finally:
        conn.close()


class BundleOpener:
    """Opens bundles in child processes, at most ``slots`` at once; one per API process (``app.state``).

    ``target`` is what the child runs (:func:`open_in_child`; a module-level function, found by name in the child).
    """

    def __init__(self, slots: int, cpu_s_per_gib: float, memory_bytes: int | None = None) -> None:
        self.slots = slots
        self.cpu_s_per_gib = cpu_s_per_gib
        self.memory_bytes = memory_bytes
        self.target: Callable[[OpenRequest, Connection], None] = open_in_child
        self.grace_s = HARD_LIMIT_GRACE_S
        self._running = 0
        self._lock = threading.Lock()

    @contextlib.contextmanager
    def slot(self) -> Iterator[None]:
        """Hold one of the slots, or answer 503 with ``Retry-After`` when all are taken (never wait for one)."""
        with self._lock:
            if self._running >= self.slots:
                raise ServiceUnavailable(
                    f"{self.slots} bundle(s) are being validated, the most at once (PANOGS_VALIDATION_SLOTS); "
                    "the upload is kept: retry shortly",
                    headers={"Retry-After": str(VALIDATION_RETRY_AFTER_S)},
                )
            self._running += 1
        try:
            yield
        finally:
            with self._lock:
                self._running -= 1

    def open(self, request: OpenRequest, filename: str) -> OpenedBundle:
        """Open the bundle in a child within its budget (call inside :meth:`slot`).

        Raises:
            BundleError: the bundle breaks the format, or spent its CPU budget (each problem names its file).
            ServiceUnavailable: the child ran past its wall-clock limit (the host, not the bundle: retry).
        """
        budget = cpu_budget_s(self.cpu_s_per_gib, Path(request.archive).stat().st_size)
        request = OpenRequest(
            request.archive, request.workdir, _with_budget(request.limits, budget), request.max_bytes, request.max_files
        )
        ctx = _context()
        receiver, sender = ctx.Pipe(duplex=False)
        child = _ChildProcess(target=_child_main, args=(self.target, request, sender), daemon=True)
        child.start()
        sender.close()
        try:
            _limit_cpu(child.pid, budget + self.grace_s)
            _limit_memory(child.pid, self.memory_bytes)
            message = _receive(receiver, WALL_FACTOR * budget + WALL_SLACK_S)
        finally:
            receiver.close()
            if child.is_alive():
                child.kill()
            child.join()
        if message is None:
            raise _ended_without_answer(child.exitcode, budget, filename)
        kind, value = message
        if kind == "invalid":
            raise BundleError(value, source=filename)
        if kind == "memory":
            raise BundleError(
                [
                    f"{filename}: validation needed more than its memory limit of {self.memory_bytes or 0:,} bytes "
                    f"of address space ({MEMORY_SETTING}) and was stopped"
                ],
                source=filename,
            )
        opened: OpenedBundle = value
        return opened


def _receive(receiver: Connection, timeout_s: float) -> tuple[str, Any] | None:
    """The child's one message, or None when it ended without one; 503 when none came within ``timeout_s``."""
    if not receiver.poll(timeout_s):
        raise ServiceUnavailable(
            f"the bundle's validation had no answer after {timeout_s:.0f} s (the host is busy); the upload is kept: "
            "retry later",
            headers={"Retry-After": str(VALIDATION_RETRY_AFTER_S)},
        )
    try:
        message: tuple[str, Any] = receiver.recv()
    except EOFError:  # the child ended without a word: killed by its budget, or crashed
        return None
    return message


def _ended_without_answer(exitcode: int | None, budget: float, filename: str) -> Exception:
    if exitcode in (-signal.SIGXCPU, -signal.SIGKILL):
        return BundleError(
            [
                f"{filename}: validation used its CPU budget of {budget:g} s for this bundle "
                f"({BUDGET_SETTING} per GiB of archive) and was stopped"
            ],
            source=filename,
        )
    request_id = uuid.uuid4().hex[:12]
    logger.error("bundle validation child ended with exit code %s without an answer (request %s)", exitcode, request_id)
    return RuntimeError(f"bundle validation failed (exit {exitcode}, request {request_id})")


def _with_budget(limits: Any, budget: float) -> Any:
    from dataclasses import replace

    return replace(limits, max_cpu_s=budget)


def _limit_memory(pid: int | None, max_bytes: int | None) -> None:
    """The kernel's address-space limit on the child: past it an allocation fails (MemoryError), never the host."""
    if pid is not None and max_bytes is not None and hasattr(resource, "prlimit"):
        with contextlib.suppress(ProcessLookupError):
            resource.prlimit(pid, resource.RLIMIT_AS, (max_bytes, max_bytes))


def _limit_cpu(pid: int | None, seconds: float) -> None:
    """The kernel's CPU limit on the child: SIGXCPU at ``seconds`` (whole, rounded up), SIGKILL a second later."""
    if pid is not None and hasattr(resource, "prlimit"):
        soft = max(1, math.ceil(seconds))
        with contextlib.suppress(ProcessLookupError):  # it already ended
            resource.prlimit(pid, resource.RLIMIT_CPU, (soft, soft + 1))


_CONTEXT_LOCK = threading.Lock()


class _PopenWithoutMain(popen_forkserver.Popen):
    """The forkserver's Popen, minus the main module in the child's preparation.

    A forkserver child otherwise runs the parent's main script again as ``__mp_main__`` before its target (under
    pytest or ``panogs serve``: their imports, seconds on a loaded host), and preloading ``__main__`` in the server
    does not prevent it on 3.11 or 3.12 (the server is never told the main's path). The child's targets are
    module-level functions of importable modules, so it needs no main. The rest is ``Popen._launch`` as it is.
    """

    def _launch(self, process_obj: Any) -> None:
        prep_data = spawn.get_preparation_data(process_obj._name)
        prep_data.pop("init_main_from_path", None)
        prep_data.pop("init_main_from_name", None)
        buf = io.BytesIO()
        set_spawning_popen(self)
        try:
            reduction.dump(prep_data, buf)
            reduction.dump(process_obj, buf)
        finally:
            set_spawning_popen(None)
        self.sentinel, w = forkserver.connect_to_new_process(self._fds)  # type: ignore[attr-defined]
        parent_w = os.dup(w)  # the parent's sentinel of the child's data pipe, as in the original
        self.finalizer = util.Finalize(self, util.close_fds, (parent_w, self.sentinel))  # type: ignore[attr-defined]
        with open(w, "wb", closefd=True) as f:
            f.write(buf.getbuffer())
        self.pid = forkserver.read_signed(self.sentinel)


class _ChildProcess(ForkServerProcess):
    @staticmethod
    def _Popen(process_obj: Any) -> Any:
        return _PopenWithoutMain(process_obj)


def _context() -> Any:
    """The forkserver context, its server preloaded with the validator (set up once per process)."""
    with _CONTEXT_LOCK:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["service.bundle_check", "panogs_core.io.bundle"])
        return ctx
