"""The core's commands, one module each: ``add_command(sub)`` adds the command's parser to an argparse subparsers
object and sets its ``func``, which takes the parsed arguments and returns the exit status. Each imports what is
heavy inside its ``func``, so that ``panogs --help`` and the parsing of any command load no numeric library."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from panogs_core.cli.commands import eval, import_, query, render, run, synth, validate

# In the order of ``panogs --help``.
CORE_COMMANDS: tuple[Callable[[Any], None], ...] = (
    synth.add_command,
    import_.add_command,
    validate.add_command,
    run.add_command,
    eval.add_command,
    query.add_command,
    render.add_command,
)
