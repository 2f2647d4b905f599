"""The commands of the installed extras: the ``panogs.commands`` entry points, each named for the extra it needs.

``pyproject.toml`` declares ``service = "service.cli:add_service_commands"`` and ``worker =
"worker.cli:add_worker_commands"``; :func:`add_command_groups` loads them, so that the core never names the
service or the worker. A group whose extra is not installed is left out and named (:class:`MissingGroup`), with
the ``pip install`` that brings it.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from importlib.metadata import Distribution, EntryPoint, PackageNotFoundError, distribution, entry_points
from typing import Any

COMMAND_GROUP = "panogs.commands"  # entry points "<extra> = module:add_commands" (pyproject.toml)
_REQUIREMENT = re.compile(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(?:\[([^\]]*)\])?")
_EXTRA_MARKER = re.compile(r"""\bextra\s*==\s*['"]([^'"]+)['"]""")


@dataclass(frozen=True)
class MissingGroup:
    """A command group this install lacks: its entry point's name, the extra that brings it and what is missing."""

    name: str
    install: str | None  # e.g. "pip install 'panogs[service]'"; None when no extra of that name exists
    missing: tuple[str, ...]

    def describe(self) -> str:
        how = f"{self.install}; " if self.install else ""
        return f"the {self.name} commands ({how}this install lacks {', '.join(self.missing)})"


def not_installed_text(groups: Iterable[MissingGroup]) -> str:
    """One sentence naming the command groups this install lacks and how to install them."""
    return "Not installed: " + "; ".join(group.describe() for group in groups) + "."


def add_command_groups(sub: Any, groups: Iterable[EntryPoint] | None = None) -> list[MissingGroup]:
    """Add the commands of every ``panogs.commands`` entry point (default: the installed ones) to ``sub``.

    Each entry point is named for the extra its commands need (``service``, ``worker``) and names a function
    that adds them to an argparse subparsers object; the core never imports those packages itself. A group is
    skipped, and returned, when that extra's distributions are not installed or loading it misses a third-party
    module; any other error of loading it, above all an import error of our own code, is raised.
    """
    found = sorted(entry_points(group=COMMAND_GROUP) if groups is None else groups, key=lambda ep: ep.name)
    # Our packages: a module of theirs that is missing is a bug to show, not an extra to install.
    own = {"panogs_core"} | {ep.module.partition(".")[0] for ep in found}
    skipped = []
    for ep in found:
        dist: Distribution | None = getattr(ep, "dist", None)
        missing = _missing_distributions(dist, ep.name)
        if not missing:
            try:
                add = ep.load()
            except ModuleNotFoundError as exc:
                if exc.name is None or exc.name.partition(".")[0] in own:
                    raise
                missing = (exc.name,)
            else:
                add(sub)
                continue
        install = f"pip install '{dist.name}[{ep.name}]'" if dist is not None and _has_extra(dist, ep.name) else None
        skipped.append(MissingGroup(ep.name, install, missing))
    return skipped


def _normal(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _extra_requirements(dist: Distribution) -> dict[str, list[tuple[str, list[str]]]]:
    """``dist``'s requirements by extra: (distribution name, its extras) per line of ``Requires-Dist``."""
    by_extra: dict[str, list[tuple[str, list[str]]]] = {}
    for line in dist.requires or ():
        spec, _, marker = line.partition(";")
        extra, name = _EXTRA_MARKER.search(marker), _REQUIREMENT.match(spec)
        if extra is not None and name is not None:
            extras = [e.strip() for e in (name[2] or "").split(",") if e.strip()]
            by_extra.setdefault(_normal(extra[1]), []).append((name[1], extras))
    return by_extra


def _has_extra(dist: Distribution, extra: str) -> bool:
    return _normal(extra) in _extra_requirements(dist)


def _missing_distributions(dist: Distribution | None, extra: str) -> tuple[str, ...]:
    """The distributions that ``extra`` of ``dist`` requires and this install lacks, through the extras of
    ``dist`` that it includes (``worker`` is ``panogs[service,pipeline]``); none when ``dist`` has no such extra."""
    if dist is None:
        return ()
    by_extra = _extra_requirements(dist)
    todo, seen, missing = [_normal(extra)], set(), set()
    while todo:
        current = todo.pop()
        if current in seen:
            continue
        seen.add(current)
        for name, extras in by_extra.get(current, ()):
            if _normal(name) == _normal(dist.name):
                todo.extend(_normal(e) for e in extras)
                continue
            try:
                distribution(name)
            except PackageNotFoundError:
                missing.add(name)
    return tuple(sorted(missing))
