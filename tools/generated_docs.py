"""The command line every docs generator under tools/ shares: ``--write`` rewrites what it generates, ``--check``
fails (exit 1) naming each difference and the command that mends it.

Each generator (run_folder_docs, reference_docs, cli_docs, layer_sketch) gives its own write and difference
functions; a test of each runs its ``--check`` against the repository (tests/tools).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable


def write_or_check(
    argv: list[str] | None,
    *,
    description: str,
    what: str,  # the text the help names, e.g. "the tables between the markers"
    source: str,  # what it is generated from, e.g. "the declaration"
    write: Callable[[], list[str]],  # writes; returns the files it changed
    differences: Callable[[], list[str]],  # one line per difference
    after_write: Callable[[], list[str]] = list,  # problems a write cannot mend (checked after it)
    hint: str,  # the command that mends a difference
) -> int:
    """Parse ``--write`` / ``--check`` from ``argv`` and do it; the exit status."""
    parser = argparse.ArgumentParser(description=description)
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--write", action="store_true", help=f"rewrite {what}")
    mode.add_argument("--check", action="store_true", help=f"fail when {what} and {source} differ")
    args = parser.parse_args(argv)
    if args.write:
        changed = write()
        sys.stdout.write(
            f"wrote {', '.join(changed)}\n" if changed else f"nothing to write: {what} and {source} agree\n"
        )
        problems = after_write()
    else:
        problems = differences()
    if problems:
        sys.stderr.write("\n".join([*problems, hint]) + "\n")
    return 1 if problems else 0
