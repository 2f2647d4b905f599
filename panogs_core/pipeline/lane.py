"""One lane for a run's background work: the stages made beside the language field's fit, the checkpoint writes and
the bundle's hash take turns on it.

The fit keeps one core (one torch thread, ``StageSpec.one_core``); the rest of the run's work meanwhile is
background: nothing on the run's thread waits for it until much later. When the stages beside, the checkpoint writer
(the fusion's 161 MB at ScanNet size) and the hash ran at once, three threads or more wanted the other core of a
2-core machine and the scheduler took the fit's core from it: its set-up, 0.3 CPU s, took 0.43-0.71 s of wall
(docs/benchmarks.md, "Language field speed"). On one lane at most one of them wants a core at a time, and a stage
beside runs its own work on one thread (:func:`panogs_core.threads.on_one_core`).

A holder waits for nothing of the run while it holds a turn (a stage's own computation, one file's write, one chunk
of the hash): a stage beside that looked up its checkpoint's key in its turn would wait for the hash, and the hash
for the lane.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

# Per process: the runs of one process (a service's jobs one after another, tests) share it; turns are short, so
# nothing waits long, and nothing waits forever.
_LANE = threading.Lock()


@contextmanager
def background_turn() -> Iterator[None]:
    """Hold the lane for one piece of background work."""
    with _LANE:
        yield
