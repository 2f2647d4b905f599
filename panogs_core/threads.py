"""How many threads the numeric libraries of one process use, and how their idle threads wait.

torch (OpenMP: the libgomp it ships), MKL, OpenBLAS and OpenCV size their pools from the machine's cores and let idle
threads spin before they sleep. On a host whose cores other processes use, those pools fight the other processes
and each other for the cores: the language-field stage took 25x longer on a busy host, where its share of the
cores called for 2-3x (docs/benchmarks.md, "Contention"). So each process gets as many threads as the cores it is
given, and idle threads sleep at once (a passive wait policy).

The pools read their environment variables once, when the library loads: :func:`apply_thread_environment` must
run before numpy or torch is imported (:func:`loaded_too_early` says when it did not), and torch's own count is
set by :func:`set_torch_threads` in the process that runs the work (after any fork). The application edges
(``panogs run``, ``panogs worker``) call these with explicit numbers; the core itself reads no environment.

The stages' per-frame work (visibility, fusion) runs a few frames ahead on that many threads: :func:`prefetched`,
sized by :func:`decode_threads`; a stage made beside another that keeps a core runs on one (:func:`on_one_core`).
"""

from __future__ import annotations

import math
import os
import sys
import threading
from collections import deque
from collections.abc import Callable, Iterator, MutableMapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import TypeVar

CGROUP_CPU_MAX = Path("/sys/fs/cgroup/cpu.max")  # cgroup v2: "<quota> <period>" in microseconds, or "max <period>"

# The thread counts of the pools a pipeline process loads: OpenMP (torch's intra-op pool, libgomp or Intel's
# libiomp), MKL, OpenBLAS (numpy's), OpenCV's own pool. They are set to the process's count, whatever the
# environment held. (open3d's TBB pool has no such variable: it follows the CPU affinity only.)
THREAD_COUNT_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "OPENCV_FOR_THREADS_NUM")

# The passive wait policy, per runtime. Defaults only: an operator who sets one keeps it.
WAIT_POLICY = {
    "OMP_WAIT_POLICY": "PASSIVE",  # libgomp and libiomp: an idle thread sleeps instead of spinning
    "KMP_BLOCKTIME": "0",  # libiomp (Intel OpenMP, MKL's Intel threading): spin 0 ms after a parallel region
    "OPENBLAS_THREAD_TIMEOUT": "4",  # OpenBLAS: spin 2^4 cycles (its least) before sleeping, not 2^28
    "OPENCV_THREAD_POOL_ACTIVE_WAIT_WORKER": "0",  # OpenCV's pool spins 2000 rounds per idle worker by default
    "OPENCV_THREAD_POOL_ACTIVE_WAIT_MAIN": "0",  # and 10000 in the calling thread
}

# Libraries that start their pools when imported: once loaded, the variables above no longer change them.
POOL_LIBRARIES = ("numpy", "torch", "scipy", "open3d", "cv2")


def cgroup_cpu_limit(cpu_max: Path = CGROUP_CPU_MAX) -> int | None:
    """The cores a cgroup v2 CPU quota allows (``quota / period``, rounded up), or None without a quota or file."""
    try:
        quota, period = cpu_max.read_text().split()[:2]
    except (OSError, ValueError):
        return None
    if quota == "max":
        return None
    try:
        return max(1, math.ceil(int(quota) / int(period)))
    except (ValueError, ZeroDivisionError):
        return None


def available_cores(cpu_max: Path = CGROUP_CPU_MAX) -> int:
    """The cores this process may run on: its CPU affinity, capped by its cgroup's CPU quota (a container's
    ``--cpus``), at least 1."""
    if hasattr(os, "sched_getaffinity"):
        cores = len(os.sched_getaffinity(0))
    else:  # macOS and Windows have no affinity call
        cores = os.cpu_count() or 1
    limit = cgroup_cpu_limit(cpu_max)
    return max(1, min(cores, limit) if limit is not None else cores)


