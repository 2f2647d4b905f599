"""Run the Alembic migrations in-process (``panogs serve`` and ``panogs keys`` on start, the tests).

The scripts ship inside this package (``service/db/migrations``) and are found with importlib.resources, so
migrating works from an installed wheel and from any working directory; no ``alembic.ini`` is read.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from alembic import command
from alembic.config import Config

MIGRATIONS_PACKAGE = "service.db.migrations"


def migrations_dir() -> Path:
    """The folder of ``env.py`` and ``versions/``, wherever the package is installed."""
    folder = Path(str(files(MIGRATIONS_PACKAGE)))
    if not (folder / "env.py").is_file():
        # A zipped install would land here: Alembic needs real files to run.
        raise FileNotFoundError(f"Alembic scripts not found under {folder}")
    return folder


def alembic_config(url: str) -> Config:
    """An Alembic config for ``url`` that depends on neither the working directory nor an ini file."""
    config = Config()
    config.set_main_option("script_location", str(migrations_dir()))
    config.attributes["url"] = url
    config.attributes["skip_logging"] = True  # keep the host application's logging as it is
    return config


def upgrade(url: str, revision: str = "head") -> None:
    """Upgrade the database at ``url`` to ``revision``."""
    command.upgrade(alembic_config(url), revision)


def downgrade(url: str, revision: str = "base") -> None:
    """Downgrade the database at ``url`` to ``revision``."""
    command.downgrade(alembic_config(url), revision)
