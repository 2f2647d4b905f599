"""Small helpers the bundle's checks share: numbers read from JSON values, problem text kept short, and the
CPU budget of one validation."""

from __future__ import annotations

import math
import time
from typing import Any


class OverBudget(Exception):
    """Validation spent its CPU budget; the message is the problem line, naming the file it stopped at."""


class CpuBudget:
    """CPU seconds of the calling thread since it was made, against a budget (None: unbounded).

    Thread time, not process time: a worker validates in one of its threads while others run.
    """

    def __init__(self, max_cpu_s: float | None) -> None:
        self.max_cpu_s = max_cpu_s
        self._start = time.thread_time()

    def spent(self) -> float:
        return time.thread_time() - self._start

    def check(self, where: str) -> None:
        """Raise :class:`OverBudget` naming ``where`` (the file or entry about to be checked) once spent."""
        if self.max_cpu_s is not None and self.spent() > self.max_cpu_s:
            raise OverBudget(
                f"{where}: validation stopped here, over its CPU budget of {self.max_cpu_s:g} s per bundle "
                f"({self.spent():.2f} s spent on the files before it)"
            )


def number(value: Any) -> float | None:
    """A finite JSON number as float, else None (booleans are not numbers here)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        number = float(value)
    except OverflowError:  # JSON integers have no size limit
        return None
    return number if math.isfinite(number) else None


def integer(value: Any) -> int | None:
    """A JSON integer (or an integral float such as 640.0), else None."""
    as_float = number(value)
    if as_float is None or as_float != int(as_float):
        return None
    return int(as_float)


def reason(exc: BaseException) -> str:
    """An exception's reason without the file name an OSError carries (an absolute path on the host)."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc)


def short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def strip_prefix(text: str, prefix: str) -> str:
    return text[len(prefix) :] if text.startswith(prefix) else text
