"""Scratch folders named by the process that owns them, so that a process starting on the same data folder can tell
the folders of a process that is gone (a worker killed with ``kill -9``, a container restarted) from those of a
live sibling (another worker process, the API extracting an upload) and remove only the first.

A folder is ``<what>-o<pid>.<start>-<random>``: ``start`` is the process's start time in clock ticks since boot
(``/proc/<pid>/stat``, field 22), so a pid reused by a later process (a container's restarted worker is often the
same small pid) does not pass for the owner. Where ``/proc`` is absent, ``start`` is 0 and the pid alone is checked.
"""

from __future__ import annotations

import os
import re
import shutil
import time
from pathlib import Path

_OWNED = re.compile(r"-o(?P<pid>\d+)\.(?P<start>\d+)-[0-9a-f]+$")
UNOWNED_GRACE_S = 24 * 3600  # a folder named before owners were recorded: removed once this old


def start_ticks(pid: int) -> int | None:
    """The start time of process ``pid`` (clock ticks since boot); 0 without ``/proc``; None when no such process."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        if Path("/proc/self/stat").exists():
            return None  # /proc is there: no such process
        return 0 if _pid_alive(pid) else None
    except OSError:
        return 0
    # The command name (field 2) may hold spaces and parentheses: count fields after its closing one.
    return int(stat[stat.rindex(")") + 2 :].split()[19])


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def owner_tag() -> str:
    """This process's part of a scratch folder's name."""
    pid = os.getpid()
    return f"o{pid}.{start_ticks(pid) or 0}"


def is_stale(folder: Path, now: float) -> bool:
    """Whether ``folder``'s owner is gone (or, for a folder without an owner in its name, it is old)."""
    match = _OWNED.search(folder.name)
    if match is None:
        try:
            return now - folder.stat().st_mtime > UNOWNED_GRACE_S
        except FileNotFoundError:
            return False
    pid, start = int(match["pid"]), int(match["start"])
    if pid == os.getpid():
        return start != (start_ticks(pid) or 0)  # ours only if we started then
    current = start_ticks(pid)
    return current is None or (start != 0 and current != 0 and current != start)


def sweep_stale(root: Path) -> list[str]:
    """Remove the scratch folders under ``root`` whose owner is gone; returns their names."""
    if not root.is_dir():
        return []
    now = time.time()
    removed = []
    for folder in root.iterdir():
        if folder.is_dir() and not folder.is_symlink() and is_stale(folder, now):
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(folder.name)
    return removed
