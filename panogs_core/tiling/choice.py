"""The ``--tiles`` value (``auto``, ``off`` or ``NxM``), parsed without the planner's imports.

argparse applies an option's type to its string default, so ``panogs run`` parses ``auto`` on every start. The
planner imports numpy and OpenCV, and once those are loaded the CLI can no longer size their thread pools
(panogs_core/threads.py): this module imports nothing numeric.
"""

from __future__ import annotations

import re

TILES_AUTO = "auto"
TILES_OFF = "off"
_GRID = re.compile(r"^([1-9][0-9]?)x([1-9][0-9]?)$")


def parse_tiles(text: str) -> str | tuple[int, int]:
    """``auto``, ``off`` or ``NxM`` (tiles along x, along y); ValueError otherwise.

    >>> parse_tiles("2x3"), parse_tiles("auto")
    ((2, 3), 'auto')
    """
    if text in (TILES_AUTO, TILES_OFF):
        return text
    match = _GRID.match(text)
    if match is None:
        raise ValueError(f"--tiles: expected auto, off or NxM (e.g. 2x2), got {text!r}")
    return int(match.group(1)), int(match.group(2))
