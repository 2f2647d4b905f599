"""Stages made on a thread beside a stage that keeps one core (``StageSpec.one_core``: the language field's fit).

:func:`panogs_core.pipeline.run.run_pipeline` starts them when it reaches that stage and takes each at its own place
in the stage table (docs/architecture.md, "The stage table"). Each computes on one thread, in turns on the run's
background lane with the checkpoint writes and the bundle's hash (:mod:`panogs_core.pipeline.lane`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

from panogs_core.pipeline import stage_table as st
from panogs_core.pipeline.profiling import StageStats
from panogs_core.pipeline.result import StageProgressFn
from panogs_core.threads import on_one_core

Made = tuple[Any, StageStats | None]  # a stage's value and, for a timed stage, what it cost


class Beside:
    """Stages made on one thread of their own beside a ``one_core`` stage (``StageSpec.one_core``), in table order;
    each is taken at its place in the table (:meth:`take`), where its error is raised.

    Their progress is not sent while they run: a job's stage is the one whose place in the table it has reached.
    """

    def __init__(
        self,
        leader: str,
        specs: list[st.StageSpec],
        inputs: dict[str, Any],
        compute: Callable[[st.StageSpec, list[Any], StageProgressFn | None], Made],
    ) -> None:
        self.leader = leader
        futures: list[Future[Made]] = [Future() for _ in specs]
        self._made = {spec.name: future for spec, future in zip(specs, futures, strict=True)}  # until taken
        self._thread = threading.Thread(
            target=self._make, args=(specs, futures, inputs, compute), name=f"beside-{leader}", daemon=True
        )
        self._thread.start()

    def __contains__(self, name: object) -> bool:
        return name in self._made

    def take(self, name: str) -> Made:
        """The stage's value and cost, once made (its error raised here)."""
        return self._made.pop(name).result()

    def wait(self) -> None:
        self._thread.join()

    def _make(
        self,
        specs: list[st.StageSpec],
        futures: list[Future[Made]],  # one per stage: the thread's own references (a stage taken leaves ``_made``)
        inputs: dict[str, Any],
        compute: Callable[[st.StageSpec, list[Any], StageProgressFn | None], Made],
    ) -> None:
        values = dict(inputs)  # and the values of the stages made here, for the ones after them
        inputs.clear()  # ``values`` is this thread's one reference to each: dropped after its last reader here
        last_reader = {name: at for at, spec in enumerate(specs) for name in spec.reads}
        at = 0
        try:
            with on_one_core():  # the leader keeps a core: the stages here ask for one thread each
                for at, spec in enumerate(specs):
                    value, stats = compute(spec, [values[name] for name in spec.reads], None)
                    values[spec.output] = value
                    for name in spec.reads:
                        if last_reader[name] == at:  # the fused features, once their cosines and colours are made
                            values.pop(name, None)
                    if stats is not None:
                        stats.beside = self.leader
                    futures[at].set_result((value, stats))
        except BaseException as exc:  # raised at its place; the stages after it here are not made
            for future in futures[at:]:
                future.set_exception(exc)
