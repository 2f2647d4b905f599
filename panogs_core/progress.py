"""Progress reporting shared by every stage.

A stage's entry function takes ``on_progress: ProgressFn | None``. It calls ``on_progress(done, total)`` as it
works (per frame, per epoch, per round). The callback may raise :class:`panogs_core.errors.Cancelled` to stop the
run cooperatively; stages must let that exception through.
"""

from __future__ import annotations

from collections.abc import Callable

ProgressFn = Callable[[int, int], None]


def report(on_progress: ProgressFn | None, done: int, total: int) -> None:
    """Call ``on_progress(done, total)`` when a callback was given."""
    if on_progress is not None:
        on_progress(done, total)
