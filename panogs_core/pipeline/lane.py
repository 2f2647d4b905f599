"""One lane for a run's background work: the stages made beside the language field's fit, the checkpoint writes and
the bundle's hash take turns on it.

The fit keeps one core (one torch thread, ``StageSpec.one_core``); the rest of the run's work meanwhile is
background: nothing on the run's thread waits for it until much later. When the stages beside, the checkpoint writer
(the fusion's 161 MB at ScanNet size) and the hash ran at once, three threads or more wanted the other core of a
2-core machine and the scheduler took the fit's core from it: its set-up, 0.3 CPU s, took 0.43-0.71 s of wall
(docs/benchmarks.md, "Language field speed"). On one lane at most one of them wants a core at a time, and a stage
beside runs its own work on one thread (:func:`panogs_core.threads.on_one_core`).

Turns are taken in the order they are asked for (:class:`_TurnQueue`): the hash asks for a turn per 1 MiB chunk, and
with a plain lock its thread took the lane again before a waiting thread woke (a waiter's median wait 63 ms, the
longest 434, against a loop hashing 1 MiB chunks; docs/benchmarks_history.md, "Language field speed, ninth pass").

A holder waits for nothing of the run while it holds a turn (a stage's own computation, one file's write, one chunk
of the hash): a stage beside that looked up its checkpoint's key in its turn would wait for the hash, and the hash
for the lane.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


class _TurnQueue:
    """A lock handed to its waiters in the order they came: a thread that releases it and asks again queues behind
    them (a plain ``threading.Lock`` lets it take the lock back before a woken waiter runs)."""

    _handover = threading.Lock  # makes a waiter's lock (a test stands in one whose wait is interrupted)

    def __init__(self) -> None:
        self._book = threading.Lock()  # guards the two fields below, held for a few instructions
        self._held = False
        self._waiting: deque[Any] = deque()  # one locked lock per waiter, released to hand it the turn

    def acquire(self) -> None:
        with self._book:
            if not self._held:
                self._held = True
                return
            handover = self._handover()
            handover.acquire()
            self._waiting.append(handover)
        try:
            handover.acquire()  # until the holder hands the turn over (``_held`` stays True meanwhile)
        except BaseException:  # a signal's exception in the wait (a job's time limit): never strand the lane
            with self._book:
                if handover in self._waiting:  # not handed the turn: leave the queue
                    self._waiting.remove(handover)
                    raise
            self.release()  # handed the turn as the exception came: pass it on
            raise

    def release(self) -> None:
        with self._book:
            if self._waiting:
                self._waiting.popleft().release()
            else:
                self._held = False


# Per process: the runs of one process (a service's jobs one after another, tests) share it; turns are short and
# come in order, so nothing waits long.
_LANE = _TurnQueue()


@contextmanager
def background_turn() -> Iterator[None]:
    """Hold the lane for one piece of background work."""
    _LANE.acquire()
    try:
        yield
    finally:
        _LANE.release()
