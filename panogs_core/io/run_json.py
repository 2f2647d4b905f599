"""The JSON files of a finished run's folder, read with errors that say which file and what to check."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from panogs_core.errors import InputError


def read_run_json(path: Path) -> Any:
    """The parsed JSON of one file of a run folder.

    Raises:
        InputError: the file is missing (naming the folder it expected to be a run's) or is not valid JSON.
    """
    if not path.is_file():
        raise InputError(f"{path}: missing; is {path.parent} the --out folder of a finished run?")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not valid JSON ({exc})") from exc
