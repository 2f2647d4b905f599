"""Are two run folders the same result? For refactors that must not move a label: every file of the first run
compared byte for byte with the second's, and the arrays of ``labels.npz`` one by one (so a difference names the
array). ``report.json`` holds timings and versions and is skipped; ``stages/`` holds checkpoints and is skipped.

Usage:
    python tools/compare_runs.py RUN_A RUN_B      # exit 0 when every compared file is identical, 1 otherwise

Example, labels before and after a change (two worktrees, the same bundle):
    (cd /tmp/before && python -m panogs_core.cli run /tmp/small0 --out /tmp/runs/before --no-resume --quiet)
    (cd /tmp/after && python -m panogs_core.cli run /tmp/small0 --out /tmp/runs/after --no-resume --quiet)
    python tools/compare_runs.py /tmp/runs/before /tmp/runs/after
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

SKIPPED = frozenset({"report.json"})


def differing_arrays(a: Path, b: Path) -> list[str]:
    """The names of the arrays of two ``.npz`` files that differ (or exist in one only)."""
    with np.load(a, allow_pickle=False) as za, np.load(b, allow_pickle=False) as zb:
        names = sorted(set(za.files) | set(zb.files))
        return [n for n in names if n not in za.files or n not in zb.files or not np.array_equal(za[n], zb[n])]


def compare(run_a: Path, run_b: Path) -> list[str]:
    """One line per difference between the top-level files of two runs; empty when they are the same."""
    names_a = {p.name for p in run_a.iterdir() if p.is_file()} - SKIPPED
    names_b = {p.name for p in run_b.iterdir() if p.is_file()} - SKIPPED
    problems = [f"{name}: only in {run_a if name in names_a else run_b}" for name in sorted(names_a ^ names_b)]
    for name in sorted(names_a & names_b):
        a, b = run_a / name, run_b / name
        if a.read_bytes() == b.read_bytes():
            continue
        if name.endswith(".npz"):
            problems.append(f"{name}: arrays differ: {', '.join(differing_arrays(a, b)) or 'none (container only)'}")
        else:
            problems.append(f"{name}: differs")
    return problems


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run_a", type=Path)
    ap.add_argument("run_b", type=Path)
    args = ap.parse_args(argv)
    problems = compare(args.run_a, args.run_b)
    compared = sorted({p.name for p in args.run_a.iterdir() if p.is_file()} - SKIPPED)
    verdict = "identical" if not problems else "DIFFERENT"
    sys.stdout.write("".join(f"{line}\n" for line in problems))
    sys.stdout.write(f"{len(compared)} files compared ({', '.join(compared)}): {verdict}\n")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
