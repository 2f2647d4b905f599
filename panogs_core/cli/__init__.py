"""The ``panogs`` command line: synth, import, validate, run, eval, query, render, and the commands of the
installed extras, found through the ``panogs.commands`` entry points.

- :mod:`~panogs_core.cli.main`: the parser and ``main`` (the console script ``panogs_core.cli:main``);
- :mod:`~panogs_core.cli.commands`: one module per core command (``import``'s sources in ``import_sources``);
- :mod:`~panogs_core.cli.command_groups`: the entry-point loader of the extras' commands;
- :mod:`~panogs_core.cli.display`: progress and result tables on the terminal;
- :mod:`~panogs_core.cli.arguments`: argument types and helpers the commands share.

Every command calls the same library functions as the service. Heavy modules are imported inside the commands,
so ``panogs --help`` is instant.
"""

from panogs_core.cli.main import build_parser, main

__all__ = ["build_parser", "main"]
