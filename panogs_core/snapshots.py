"""Partial work of a long stage, kept so that a stopped run resumes in the middle of the stage, not at its start.

Stage checkpoints (:mod:`panogs_core.pipeline.checkpoints`) are written when a stage ends. The appearance fit can
run for minutes (7,000 iterations on a GPU), so it also writes a snapshot of its state (parameters, optimiser
moments, the position in its frame order) every ``SNAPSHOT_EVERY_S`` seconds and when it is cancelled. A resumed run
whose stage key matches continues from the snapshot and ends with the same result as an uninterrupted run; the
checkpoint store deletes the snapshot once the stage's checkpoint is written. It sits on the core's bottom floor:
the fit (``gaussians/``) writes it and the pipeline, a floor above, places it.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

# Wall seconds between two periodic snapshots: a worker that dies loses at most this much of a fit. Writing one of
# 150k Gaussians takes 0.05 s at SH degree 1 (36 MB with the Adam moments) and 0.28 s at degree 3 (98 MB), measured
# with `python bench/snapshot_cost.py` (docs/benchmarks.md): under 1 % of the time between two.
SNAPSHOT_EVERY_S = 30.0


class StageSnapshot:
    """The latest partial state of one stage, valid only for the stage key it was made with.

    Args:
        path: The snapshot file (``stages/<stage>.partial.pt``).
        key: The stage's checkpoint key; a snapshot made under another key is ignored.
        readable: False for a run that must start afresh (``resume=False``): it still writes snapshots, so that a
            later resumed run can use them, but never reads one.
    """

    def __init__(self, path: Path, key: str, readable: bool = True) -> None:
        self.path = path
        self.key = key
        self.readable = readable

    def load(self) -> dict[str, Any] | None:
        """The saved state, or None when there is none for this key (or it cannot be read: it is then ignored)."""
        if not (self.readable and self.path.is_file()):
            return None
        import torch

        try:
            saved = torch.load(self.path, map_location="cpu", weights_only=True)
        except Exception as exc:  # a file cut short by a crash mid-write of an older version: start afresh
            log.warning("ignoring the unreadable snapshot %s: %s", self.path, exc)
            return None
        if not isinstance(saved, dict) or saved.get("key") != self.key:
            return None
        state: dict[str, Any] = saved["state"]
        return state

    def save(self, state: dict[str, Any]) -> None:
        """Write ``state`` (tensors, numbers, strings, lists and dicts of them) atomically under this key."""
        import torch

        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".tmp")
        torch.save({"key": self.key, "state": state}, tmp)
        tmp.replace(self.path)

    def discard(self) -> None:
        self.path.unlink(missing_ok=True)
