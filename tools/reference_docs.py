"""Write the settings reference and the module lists of ``service/`` and ``worker/`` from the code they describe.

- docs/settings.md: every field of the pydantic-settings classes of ``service/settings.py``, with its environment
  variable, type, default, bounds and description. The description is the field's ``description=`` when it has one,
  else its comment in the source (the comment at the end of its line, or the lines of comment right above it); a
  comment after a blank line heads a group of fields (``# Uploads.``).
- docs/architecture.md: one table per package, a row per module with the first sentence of its docstring.

Both stand between markers; ``--check`` fails when either differs from the code (or a module has no docstring).

    .venv/bin/python tools/reference_docs.py --write    # make docs-tables
    .venv/bin/python tools/reference_docs.py --check
"""

from __future__ import annotations

import ast
import difflib
import importlib
import io
import json
import re
import sys
import textwrap
import tokenize
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import annotated_types
from generated_docs import write_or_check  # tools/generated_docs.py: the script's own folder is on sys.path
from pydantic.fields import FieldInfo
from pydantic_settings import BaseSettings

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's modules, whichever checkout the environment installed

SETTINGS_MODULE = "service.settings"
SETTINGS_DOC = "docs/settings.md"
MODULES_DOC = "docs/architecture.md"
PACKAGES = ("service", "worker")
# Not modules a reader looks for: one file per database revision (their list is the folder).
SKIPPED = ("service/db/migrations/versions/",)
# The fields before the first group comment of a class have no heading of their own.
FIRST_GROUP = "Data, database, broker and storage"

SETTINGS_BEGIN = "<!-- settings:begin (written by tools/reference_docs.py from service/settings.py) -->"
SETTINGS_END = "<!-- settings:end -->"
MODULES_BEGIN = "<!-- modules:begin (written by tools/reference_docs.py from the docstrings) -->"
MODULES_END = "<!-- modules:end -->"

BOUNDS = ((annotated_types.Gt, ">"), (annotated_types.Ge, "≥"), (annotated_types.Lt, "<"), (annotated_types.Le, "≤"))


def _cell(text: str) -> str:
    """Text for one table cell: reStructuredText literals as Markdown ones, no pipe that would split the row, and
    no ``<`` outside code that Markdown would read as a tag (``<data_dir>``)."""
    text = re.sub(r":[a-z]+:`([^`]+)`", r"`\1`", text).replace("``", "`").replace("|", "\\|")
    parts = text.split("`")
    parts[::2] = [part.replace("<", "\\<") for part in parts[::2]]  # even parts are outside code spans
    return "`".join(parts).strip()


def _paragraph(text: str) -> list[str]:
    """Prose as the docs write it: lines of at most 120 characters."""
    return textwrap.wrap(_cell(" ".join(text.split())), 120, break_long_words=False, break_on_hyphens=False)


# -- settings -------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FieldSource:
    """What the source says about one field beyond pydantic: its annotation and default as written, its comment."""

    annotation: str
    default: str | None
    comment: str
    group: str


def _comments(source: str) -> dict[int, str]:
    """Line number -> the text of the comment on that line."""
    found = {}
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            found[token.start[0]] = token.string.lstrip("#").strip()
    return found


def _default_source(node: ast.AnnAssign, source: str) -> str | None:
    """The default as written: ``value`` or ``Field(default=value, ...)``'s."""
    value = node.value
    if value is None:
        return None
    if isinstance(value, ast.Call) and getattr(value.func, "id", None) == "Field":
        value = next((k.value for k in value.keywords if k.arg == "default"), value.args[0] if value.args else None)
    return None if value is None else ast.get_source_segment(source, value)


def field_sources(cls_node: ast.ClassDef, source: str) -> dict[str, FieldSource]:
    """Each annotated field of a class as its source writes it, with its comment and its group."""
    comments = _comments(source)
    lines = source.splitlines()
    found: dict[str, FieldSource] = {}
    group = FIRST_GROUP
    for node in cls_node.body:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        above: list[str] = []
        line = node.lineno - 1  # 1-based number of the line above the field
        while line in comments and lines[line - 1].lstrip().startswith("#"):
            above.insert(0, comments[line])
            line -= 1
        if above and not lines[line - 1].strip():  # a comment after a blank line heads the fields that follow
            group, above = " ".join(above).rstrip("."), []
        trailing = comments.get(node.end_lineno or node.lineno, "")
        annotation = ast.get_source_segment(source, node.annotation) or ""
        comment = " ".join([*above, trailing]).strip()
        found[node.target.id] = FieldSource(annotation, _default_source(node, source), comment, group)
    return found


def _bounds(info: FieldInfo) -> str:
    parts = [
        f"{sign} {getattr(m, type(m).__name__.lower())}"
        for m in info.metadata
        for kind, sign in BOUNDS
        if isinstance(m, kind)
    ]
    return ", ".join(parts) or "-"


def _default_cell(value: Any, written: str | None) -> str:
    """The default as a value, and as the source writes it when that reads otherwise (``16 * GIB``)."""
    if value is None:
        return "none"
    shown = json.dumps(value) if isinstance(value, str | bool) else str(value)
    try:
        plain = written is None or ast.literal_eval(written) == value
    except ValueError:
        plain = written == f'Path("{value}")'
    return f"`{shown}`" if plain else f"`{shown}` (`{written}`)"


def _env_name(cls: type[BaseSettings], name: str, info: FieldInfo) -> str:
    alias = info.validation_alias if isinstance(info.validation_alias, str) else info.alias
    return alias or f"{cls.model_config.get('env_prefix', '')}{name}".upper()


