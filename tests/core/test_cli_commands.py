"""How ``panogs`` takes in the commands of the extras: ``panogs.commands`` entry points, each named for its extra.

A made-up distribution (``fakepanogs``, a ``.dist-info`` folder in tmp_path) declares the groups, so that every
case runs without installing anything: an extra that is installed, one that is not, one that includes another,
a third-party module missing at load, and our own import errors, which must not be hidden.
"""

from __future__ import annotations

import argparse
import sys
import textwrap
from collections.abc import Iterator
from importlib.metadata import EntryPoint, PathDistribution
from pathlib import Path

import pytest

from panogs_core.cli import command_groups
from panogs_core.cli.main import main as cli_main

MODULES = {
    "fake_tools_cli": "def add(sub):\n    sub.add_parser('hello').set_defaults(func=lambda args: 0)\n",
    "fake_server_cli": "raise AssertionError('a group whose extra is missing must not be imported')\n",
    "fake_third_party_cli": "import no_such_third_party_module_for_panogs\n",
    "fakeown/__init__.py": "",
    "fakeown/cli.py": "import fakeown.helpers_that_were_renamed\n",
    "fake_core_cli": "import panogs_core.no_such_module_for_panogs\n",
    "fake_name_cli": "from panogs_core.errors import NoSuchErrorForPanogs\n",
}
METADATA = """\
Metadata-Version: 2.1
Name: fakepanogs
Version: 1.0
Provides-Extra: tools
Requires-Dist: pyyaml>=6; extra == "tools"
Provides-Extra: server
Requires-Dist: no-such-distribution-for-panogs>=1; extra == "server"
Requires-Dist: pyyaml; extra == "server"
Provides-Extra: everything
Requires-Dist: fakepanogs[server,tools]; extra == "everything"
"""


@pytest.fixture
def fake(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[PathDistribution]:
    """The made-up distribution, with its command modules importable."""
    for name, source in MODULES.items():
        path = tmp_path / (name if name.endswith(".py") else f"{name}.py")
        path.parent.mkdir(exist_ok=True)
        path.write_text(source)
    monkeypatch.syspath_prepend(str(tmp_path))
    info = tmp_path / "fakepanogs-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(METADATA)
    yield PathDistribution(info)
    for name in [*sys.modules]:
        if name.startswith(("fake_", "fakeown")):
            del sys.modules[name]


def groups(dist: PathDistribution, **values: str) -> list[EntryPoint]:
    """Entry points of ``dist`` (so that each knows its distribution), declared as ``name=value``."""
    lines = "".join(f"{name} = {value}\n" for name, value in values.items())
    info = Path(str(dist.locate_file("fakepanogs-1.0.dist-info")))
    (info / "entry_points.txt").write_text(f"[{command_groups.COMMAND_GROUP}]\n{lines}")
    return list(dist.entry_points.select(group=command_groups.COMMAND_GROUP))


def subparsers() -> argparse._SubParsersAction[argparse.ArgumentParser]:
    return argparse.ArgumentParser().add_subparsers(dest="command")


def test_a_group_whose_extra_is_installed_adds_its_commands(fake: PathDistribution) -> None:
    sub = subparsers()
    assert command_groups.add_command_groups(sub, groups(fake, tools="fake_tools_cli:add")) == []
    assert "hello" in sub.choices


def test_a_group_whose_extra_is_missing_is_left_out_unimported_and_named(fake: PathDistribution) -> None:
    sub = subparsers()
    skipped = command_groups.add_command_groups(
        sub, groups(fake, server="fake_server_cli:add", tools="fake_tools_cli:add")
    )
    assert "hello" in sub.choices, "the other group is still added"
    assert [(s.name, s.install, s.missing) for s in skipped] == [
        ("server", "pip install 'fakepanogs[server]'", ("no-such-distribution-for-panogs",))
    ]
    assert "fake_server_cli" not in sys.modules


def test_an_extra_that_includes_another_needs_what_that_one_needs(fake: PathDistribution) -> None:
    (skipped,) = command_groups.add_command_groups(subparsers(), groups(fake, everything="fake_tools_cli:add"))
    assert skipped.missing == ("no-such-distribution-for-panogs",)
    assert skipped.install == "pip install 'fakepanogs[everything]'"


def test_a_third_party_module_missing_at_load_leaves_the_group_out(fake: PathDistribution) -> None:
    (skipped,) = command_groups.add_command_groups(subparsers(), groups(fake, tools="fake_third_party_cli:add"))
    assert skipped.missing == ("no_such_third_party_module_for_panogs",)


@pytest.mark.parametrize(
    ("module", "error"),
    [
        ("fakeown.cli", ModuleNotFoundError),  # a module of the group's own package, renamed
        ("fake_core_cli", ModuleNotFoundError),  # a module of the core
        ("fake_name_cli", ImportError),  # a name our module does not have
    ],
)
def test_our_own_import_errors_are_raised(fake: PathDistribution, module: str, error: type[Exception]) -> None:
    with pytest.raises(error):
        command_groups.add_command_groups(subparsers(), groups(fake, tools=f"{module}:add"))


def test_help_and_an_unknown_command_say_what_to_install(
    fake: PathDistribution, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    declared = groups(fake, server="fake_server_cli:add", tools="fake_tools_cli:add")
    monkeypatch.setattr(command_groups, "entry_points", lambda group: [ep for ep in declared if ep.group == group])
    with pytest.raises(SystemExit):
        cli_main(["--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "hello" in help_text
    assert "Not installed: the server commands (pip install 'fakepanogs[server]'; this install lacks" in help_text
    with pytest.raises(SystemExit) as exit_:
        cli_main(["serve"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'serve'" in err
    assert "pip install 'fakepanogs[server]'" in err


def test_an_entry_point_not_named_for_an_extra_says_only_what_is_missing(fake: PathDistribution) -> None:
    (skipped,) = command_groups.add_command_groups(subparsers(), groups(fake, plugin="fake_third_party_cli:add"))
    assert skipped.install is None
    assert skipped.describe() == "the plugin commands (this install lacks no_such_third_party_module_for_panogs)"


def test_the_installed_panogs_declares_its_groups() -> None:
    """The groups pyproject.toml declares, as the installed metadata has them (the lead reinstalls at merge)."""
    declared = {ep.name: ep.value for ep in command_groups.entry_points(group=command_groups.COMMAND_GROUP)}
    pyproject = (Path(__file__).resolve().parents[2] / "pyproject.toml").read_text()
    section = pyproject.split(f'[project.entry-points."{command_groups.COMMAND_GROUP}"]\n', 1)[1].split("\n\n", 1)[0]
    expected = dict(line.replace('"', "").split(" = ") for line in textwrap.dedent(section).splitlines())
    assert declared == expected
