"""Tests of panogs_core.heap: freed heap memory handed back to the system."""

from __future__ import annotations

import ctypes
import sys

import pytest

from panogs_core import heap


def _resident_mb() -> float:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * 4096 / 2**20


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc and /proc: Linux")
def test_freed_heap_leaves_the_resident_size() -> None:
    # 64 KiB blocks stay under glibc's mmap threshold: they live on the heap. Every other one freed leaves free
    # chunks between held ones, which glibc keeps resident (it only shrinks the heap's top by itself).
    blocks = [bytearray(64 * 1024) for _ in range(3000)]  # about 190 MB, every page written (zero-filled)
    held = _resident_mb()
    del blocks[::2]  # about 95 MB freed
    kept = _resident_mb()
    heap.return_freed_heap()
    after = _resident_mb()
    assert kept > held - 30  # glibc kept the freed half
    assert after < kept - 60  # and gave it back when asked
    assert len(blocks) == 1500


def test_without_glibc_it_does_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    asked: list[str] = []

    def no_libc(name: str) -> None:
        asked.append(name)
        raise OSError(f"{name}: cannot open shared object file")

    monkeypatch.setattr(ctypes, "CDLL", no_libc)
    assert heap.return_freed_heap() is None  # no error escapes
    assert asked == ["libc.so.6"]  # it did look for glibc
