"""What ``panogs import <source>`` needs of the capture importers: per source its text (:mod:`.source_cli`: help,
description, example, options), its options dataclass and its import function, and the function that builds the
options dataclass from parsed values. The command line builds one subcommand per entry of
:data:`~panogs_core.io.importers.source_cli.CAPTURE_CLIS` and runs it through :data:`CAPTURE_SOURCES`.

Example:
    >>> from panogs_core.io.importers.tum import TumOptions
    >>> opts = options_from_values(TumOptions, {"camera": "freiburg1", "selection.stride": 5})
    >>> (opts.camera, opts.selection.stride, opts.max_time_difference)
    ('freiburg1', 5, 0.02)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from panogs_core.errors import InputError
from panogs_core.io.importers.capture import CaptureReport, FrameSelection, MapSources
from panogs_core.io.importers.nerfstudio import NerfstudioOptions, import_nerfstudio
from panogs_core.io.importers.record3d import Record3DOptions, import_record3d
from panogs_core.io.importers.source_cli import NERFSTUDIO_CLI, RECORD3D_CLI, TUM_CLI, SourceCli
from panogs_core.io.importers.tum import TumOptions, import_tum


def options_from_values(cls: type[Any], values: dict[str, Any]) -> Any:
    """A source's options dataclass from ``{field: value}`` (fields as in :class:`CliOption`; ``maps.vocabulary``
    takes an already resolved :class:`Vocabulary`). Missing fields keep their defaults.

    Raises:
        InputError: for a field the dataclass does not have, or a value its checks refuse.
    """
    groups: dict[str, dict[str, Any]] = {"selection": {}, "maps": {}, "": {}}
    for key, value in values.items():
        group, _, name = key.rpartition(".")
        if group not in groups:
            raise InputError(f"import: unknown option field {key!r}")
        paths = ("features", "masks", "intrinsics")
        groups[group][name] = Path(value) if isinstance(value, str) and name in paths else value
    known = {f.name for f in fields(cls)}
    unknown = set(groups[""]) - known
    if unknown:
        raise InputError(f"import: {cls.__name__} has no field {', '.join(sorted(unknown))}")
    try:
        selection, maps = FrameSelection(**groups["selection"]), MapSources(**groups["maps"])
    except TypeError as exc:
        raise InputError(f"import: {exc}") from exc
    return cls(selection=selection, maps=maps, **groups[""])


@dataclass(frozen=True)
class CaptureSource:
    """One row of the table: the command line's text, the options class and the import function."""

    cli: SourceCli
    options: type[Any]
    run: Callable[..., CaptureReport]  # run(src, dst, options, *, on_progress=None)


CAPTURE_SOURCES: dict[str, CaptureSource] = {
    "nerfstudio": CaptureSource(NERFSTUDIO_CLI, NerfstudioOptions, import_nerfstudio),
    "record3d": CaptureSource(RECORD3D_CLI, Record3DOptions, import_record3d),
    "tum": CaptureSource(TUM_CLI, TumOptions, import_tum),
}
