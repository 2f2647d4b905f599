"""Write docs/cli.md, the reference of every ``panogs`` command, from the parsers themselves.

The page is the argparse tree of ``panogs_core.cli.build_parser()``: the core's commands and those the installed
extras declare (``panogs.commands`` entry points: the service's and the worker's), each with its usage, its
arguments (name, default, help) and its example, as argparse holds them. ``--check`` fails when the page differs
from what the parsers would write, so an option added, renamed or re-explained in the code without the page fails
the test (tests/tools/test_cli_docs.py). The page lists every command, so it is written and checked only where
every extra's commands are installed.

    .venv/bin/python tools/cli_docs.py --write    # make docs-cli
    .venv/bin/python tools/cli_docs.py --check
"""

from __future__ import annotations

import argparse
import difflib
import sys
from collections.abc import Iterator
from pathlib import Path

from generated_docs import write_or_check  # tools/generated_docs.py: the script's own folder is on sys.path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's parsers, whichever checkout the environment installed


from panogs_core.cli import build_parser  # noqa: E402
from panogs_core.cli.command_groups import not_installed_text  # noqa: E402

PAGE = "docs/cli.md"
WIDTH = 100  # usage lines are wrapped at this width, whatever the terminal that writes the page
HEADER = """# The `panogs` command line

<!-- written by tools/cli_docs.py from the parsers (make docs-cli); edit the parsers, not this page -->

Every command of `panogs` with its usage and its arguments, as the parsers hold them: the core's commands
(`panogs_core/cli/commands/`) and those the `service` and `worker` extras add (their `panogs.commands` entry
points). `tools/cli_docs.py --write` writes this page and `tests/tools/test_cli_docs.py` fails when it differs from
the parsers. `panogs COMMAND --help` prints the same on a terminal; `python -m panogs_core.cli` is the same
command without the console script.
"""


class MissingCommands(SystemExit):
    """This install lacks an extra's commands, so the page cannot be written nor checked here."""


def _subcommands(parser: argparse.ArgumentParser) -> tuple[argparse._SubParsersAction | None, dict[str, str]]:
    """The parser's subcommands action and each subcommand's one-line help (argparse keeps both private)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action, {a.dest: a.help or "" for a in action._choices_actions}
    return None, {}


def _formatter(parser: argparse.ArgumentParser) -> argparse.HelpFormatter:
    return parser.formatter_class(prog=parser.prog, width=WIDTH)


def usage(parser: argparse.ArgumentParser) -> str:
    """The usage line(s), wrapped at :data:`WIDTH`."""
    formatter = _formatter(parser)
    formatter.add_usage(parser.usage, parser._actions, parser._mutually_exclusive_groups)
    return formatter.format_help().strip()


def _cell(text: str, *, code: bool = False) -> str:
    """Text for one line or table cell of Markdown: pipes escaped; outside a code span also ``<file>`` shown rather
    than read as HTML and ``*`` as written rather than emphasis."""
    text = " ".join(text.split()).replace("|", "\\|")
    return text if code else text.replace("<", "&lt;").replace("*", "\\*")


def _default(action: argparse.Action) -> str:
    if action.required and action.nargs not in ("*", "?"):  # argparse marks a positional "*" required
        return "required"
    if action.default in (None, False, argparse.SUPPRESS) or isinstance(action, argparse._StoreTrueAction):
        return ""
    return f"`{action.default}`"


def argument_rows(parser: argparse.ArgumentParser) -> list[str]:
    """One table row per argument (not ``--help`` nor a subcommands action): as ``--help`` shows it, its default
    and its help."""
    formatter = _formatter(parser)
    rows = []
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction | argparse._SubParsersAction):
            continue
        invocation = formatter._format_action_invocation(action)
        meaning = formatter._expand_help(action) if action.help else ""
        rows.append(f"| `{_cell(invocation, code=True)}` | {_default(action)} | {_cell(meaning)} |")
    return ["| argument | default | meaning |", "|---|---|---|", *rows] if rows else []


def command_section(parser: argparse.ArgumentParser, help_line: str, level: int) -> Iterator[str]:
    """The section of one parser, then those of its subcommands one level down."""
    yield f"{'#' * level} `{parser.prog}`"
    yield ""
    if help_line:
        yield _cell(help_line[0].upper() + help_line[1:] + ("" if help_line.endswith(".") else "."))
        yield ""
    yield from ("```text", usage(parser), "```", "")
    rows = argument_rows(parser)
    if rows:
        yield from (*rows, "")
    if parser.epilog:
        yield from ("```text", parser.epilog.strip(), "```", "")
    action, helps = _subcommands(parser)
    if action is None:
        return
    yield from ("| command | what it does |", "|---|---|")
    yield from (
        f"| [`{name}`](#{_anchor(p.prog)}) | {_cell(helps.get(name, ''))} |" for name, p in action.choices.items()
    )
    yield ""
    for name, sub in action.choices.items():
        yield from command_section(sub, helps.get(name, ""), level + 1)


def _anchor(title: str) -> str:
    """GitHub's anchor of a heading ``# `title` ``: lower case, spaces to hyphens, other punctuation dropped."""
    kept = (c for c in title.lower().replace(" ", "-") if c.isalnum() or c in "-_")
    return "".join(kept)


def page(parser: argparse.ArgumentParser | None = None) -> str:
    """docs/cli.md as the parsers would write it; refuses an install that lacks an extra's commands."""
    parser = parser or build_parser()
    missing = getattr(parser, "not_installed", ())
    if missing:
        raise MissingCommands(f"{PAGE} lists every command: {not_installed_text(missing)}")
    body = "\n".join(command_section(parser, parser.description or "", 2)).rstrip()
    return f"{HEADER}\n{body}\n"


def differences(root: Path = REPO) -> list[str]:
    """A unified diff of the page against the parsers' (empty when they agree)."""
    path = root / PAGE
    now = path.read_text() if path.is_file() else ""
    diff = difflib.unified_diff(now.splitlines(), page().splitlines(), f"{PAGE} (now)", f"{PAGE} (parsers)", n=1)
    return ["\n".join(diff)] if now != page() else []


def write(root: Path = REPO) -> bool:
    """Write the page; True when it changed."""
    path, text = root / PAGE, page()
    if path.is_file() and path.read_text() == text:
        return False
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return True


def main(argv: list[str] | None = None) -> int:
    return write_or_check(
        argv,
        description=__doc__.splitlines()[0],
        what=PAGE,
        source="the parsers",
        write=lambda: [PAGE] if write() else [],
        differences=differences,
        hint="run tools/cli_docs.py --write (make docs-cli)",
    )


if __name__ == "__main__":
    raise SystemExit(main())
