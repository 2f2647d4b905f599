"""``panogs``'s parser and entry point: the core's commands (:mod:`panogs_core.cli.commands`), then those of the
installed extras (:mod:`panogs_core.cli.command_groups`); a user error prints one line and exits 2."""

from __future__ import annotations

import argparse
import atexit
import logging
import os
import sys
import threading
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from panogs_core.cli.command_groups import MissingGroup, add_command_groups, not_installed_text
from panogs_core.cli.commands import CORE_COMMANDS
from panogs_core.cli.commands.import_ import options_before_source
from panogs_core.errors import PanoGSError


class CommandParser(argparse.ArgumentParser):
    """``panogs``'s parsers (argparse makes each command's of the same class).

    An unknown command also names the command groups this install lacks, with the extra that brings each;
    unknown options go to the command's ``on_unknown`` (when it set one) before the plain message; and the
    ``rewrites`` read spellings of before (on the top parser only).
    """

    not_installed: tuple[MissingGroup, ...] = ()
    rewrites: tuple[Callable[[list[str]], list[str]], ...] = ()

    def error(self, message: str) -> NoReturn:
        if self.not_installed and "invalid choice" in message:
            message = f"{message}\n{not_installed_text(self.not_installed)}"
        super().error(message)

    def parse_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> argparse.Namespace:
        argv = list(sys.argv[1:] if args is None else args)
        for rewrite in self.rewrites:
            argv = rewrite(argv)
        parsed, extras = self.parse_known_args(argv, namespace)
        if extras:
            on_unknown = getattr(parsed, "on_unknown", None)
            if on_unknown is not None:
                on_unknown(extras)  # exits when it has something to say
            self.error(f"unrecognized arguments: {' '.join(extras)}")
        return parsed


def build_parser() -> argparse.ArgumentParser:
    """The argparse tree of every command."""
    parser = CommandParser(
        prog="panogs", description="Open-vocabulary 3D panoptic segmentation (PanoGS) of posed RGB-D captures."
    )
    parser.rewrites = (options_before_source,)
    parser.add_argument("-v", "--verbose", action="store_true", help="log stage details")
    sub: Any = parser.add_subparsers(dest="command", required=True)
    for add_command in CORE_COMMANDS:
        add_command(sub)
    parser.not_installed = tuple(add_command_groups(sub))
    if parser.not_installed:
        parser.epilog = not_installed_text(parser.not_installed)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``panogs``; user errors print one clear message and exit 2.

    As the process's entry (``argv`` None: the command line is ``sys.argv``), a ``run`` that succeeded ends the
    process here, without the interpreter's teardown (:func:`_end_process`).
    """
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s"
    )
    os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
    if not sys.stderr.isatty():
        # The text encoder's own bars ("Loading weights") redraw in place too, and a log keeps every frame.
        os.environ.setdefault("HF_HUB_DISABLE_PROGRESS_BARS", "1")
    try:
        code = int(args.func(args) or 0)
        if argv is None and args.command == "run" and code == 0:
            _end_process(code)
        return code
    except PanoGSError as exc:
        print(f"panogs {args.command}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


def _end_process(code: int) -> None:
    """End the process now: the exit handlers run and the output streams are flushed, the rest of the
    interpreter's teardown is skipped (it unloads torch: 0.25-0.45 s of each ``panogs run``, ``python -c "import
    torch"`` against the same with ``os._exit``). Only when this is the last thread; otherwise nothing happens and
    the process exits the usual way.
    """
    if threading.active_count() > 1:
        return
    atexit._run_exitfuncs()  # logging's flush, weakref finalizers (an extracted bundle's folder), the caller's
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    os._exit(code)