def threads_per_process(cores: int, processes: int) -> int:
    """The threads each of ``processes`` concurrent workers gets from ``cores``: an equal share, at least 1."""
    if cores < 1 or processes < 1:
        raise ValueError(f"cores ({cores}) and processes ({processes}) must be at least 1")
    return max(1, cores // processes)


def thread_environment(threads: int) -> dict[str, str]:
    """The environment variables of ``threads`` threads per pool with a passive wait policy."""
    if threads < 1:
        raise ValueError(f"threads must be at least 1, got {threads}")
    return {**dict.fromkeys(THREAD_COUNT_VARIABLES, str(threads)), **WAIT_POLICY}


def apply_thread_environment(environ: MutableMapping[str, str], threads: int) -> None:
    """Set the thread counts in ``environ`` (this process's ``os.environ``, inherited by its children) and the
    wait policy where ``environ`` has none. Call before numpy or torch is imported."""
    for name, value in thread_environment(threads).items():
        if name in THREAD_COUNT_VARIABLES:
            environ[name] = value
        else:
            environ.setdefault(name, value)


def loaded_too_early() -> list[str]:
    """The pool libraries already imported in this process (their pools kept the sizes they started with)."""
    return [name for name in POOL_LIBRARIES if name in sys.modules]


def set_torch_threads(threads: int) -> None:
    """Set torch's intra-op threads (and its inter-op threads, while torch still allows it) in this process.

    Imports torch: call it in the process that runs the work, never in a prefork parent before it forks.
    """
    import torch

    torch.set_num_threads(threads)
    try:
        torch.set_num_interop_threads(threads)
    except RuntimeError:  # fixed once any inter-op work ran in this process; the intra-op count is what matters
        pass


@contextmanager
def torch_threads(threads: int | None) -> Iterator[None]:
    """torch's intra-op threads set to ``threads`` inside the block and restored after it; None keeps torch's.

    For one stage of a pipeline that runs best with a count of its own (a CPU fit of small kernels).
    """
    import torch

    before = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


_this_thread = threading.local()  # ``one_core``: set by :func:`on_one_core` for the thread it runs in


@contextmanager
def on_one_core() -> Iterator[None]:
    """Inside the block, this thread's stage work asks for one thread: :func:`decode_threads` and
    :func:`query_workers` give 1 (a stage made beside the language field's fit, which keeps the other core)."""
    before = getattr(_this_thread, "one_core", False)
    _this_thread.one_core = True
    try:
        yield
    finally:
        _this_thread.one_core = before


def query_workers() -> int:
    """``workers`` for scipy's cKDTree queries: every core (-1), or 1 in :func:`on_one_core`."""
    return 1 if getattr(_this_thread, "one_core", False) else -1


def decode_threads() -> int:
    """Threads for the stages' per-frame work: OpenCV's thread count (the process's, set as above), or
    torch's where that is lower (a tile's process narrows torch's count to its share of the cores); 1 in
    :func:`on_one_core`."""
    if getattr(_this_thread, "one_core", False):
        return 1
    import cv2

    threads = int(cv2.getNumThreads())
    torch = sys.modules.get("torch")  # never imported here: the count only matters once torch has been set up
    if torch is not None:
        threads = min(threads, int(torch.get_num_threads()))
    return max(1, threads)


Item = TypeVar("Item")
Result = TypeVar("Result")


def prefetched(read: Callable[[Item], Result], items: Sequence[Item], workers: int | None = None) -> Iterator[Result]:
    """``read(item)`` of each item, in order, with up to ``workers`` reads running ahead on threads.

    For the stages' per-frame image decoding (a 640 x 480 16-bit depth PNG: 4-5 ms, a mask PNG or a colour JPEG:
    1-2 ms): OpenCV decodes without the GIL, so the next frames decode on the other cores while this thread works
    on the current one, and a stage waits on the slowest of the two instead of their sum. ``workers`` defaults to
    :func:`decode_threads`; with 1, or a single item, the reads run here, one by one. An exception of a read is
    raised where its result is due.
    """
    workers = decode_threads() if workers is None else workers
    if workers <= 1 or len(items) <= 1:
        yield from map(read, items)
        return
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="prefetch")
    pending: deque[Future[Result]] = deque()
    try:
        for item in items:
            pending.append(pool.submit(read, item))
            if len(pending) > workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
