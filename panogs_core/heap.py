"""Handing freed heap memory back to the system (glibc), so that a process's resident size follows what it holds.

glibc keeps memory that was freed on its heaps for later allocations: after a stage's temporaries are freed the
process stays that much larger, and a next allocation served by fresh pages (a large array is its own mapping)
adds to it. At ScanNet size the language field's training left 45-60 MB of its freed temporaries resident while
its decoding allocated the (N, D) output, which was the run's peak (docs/benchmarks.md, "Language field speed").
"""

from __future__ import annotations

import ctypes


def return_freed_heap() -> None:
    """Ask glibc to give its heaps' free memory back to the system (``malloc_trim(0)``); a no-op without glibc."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc (macOS, musl): nothing to do
        pass
