"""Where the built front end lives: ``service/static/app`` (written by ``web/build.mjs``, carried by the wheel)."""

from __future__ import annotations

from pathlib import Path

from panogs_core.errors import InputError

STATIC_DIR = Path(__file__).resolve().parent.parent / "static" / "app"
BUILT_FILES = ("index.html", "viewer.html", "app.js", "view.js", "viewer.js", "app.css")


def static_dir() -> Path:
    """The built assets' folder.

    Raises:
        InputError: the front end was not built (a source checkout before ``make web``).
    """
    missing = [name for name in BUILT_FILES if not (STATIC_DIR / name).is_file()]
    if missing:
        raise InputError(
            f"{STATIC_DIR}: the web app is not built ({', '.join(missing)} missing); run `make web` "
            "(npm ci and npm run build in web/)"
        )
    return STATIC_DIR
