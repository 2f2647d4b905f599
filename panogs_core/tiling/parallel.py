"""Tiles of one run in several processes of this machine (``panogs run --tile-workers N``; docs/method.md §16).

Each tile is independent until the merge (its own bundle view, its own run folder), so a machine with the cores and
the memory for several tiles at once runs them side by side; the service does the same with a worker per tile.
Processes are spawned, not forked: a torch op in the parent before a fork deadlocks the child. A process opens the
bundle and the saved plan itself (no large array crosses a pipe), runs :func:`tile.run_tile` and sends back its
report row and timing; its stages' progress comes back through a queue that one thread of the parent drains into
the run's progress sink, so the display shows every running tile.
"""

from __future__ import annotations

import multiprocessing
import queue
import threading
from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any

from panogs_core.pipeline.config import PipelineConfig
from panogs_core.pipeline.profiling import StageStats
from panogs_core.pipeline.result import StageProgressFn
from panogs_core.tiling.plan import TilePlan
from panogs_core.types import Vocabulary

_DONE = None  # what the drain thread stops on


def run_tiles_in_processes(
    root: Path,
    out: Path,
    plan: TilePlan,
    cfg: PipelineConfig,
    vocab: Vocabulary,
    *,
    workers: int,
    resume: bool,
    on_progress: StageProgressFn | None,
) -> list[tuple[dict[str, Any], StageStats]]:
    """Run every tile of ``plan`` (saved under ``out``) in ``workers`` processes; their rows and timings, in plan
    order. The first tile that fails stops the others from starting and its error is raised here.

    Args:
        root: The bundle's folder (extracted when it was an archive), which each process opens.
        out: The run folder (``tiles/plan.json`` is written).
        workers: Processes at once; each gets an equal share of this process's torch threads (a tile runs as it
            would here, on fewer threads).
    """
    import torch

    threads = max(1, torch.get_num_threads() // workers)
    context = multiprocessing.get_context("spawn")
    with context.Manager() as manager:
        messages = manager.Queue()
        drain = threading.Thread(target=_drain, args=(messages, on_progress), daemon=True)
        drain.start()
        try:
            with ProcessPoolExecutor(workers, mp_context=context, initializer=_init, initargs=(threads,)) as pool:
                futures = [
                    pool.submit(_tile_task, str(root), str(out), tile.index, cfg, vocab, resume, messages)
                    for tile in plan.tiles
                ]
                done, _ = wait(futures, return_when=FIRST_EXCEPTION)
                failed = [f for f in done if f.exception() is not None]
                if failed:
                    for f in futures:
                        f.cancel()
                    raise failed[0].exception()  # type: ignore[misc]
                return [f.result() for f in futures]
        finally:
            messages.put(_DONE)
            drain.join()


def _init(threads: int) -> None:
    import torch

    torch.set_num_threads(threads)


def _tile_task(
    root: str, out: str, index: int, cfg: PipelineConfig, vocab: Vocabulary, resume: bool, messages: Any
) -> tuple[dict[str, Any], StageStats]:
    """One tile in a worker process: the bundle, the plan and the primitives' points read here."""
    from panogs_core.io.bundle import open_bundle
    from panogs_core.tiling.tile import plan_path, release_memory, run_tile

    scene = open_bundle(root)
    plan = TilePlan.load(plan_path(Path(out)))
    geometry = scene.read_geometry()
    assert geometry is not None  # a tiled plan needs geometry (runner.plan_run)
    row, stats = run_tile(scene, plan, plan.tiles[index], geometry.points, cfg, vocab, Path(out),
                          lambda stage, done, total: messages.put((stage, done, total)), resume)  # fmt: skip
    del scene, plan, geometry
    release_memory()  # the process runs the next tile next: its peak is to be its own
    return row, stats


def _drain(messages: Any, on_progress: StageProgressFn | None) -> None:
    while True:
        try:
            item = messages.get(timeout=1.0)
        except queue.Empty:
            continue
        except (EOFError, OSError):  # the manager is gone
            return
        if item is _DONE:
            return
        if on_progress is not None:
            on_progress(*item)
