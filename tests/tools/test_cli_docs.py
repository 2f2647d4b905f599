"""docs/cli.md is the parsers' (tools/cli_docs.py): every command and subcommand of ``panogs`` with its usage and
arguments; an option added, removed or re-explained in the code without the page fails here."""

from __future__ import annotations

import argparse
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from tool_modules import load_tool

from panogs_core.cli import build_parser
from panogs_core.cli.command_groups import MissingGroup

REPO = Path(__file__).resolve().parents[2]

tool = load_tool("cli_docs")


@pytest.fixture
def parser() -> argparse.ArgumentParser:
    """``panogs``'s parser, where every extra's commands are installed (the page lists them all)."""
    built = build_parser()
    if getattr(built, "not_installed", ()):
        pytest.skip("this install lacks an extra's commands, which docs/cli.md lists")
    return built


def _parsers(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _parsers(sub)


def _source_parser(parser: argparse.ArgumentParser, *names: str) -> argparse.ArgumentParser:
    for name in names:
        (action,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = action.choices[name]
    return parser


def test_the_page_is_the_parsers(parser: argparse.ArgumentParser) -> None:
    problems = tool.differences()
    assert problems == [], "\n".join(problems) + "\nrun tools/cli_docs.py --write (make docs-cli)"


def test_every_command_and_option_has_its_place(parser: argparse.ArgumentParser) -> None:
    page = (REPO / tool.PAGE).read_text()
    progs = [p.prog for p in _parsers(parser)]
    assert {"panogs import scannet", "panogs import sevenscenes", "panogs keys revoke", "panogs worker"} <= set(progs)
    for sub in _parsers(parser):
        assert f"# `{sub.prog}`\n" in page, sub.prog
        for action in sub._actions:
            for option in action.option_strings:
                assert option in page, f"{sub.prog} {option}"
    assert page.count("panogs import sevenscenes 7scenes/") == 1, "the example, once"


def test_an_option_added_in_the_code_changes_the_page(parser: argparse.ArgumentParser) -> None:
    before = tool.page(build_parser())
    _source_parser(parser, "import", "scannet").add_argument("--frame-rate", type=float, default=0.001, help="m")
    after = tool.page(parser)
    assert "| `--frame-rate FRAME_RATE` | `0.001` | m |" in after
    assert "--frame-rate" not in before


def test_a_stale_page_is_found_and_written_back(parser: argparse.ArgumentParser, tmp_path: Path) -> None:
    (tmp_path / "docs").mkdir()
    shutil.copy(REPO / tool.PAGE, tmp_path / tool.PAGE)
    page = tmp_path / tool.PAGE
    page.write_text(page.read_text().replace("| `--depth-scale VALUE` | `6553.5` |", "| `--depth-scale VALUE` | `1` |"))
    (problem,) = tool.differences(tmp_path)
    assert "-| `--depth-scale VALUE` | `1` |" in problem
    assert "+| `--depth-scale VALUE` | `6553.5` |" in problem
    assert tool.write(tmp_path)
    assert tool.differences(tmp_path) == []
    assert not tool.write(tmp_path), "nothing left to write"


def test_an_install_without_an_extras_commands_is_refused() -> None:
    lacking = build_parser()
    lacking.not_installed = (MissingGroup("worker", "pip install 'panogs[worker]'", ("celery",)),)  # type: ignore[attr-defined]
    with pytest.raises(tool.MissingCommands, match=r"pip install 'panogs\[worker\]'"):
        tool.page(lacking)
