"""Argument types and helpers that several commands share.

Parsing runs before ``panogs run`` sizes the thread pools (:func:`limit_threads`), and argparse converts string
defaults too: nothing here may import numpy, torch or OpenCV at module level or while converting an argument.
"""

from __future__ import annotations

import argparse
import os
from typing import Any

from panogs_core.errors import PanoGSError

VOCABULARY_HELP = "scannet20 | matterport21 | path to vocabulary.json"


def parse_overrides(pairs: list[str]) -> dict[str, Any]:
    """``section.key=value`` pairs (values parsed as YAML) into a nested dict."""
    import yaml

    out: dict[str, Any] = {}
    for pair in pairs:
        if "=" not in pair:
            raise PanoGSError(f"--set {pair!r}: expected section.key=value")
        dotted, raw = pair.split("=", 1)
        node = out
        parts = dotted.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = yaml.safe_load(raw)
    return out


def limit_threads(requested: int | None) -> None:
    """Size torch's, OpenMP's and BLAS's pools for this run (``--threads``, default the cores this process may
    use) with idle threads sleeping instead of spinning: a busy host then slows a run by the share of the cores
    it lost, not many times more (panogs_core/threads.py). Before the pipeline's imports: the pools read the
    environment when their library loads."""
    from panogs_core.threads import apply_thread_environment, available_cores, loaded_too_early, set_torch_threads

    if loaded_too_early():  # called in a process that already runs numpy/torch (a test, a notebook): its pools
        if requested is not None:  # are its own; only an explicit --threads changes torch's count
            set_torch_threads(requested)
        return
    threads = requested if requested is not None else available_cores()
    apply_thread_environment(os.environ, threads)
    set_torch_threads(threads)


def positive_int(text: str) -> int:
    """An argparse type: a whole number of at least 1."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number of at least 1, got {text!r}")
    return value


def tiles_choice(text: str) -> str | tuple[int, int]:
    """An argparse type: ``--tiles auto|off|NxM``."""
    from panogs_core.tiling.choice import parse_tiles  # not plan.py: it loads numpy (argparse parses the default)

    try:
        return parse_tiles(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc
