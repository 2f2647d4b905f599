"""A small thread-safe cache whose entries expire, for per-process caching of hot reads."""

from __future__ import annotations

import threading
import time
from typing import Generic, TypeVar

K = TypeVar("K")
V = TypeVar("V")


class TTLCache(Generic[K, V]):
    """Entries live ``ttl_s`` seconds; past ``max_items`` the cache is emptied rather than grown.

    A ``ttl_s`` of 0 disables it (``get`` always misses, ``put`` keeps nothing).
    """

    def __init__(self, ttl_s: float, max_items: int = 10_000) -> None:
        self.ttl_s = ttl_s
        self._max_items = max_items
        self._items: dict[K, tuple[float, V]] = {}
        self._lock = threading.Lock()

    def get(self, key: K) -> tuple[bool, V | None]:
        """(True, value) for a live entry, else (False, None)."""
        with self._lock:
            hit = self._items.get(key)
        if hit is not None and hit[0] > time.monotonic():
            return True, hit[1]
        return False, None

    def put(self, key: K, value: V) -> None:
        """Keep ``value`` for ``ttl_s`` seconds."""
        if self.ttl_s <= 0:
            return
        with self._lock:
            if len(self._items) >= self._max_items:
                self._items.clear()
            self._items[key] = (time.monotonic() + self.ttl_s, value)

    def drop(self, key: K) -> None:
        """Forget ``key``."""
        with self._lock:
            self._items.pop(key, None)
