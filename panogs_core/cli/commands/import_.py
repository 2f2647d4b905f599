"""``panogs import <source> SRC DST``: a capture converted into a scene bundle, one subcommand per layout of
:data:`~panogs_core.cli.commands.import_sources.IMPORT_SOURCES`, each with only its own options. (The module is
``import_``: ``import`` is a keyword.)

Before the subcommands, ``import`` took the layout as a positional argument and one list of options for every
layout, so two spellings of then need a word now:

- options before the layout (``panogs import --stride 10 scannet SRC DST``) still run, moved after it, with a note
  on stderr that gives today's spelling (:func:`options_before_source`);
- an option of another layout, which was silently ignored (``--depth-scale`` on ScanNet), is refused with a
  message naming the layouts that take it (:func:`refuse_foreign_options`).
"""

from __future__ import annotations

import argparse
import shlex
import sys
import textwrap
from functools import partial
from typing import Any

from panogs_core.cli.arguments import VOCABULARY_HELP
from panogs_core.cli.commands.import_sources import IMPORT_SOURCES, ImportSource

HELP_FLAGS = ("-h", "--help")
HELP_WIDTH = 78  # the description is kept as written (the example must stay one line to copy): wrapped here


def add_command(sub: Any) -> None:
    """Add ``import`` and one subcommand per source to an argparse subparsers object."""
    names = ", ".join(source.name for source in IMPORT_SOURCES)
    p = sub.add_parser("import", help=f"convert a capture to a bundle ({names})")
    sources = p.add_subparsers(dest="source", required=True)
    parsers = {}
    for source in IMPORT_SOURCES:
        s = sources.add_parser(
            source.name,
            help=source.help,
            description=_description(source),
            epilog=f"example:\n  {source.example}",
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        s.add_argument("src", help="the capture's folder")
        s.add_argument("dst", help="the bundle folder to write (absent or empty)")
        s.add_argument("--stride", type=int, default=1, metavar="N", help="keep every n-th frame")
        s.add_argument("--vocabulary", metavar="NAME|FILE", help=VOCABULARY_HELP)
        s.add_argument(
            "--feature-space",
            default="clip-vit-b32",
            metavar="SPACE",
            help="the feature maps' space (default %(default)s)",
        )
        source.add_options(s)
        s.set_defaults(func=run_import, import_source=source)
        parsers[source.name] = s
    for name, s in parsers.items():
        s.set_defaults(on_unknown=partial(refuse_foreign_options, s, name, _owners(parsers)))


def _description(source: ImportSource) -> str:
    """The subcommand's help: its line, then its description (when it has one), each wrapped."""
    return "\n\n".join(textwrap.fill(text, HELP_WIDTH) for text in (source.help, source.description) if text)


def run_import(args: argparse.Namespace) -> int:
    """Read ``--vocabulary``, run the source's importer, print its summary (and where the ground truth went)."""
    from panogs_core.language.label_sets import vocabulary_from_name_or_file

    vocabulary = (
        vocabulary_from_name_or_file(args.vocabulary, feature_space=args.feature_space) if args.vocabulary else None
    )
    report = args.import_source.run(args, vocabulary)
    print(report.summary())
    gt = vars(args).get("gt")  # only the sources that take --gt have it
    if gt:
        from panogs_core.io.ground_truth import is_scannet_annotation

        brought = " with vocabulary scannet20" if vocabulary is None and is_scannet_annotation(gt) else ""
        print(f"ground truth from {gt} written to gt/labels.npz{brought}")
    return 0


def _owners(parsers: dict[str, argparse.ArgumentParser]) -> dict[str, list[str]]:
    """Each option string of the sources' parsers -> the sources that take it."""
    owners: dict[str, list[str]] = {}
    for name, parser in parsers.items():
        for action in parser._actions:  # argparse lists a parser's options nowhere public
            for option in action.option_strings:
                owners.setdefault(option, []).append(name)
    return owners


def refuse_foreign_options(
    parser: argparse.ArgumentParser, source: str, owners: dict[str, list[str]], extras: list[str]
) -> None:
    """Exit through ``parser`` naming, for each unknown option of ``extras`` that another source takes, those
    sources; returns when none is another source's (the plain "unrecognized arguments" then)."""
    lines = []
    for token in extras:
        option = token.split("=", 1)[0]
        if option.startswith("-") and option in owners:
            takers = " and ".join(f"`panogs import {name}`" for name in owners[option])
            lines.append(f"{option} is an option of {takers}, not of `panogs import {source}` (see its --help)")
    if lines:
        parser.error(f"unrecognized arguments: {' '.join(extras)}\n" + "\n".join(lines))


def options_before_source(argv: list[str]) -> list[str]:
    """``argv`` with the options given between ``import`` and the source moved after the source (the spelling of
    before the subcommands), and a note with today's spelling on stderr; any other ``argv`` as it is."""
    command = next((i for i, token in enumerate(argv) if not token.startswith("-")), None)
    if command is None or argv[command] != "import" or command + 1 >= len(argv):
        return argv
    first = argv[command + 1]
    if not first.startswith("-") or first in HELP_FLAGS:
        return argv
    names = {source.name for source in IMPORT_SOURCES}
    where = next((i for i in range(command + 1, len(argv)) if argv[i] in names), None)
    if where is None:
        return argv
    moved = [*argv[: command + 1], argv[where], *argv[command + 1 : where], *argv[where + 1 :]]
    today = shlex.join(["panogs", *moved[command:]])
    print(f"panogs import: the source comes before the options now: {today}", file=sys.stderr)
    return moved
