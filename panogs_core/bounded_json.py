"""One bounded JSON reader for every JSON document a user sends: request bodies and the JSON files of a bundle.

Python's ``json`` has no limits of its own: a document nested 100,000 levels deep raises ``RecursionError`` from
the C scanner, an integer of 5,000 digits raises ``ValueError`` (Python 3.11's ``int_max_str_digits``), and a
few hundred levels pass the parser only to break pydantic's serializer later; each surfaced as a 500.
:func:`loads` checks three limits, each before the work it protects:

1. size, in bytes, before anything is decoded;
2. depth, the deepest nesting of arrays and objects, on the text outside strings and before ``json.loads``
   (strings are cut out by one regular expression and the brackets left are summed, a few passes at C speed
   instead of a Python loop per character);
3. integer digits, in the ``parse_int`` hook, before ``int()`` sees the literal.

A broken limit raises :class:`JsonLimitError` naming the document, the limit and, where it can be found, the
field path (``frames[3].pose``) with line and column; a document that is not JSON raises :class:`JsonSyntaxError`.
``RecursionError`` never escapes.

This module imports only the standard library (and the core's errors), so that the API imports it without numpy,
OpenCV or torch; it sits on the core's bottom floor (docs/architecture.md, "Layers"), below the language package
that reads user vocabularies with it and the ``io`` package that reads bundles with it.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from panogs_core.errors import InputError

__all__ = ["JsonLimitError", "JsonLimits", "JsonSyntaxError", "loads", "nesting_depth", "read_json_file"]

LimitName = Literal["bytes", "depth", "int_digits"]

# A JSON string: quote, runs of plain characters and escapes, quote (the "unrolled loop" form: no backtracking).
_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"', re.DOTALL)
_NOT_BRACKETS = bytes(c for c in range(256) if c not in b"[]{}")
_PARENS = bytes.maketrans(b"[]{}", b"()()")
# Tokens for locating a problem (error path only): strings and structure.
_TOKEN = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"|[\[\]{},:]', re.DOTALL)
_BRACKET = re.compile(r"[\[\]{}]")
_MAX_WALK_TOKENS = 200_000
_PATH_PARTS_SHOWN = 6  # a path 64 levels deep is shown by its first parts and "..."


@dataclass(frozen=True)
class JsonLimits:
    """The limits of one JSON document.

    Attributes:
        max_depth: Most levels of nested arrays and objects (``{"a": [1]}`` is 2).
        max_bytes: Most bytes of the document's text.
        max_int_digits: Most digits of an integer literal (20 holds every 64-bit integer).
    """

    max_depth: int = 64
    max_bytes: int = 64 * 1024**2
    max_int_digits: int = 20


class JsonSyntaxError(InputError):
    """The document is not JSON (or not text); the message names the document and the position."""


class JsonLimitError(InputError):
    """The document breaks a limit of :class:`JsonLimits`.

    Attributes:
        source: The document, as named in the message (a file relative to its bundle, or ``request body``).
        limit: Which limit: ``bytes``, ``depth`` or ``int_digits``.
        value: The limit's value.
        path: Field path where the limit was passed (``frames[3].pose``), or None when it is the whole document.
    """

    def __init__(self, source: str, limit: LimitName, value: int, detail: str, path: str | None = None) -> None:
        super().__init__(f"{source}: {detail}")
        self.source = source
        self.limit = limit
        self.value = value
        self.path = path


def loads(data: str | bytes, limits: JsonLimits | None = None, *, source: str = "document") -> Any:
    """Parse a JSON document within ``limits``.

    Args:
        data: The text, or its bytes (UTF-8, -16 or -32, told apart as ``json.loads`` does).
        limits: The limits (default: :class:`JsonLimits()`).
        source: What the messages call the document, e.g. ``scene.json`` or ``request body``.

    Returns:
        The parsed value.

    Raises:
        JsonLimitError: a limit is broken.
        JsonSyntaxError: not JSON, or bytes that are not text.
    """
    limits = limits or JsonLimits()
    size = len(data.encode("utf-8", "surrogatepass")) if isinstance(data, str) else len(data)
    if size > limits.max_bytes:
        raise JsonLimitError(
            source, "bytes", limits.max_bytes, f"{size:,} bytes, over the JSON size limit of {limits.max_bytes:,} bytes"
        )
    if isinstance(data, bytes):
        try:
            text = data.decode(json.detect_encoding(data), "surrogatepass")
        except UnicodeDecodeError as exc:
            raise JsonSyntaxError(
                f"{source}: not valid JSON (not UTF-8 text: {exc.reason} at byte {exc.start})"
            ) from exc
    else:
        text = data
    if nesting_depth(text, stop_above=limits.max_depth) > limits.max_depth:
        raise _depth_error(text, limits, source)

    def checked_int(literal: str) -> int:
        if len(literal.lstrip("-")) > limits.max_int_digits:
            raise _int_error(text, limits, source)
        return int(literal)

    try:
        return json.loads(text, parse_int=checked_int)
    except json.JSONDecodeError as exc:
        raise JsonSyntaxError(f"{source}: not valid JSON ({exc.msg} at line {exc.lineno}, column {exc.colno})") from exc
    except RecursionError:  # unreachable after the depth check; kept so that no input can make one escape
        raise _depth_error(text, limits, source) from None


def read_json_file(path: str | Path, limits: JsonLimits | None = None, *, name: str | None = None) -> Any:
    """Read and parse a JSON file within ``limits``; its size is checked before it is read.

    Args:
        path: The file.
        limits: The limits (default: :class:`JsonLimits()`).
        name: What the messages call the file (default: its name); inside a bundle, its bundle-relative path.

    Raises:
        JsonLimitError: a limit is broken.
        JsonSyntaxError: not JSON.
        InputError: the file cannot be read.
    """
    path = Path(path)
    name = name or path.name
    limits = limits or JsonLimits()
    try:
        with path.open("rb") as fh:
            # Read one byte past the limit: enough to know it is passed, without reading a huge file whole.
            data = fh.read(limits.max_bytes + 1)
            size = fh.seek(0, 2) if len(data) > limits.max_bytes else len(data)
    except OSError as exc:
        raise InputError(f"{name}: cannot be read ({exc.strerror or type(exc).__name__})") from exc
    if size > limits.max_bytes:
        raise JsonLimitError(
            name, "bytes", limits.max_bytes, f"{size:,} bytes, over the JSON size limit of {limits.max_bytes:,} bytes"
        )
    return loads(data, limits, source=name)


def nesting_depth(text: str, *, stop_above: int | None = None) -> int:
    """Deepest nesting of arrays and objects in ``text``, counting brackets outside strings only.

    Strings are cut out, every bracket becomes ``(`` or ``)``, and each round deletes the innermost pairs
    ``()``; the rounds count the levels. ``bytes.replace`` does not look again at the pairs its own deletions
    make, so one round is one level, and every round runs at C speed. Exact for valid JSON; for text that is not,
    the unclosed brackets left over are added, so that it still bounds how deep ``json.loads`` recurses before it
    finds the error.

    Args:
        text: The document.
        stop_above: Stop counting (and return) once the depth passes this.
    """
    structure = _STRING.sub("", text).encode("utf-8", "surrogatepass").translate(_PARENS, _NOT_BRACKETS)
    depth = 0
    while b"()" in structure:
        structure = structure.replace(b"()", b"")
        depth += 1
        if stop_above is not None and depth > stop_above:
            return depth
    return depth + structure.count(b"(")


# -- messages (error path only) ------------------------------------------------------------------------------


def _depth_error(text: str, limits: JsonLimits, source: str) -> JsonLimitError:
    blank = _blank_strings(text)
    offset = _too_deep_offset(blank, limits.max_depth)
    path = _path_to(text, blank, offset) if offset is not None else None
    detail = f"nested deeper than the JSON depth limit of {limits.max_depth} levels{_at(text, offset, path)}"
    return JsonLimitError(source, "depth", limits.max_depth, detail, path)


def _int_error(text: str, limits: JsonLimits, source: str) -> JsonLimitError:
    blank = _blank_strings(text)
    match = re.search(rf"(?<![\d.eE+-])-?\d{{{limits.max_int_digits + 1},}}(?![\d.eE])", blank)
    offset = match.start() if match else None
    path = _path_to(text, blank, offset) if offset is not None else None
    digits = f"an integer of {len(match.group().lstrip('-')):,} digits" if match else "an integer"
    detail = f"{digits}{_at(text, offset, path)}, over the JSON integer limit of {limits.max_int_digits} digits"
    return JsonLimitError(source, "int_digits", limits.max_int_digits, detail, path)


def _blank_strings(text: str) -> str:
    """``text`` with the inside of every string blanked: offsets stay, and no bracket or digit in a string counts."""
    return _STRING.sub(lambda m: '"' + " " * (len(m.group()) - 2) + '"', text)


def _too_deep_offset(blank: str, max_depth: int) -> int | None:
    depth = 0
    for match in _BRACKET.finditer(blank):
        depth += 1 if match.group() in "[{" else -1
        if depth > max_depth:
            return match.start()
    return None


def _at(text: str, offset: int | None, path: str | None) -> str:
    if offset is None:
        return ""
    line = text.count("\n", 0, offset) + 1
    position = f"line {line}, column {offset - text.rfind(chr(10), 0, offset)}"
    return f" at {path} ({position})" if path else f" ({position})"


def _path_to(text: str, blank: str, offset: int) -> str | None:
    """The field path of the value at ``offset`` (``frames[3].pose``), or None when finding it costs too much.

    A Python walk over the tokens before ``offset``; a hostile prefix of a million tokens would take seconds, so
    past ``_MAX_WALK_TOKENS`` the message gives only the line and column.
    """
    prefix = blank[:offset]
    if sum(prefix.count(c) for c in "[]{},:") > _MAX_WALK_TOKENS:
        return None
    # One entry per open container: [is_array, index or key, expecting a key (objects)].
    stack: list[list[Any]] = []
    for match in _TOKEN.finditer(text, 0, offset):
        token = match.group()
        first = token[0]
        if first in "[{":
            stack.append([first == "[", 0 if first == "[" else None, first == "{"])
        elif first in "]}":
            if stack:
                stack.pop()
        elif first == "," and stack:
            if stack[-1][0]:
                stack[-1][1] += 1
            else:
                stack[-1][2] = True
        elif first == '"' and stack and not stack[-1][0] and stack[-1][2]:
            stack[-1][1] = _key(token)
            stack[-1][2] = False
    parts = [f"[{entry[1]}]" if entry[0] else f".{entry[1]}" for entry in stack if entry[0] or entry[1] is not None]
    shown = "".join(parts[:_PATH_PARTS_SHOWN]) + ("..." if len(parts) > _PATH_PARTS_SHOWN else "")
    return shown.removeprefix(".") or None


def _key(token: str) -> str:
    try:
        key = str(json.loads(token))
    except ValueError:
        key = token[1:-1]
    return key if len(key) <= 40 else key[:37] + "..."