def settings_classes(module_name: str = SETTINGS_MODULE) -> list[tuple[type[BaseSettings], ast.ClassDef, str]]:
    """The pydantic-settings classes a module defines, each with its parsed source."""
    module = importlib.import_module(module_name)
    source = Path(module.__file__ or "").read_text(encoding="utf-8")
    nodes = {n.name: n for n in ast.parse(source).body if isinstance(n, ast.ClassDef)}
    return [
        (obj, nodes[name], source)
        for name, obj in vars(module).items()
        if isinstance(obj, type) and issubclass(obj, BaseSettings) and obj is not BaseSettings and name in nodes
    ]


def settings_reference(module_name: str = SETTINGS_MODULE) -> list[str]:
    """docs/settings.md's tables: per class and group of fields, a row per field."""
    out: list[str] = []
    for cls, node, source in settings_classes(module_name):
        sources = field_sources(node, source)
        out += ["", f"### `{cls.__name__}`", "", *_paragraph(ast.get_docstring(node) or "")]
        group = None
        for name, info in cls.model_fields.items():
            written = sources[name]
            if written.group != group:
                group = written.group
                heading, _, rest = re.split(r"(?<=[^.:])([.:] )", group + ". ", maxsplit=1)
                out += ["", f"#### {_cell(heading)}", ""]
                rest = rest.strip().rstrip(".")
                out += [*_paragraph(rest[:1].upper() + rest[1:] + "."), ""] if rest else []
                out.append("| variable | type | default | bounds | description |")
                out.append("|---|---|---|---|---|")
            description = info.description or written.comment or "-"
            out.append(
                f"| `{_env_name(cls, name, info)}` | `{_cell(written.annotation)}` | "
                f"{_default_cell(info.default, written.default)} | {_bounds(info)} | {_cell(description)} |"
            )
    return out[1:]


# -- module lists ---------------------------------------------------------------------------------------------------


def summary(docstring: str) -> str:
    """The first sentence of a docstring's first paragraph, on one line."""
    paragraph = " ".join(docstring.strip().split("\n\n", 1)[0].split())
    match = re.match(r"(.+?[.!?])(?=\s|$)", paragraph)
    return match.group(1) if match else paragraph


def package_modules(package: str, root: Path = REPO) -> list[Path]:
    """Every module of a package, the package's own ``__init__.py`` first, then by path."""
    paths = [p for p in (root / package).rglob("*.py") if not p.relative_to(root).as_posix().startswith(SKIPPED)]
    return sorted(paths, key=lambda p: (p.relative_to(root / package).parts != ("__init__.py",), p.as_posix()))


def module_rows(package: str, root: Path = REPO) -> tuple[list[str], list[str]]:
    """A table row per module of ``package``, and the modules that have no docstring."""
    rows, missing = ["| module | what it is |", "|---|---|"], []
    for path in package_modules(package, root):
        name = path.relative_to(root).as_posix()
        docstring = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")))
        if not docstring:
            missing.append(name)
            continue
        rows.append(f"| `{name}` | {_cell(summary(docstring))} |")
    return rows, missing


def module_lists(root: Path = REPO) -> list[str]:
    """docs/architecture.md's block: one table per package."""
    out: list[str] = []
    for package in PACKAGES:
        rows, _ = module_rows(package, root)
        out += [f"`{package}/`:", "", *rows, ""]
    return out[:-1]


def modules_without_docstring(root: Path = REPO) -> list[str]:
    return [name for package in PACKAGES for name in module_rows(package, root)[1]]


# -- the documents --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Block:
    """A generated part of a document: the text between two markers."""

    doc: str
    begin: str
    end: str
    lines: Callable[[], list[str]]

    def render(self) -> str:
        return "\n".join([self.begin, *self.lines(), self.end])

    def current(self, text: str) -> str:
        """The text between (and with) the markers; refuses a document without them."""
        start, end = text.find(self.begin), text.find(self.end)
        if start < 0 or end < start:
            raise SystemExit(f"{self.doc}: no markers ({self.begin} ... {self.end})")
        return text[start : end + len(self.end)]


def blocks(root: Path = REPO) -> list[Block]:
    return [
        Block(SETTINGS_DOC, SETTINGS_BEGIN, SETTINGS_END, settings_reference),
        Block(MODULES_DOC, MODULES_BEGIN, MODULES_END, lambda: module_lists(root)),
    ]


def differences(root: Path = REPO) -> list[str]:
    """A unified diff per generated block that is not the code's, and the modules without a docstring."""
    problems = [f"{name}: no module docstring (its row needs one)" for name in modules_without_docstring(root)]
    for block in blocks(root):
        old, new = block.current((root / block.doc).read_text(encoding="utf-8")), block.render()
        if old != new:
            diff = difflib.unified_diff(
                old.splitlines(), new.splitlines(), f"{block.doc} (now)", f"{block.doc} (code)", n=0
            )
            problems.append("\n".join(diff))
    return problems


def write(root: Path = REPO) -> list[str]:
    """Rewrite each generated block; returns the documents that changed."""
    changed = []
    for block in blocks(root):
        path = root / block.doc
        text = path.read_text(encoding="utf-8")
        new = text.replace(block.current(text), block.render())
        if new != text:
            path.write_text(new, encoding="utf-8")
            changed.append(block.doc)
    return changed


def main(argv: list[str] | None = None) -> int:
    return write_or_check(
        argv,
        description=(__doc__ or "").splitlines()[0],
        what="the generated blocks",
        source="the code",
        write=write,
        differences=differences,
        after_write=lambda: [f"{name}: no module docstring" for name in modules_without_docstring()],
        hint="run tools/reference_docs.py --write",
    )


if __name__ == "__main__":
    raise SystemExit(main())
