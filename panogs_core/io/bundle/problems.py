"""Small helpers the bundle's checks share: numbers read from JSON values, and problem text kept short."""

from __future__ import annotations

import math
from typing import Any


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
