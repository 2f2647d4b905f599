"""The background lane: turns in the order they are asked for (``pipeline/lane.py``)."""

from __future__ import annotations

import threading
import time

import pytest

from panogs_core.pipeline.lane import _TurnQueue


def _wait_until(condition: object, timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while not condition():  # type: ignore[operator]
        assert time.monotonic() < end, "timed out"
        time.sleep(0.001)


def test_a_thread_that_asks_again_queues_behind_the_waiting_one() -> None:
    """The hash asks for a turn per chunk: with a plain lock it took the lane back before a waiter woke."""
    lane, order = _TurnQueue(), []
    lane.acquire()

    def waiter() -> None:
        lane.acquire()
        order.append("waiter")
        lane.release()

    thread = threading.Thread(target=waiter)
    thread.start()
    _wait_until(lambda: len(lane._waiting) == 1)
    lane.release()
    lane.acquire()  # at once, as a loop does: after the waiter's turn
    order.append("again")
    lane.release()
    thread.join(timeout=10)
    assert order == ["waiter", "again"]


def test_one_holder_at_a_time() -> None:
    lane, inside, most = _TurnQueue(), [0], [0]
    guard = threading.Lock()

    def work() -> None:
        for _ in range(200):
            lane.acquire()
            with guard:
                inside[0] += 1
                most[0] = max(most[0], inside[0])
            with guard:
                inside[0] -= 1
            lane.release()

    threads = [threading.Thread(target=work) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=30)
    assert most[0] == 1
    assert not lane._held


class _InterruptedWait:
    """A waiter's lock whose wait ends in an exception (as a signal's does in the thread that waits)."""

    def __init__(self) -> None:
        self._calls = 0

    def acquire(self) -> None:
        self._calls += 1
        if self._calls == 2:  # the first locks it, the second is the wait
            raise KeyboardInterrupt

    def release(self) -> None:
        pass


def test_a_waiter_whose_wait_is_interrupted_leaves_the_queue() -> None:
    """Otherwise the turn would one day be handed to a thread that left, and the lane stay held for good."""
    lane = _TurnQueue()
    lane.acquire()
    lane._handover = _InterruptedWait  # type: ignore[assignment]
    with pytest.raises(KeyboardInterrupt):
        lane.acquire()
    assert not lane._waiting
    lane.release()
    assert not lane._held
    lane.acquire()  # free again
    lane.release()


def test_a_waiter_handed_the_turn_as_its_wait_is_interrupted_passes_it_on() -> None:
    lane = _TurnQueue()
    lane.acquire()

    class HandedThenInterrupted(_InterruptedWait):
        def acquire(self) -> None:
            self._calls += 1
            if self._calls == 2:
                lane.release()  # the holder hands this waiter the turn ...
                raise KeyboardInterrupt  # ... as the exception comes

    lane._handover = HandedThenInterrupted  # type: ignore[assignment]
    with pytest.raises(KeyboardInterrupt):
        lane.acquire()
    assert not lane._waiting
    assert not lane._held  # passed on: nobody waits, so the lane is free
