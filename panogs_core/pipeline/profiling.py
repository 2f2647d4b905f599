"""Wall time and peak resident memory per pipeline stage.

Peak RSS of a stage is sampled from ``/proc/self/statm`` by a background thread (every 20 ms), because
``getrusage`` only knows the peak of the whole process lifetime.
"""

from __future__ import annotations

import os
import resource
import threading
import time
from dataclasses import dataclass
from types import TracebackType

_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def current_rss_bytes() -> int:
    """Resident set size of this process now (0 where /proc is unavailable)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * _PAGE
    except (OSError, ValueError, IndexError):
        return 0


def lifetime_peak_rss_bytes() -> int:
    """Peak RSS over the process lifetime (Linux reports kilobytes)."""
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


@dataclass
class StageStats:
    """What one stage cost."""

    name: str
    wall_s: float = 0.0
    peak_rss_mb: float = 0.0
    cached: bool = False
    beside: str = ""  # the stage it ran beside (its time overlaps that one's), or "" when it ran alone

    def to_json(self) -> dict[str, object]:
        """Plain dict for report.json (``beside`` only for a stage that ran beside another)."""
        row: dict[str, object] = {
            "stage": self.name,
            "wall_s": round(self.wall_s, 3),
            "peak_rss_mb": round(self.peak_rss_mb, 1),
            "cached": self.cached,
        }
        if self.beside:
            row["beside"] = self.beside
        return row


class StageTimer:
    """Context manager measuring wall time and sampled peak RSS of a block."""

    def __init__(self, name: str, interval_s: float = 0.02) -> None:
        self.stats = StageStats(name)
        self._interval = interval_s
        self._stop = threading.Event()
        self._peak = 0
        self._thread: threading.Thread | None = None
        self._t0 = 0.0

    def _sample(self) -> None:
        while not self._stop.wait(self._interval):
            self._peak = max(self._peak, current_rss_bytes())

    def __enter__(self) -> StageTimer:
        self._peak = current_rss_bytes()
        self._thread = threading.Thread(target=self._sample, name=f"rss-{self.stats.name}", daemon=True)
        self._thread.start()
        self._t0 = time.perf_counter()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stats.wall_s = time.perf_counter() - self._t0
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._peak = max(self._peak, current_rss_bytes())
        self.stats.peak_rss_mb = self._peak / 2**20
