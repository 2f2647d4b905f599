"""A PLY header parsed and bounded: the format line, the elements and their properties, the declared sizes."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from panogs_core.errors import InputError

# PLY scalar type names (both spellings of the spec) -> numpy dtype code (without byte order).
PLY_TYPES: dict[str, str] = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}  # fmt: skip

# A header longer than this is not a PLY header (guards against reading a whole binary file as header lines).
MAX_HEADER_LINES = 10_000
MAX_HEADER_BYTES = 1024**2  # also bounds one line: a header of comments from any real writer is a few KB
MAX_COUNT_DIGITS = 19  # an element count fits in int64; more digits than that is refused before int() sees it


@dataclass(frozen=True)
class Property:
    name: str
    dtype: str  # numpy code, e.g. "f4"; for a list property: the item type
    count_dtype: str | None = None  # list properties only: the type of the length prefix


@dataclass(frozen=True)
class Element:
    name: str
    count: int
    properties: tuple[Property, ...]

    @property
    def has_lists(self) -> bool:
        return any(p.count_dtype is not None for p in self.properties)


@dataclass(frozen=True)
class Header:
    encoding: str  # "ascii" | "binary_little_endian" | "binary_big_endian"
    elements: tuple[Element, ...]


def read_header(fh: BinaryIO, path: Path) -> Header:
    """Parse the header up to ``end_header``, leaving ``fh`` at the first data byte.

    Every number in it is bounded before it is used: the header's length (:data:`MAX_HEADER_LINES`,
    :data:`MAX_HEADER_BYTES`), each element count's digits, and the data the counts declare against the bytes
    the file holds after the header. Messages name the file and the header line.
    """
    if fh.readline(MAX_HEADER_BYTES).strip() != b"ply":
        raise InputError(f"{path.name}: not a PLY file (first line is not 'ply')")
    encoding = ""
    elements: list[tuple[str, int, list[Property]]] = []
    used = fh.tell()
    for number in range(2, MAX_HEADER_LINES + 1):
        raw = fh.readline(MAX_HEADER_BYTES - used + 1)
        used += len(raw)
        if used > MAX_HEADER_BYTES:
            raise InputError(f"{path.name}: line {number}: PLY header longer than {MAX_HEADER_BYTES:,} bytes")
        if not raw:
            raise InputError(f"{path.name}: PLY header has no end_header")
        try:
            words = raw.decode("ascii").split()
        except UnicodeDecodeError as exc:
            raise InputError(f"{path.name}: line {number}: PLY header is not ASCII") from exc
        where = f"{path.name}: line {number}"
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            encoding = _parse_format(words, where)
        elif words[0] == "element":
            elements.append(_parse_element(words, [e[0] for e in elements], where))
        elif words[0] == "property":
            if not elements:
                raise InputError(f"{where}: PLY property before any element")
            prop = _parse_property(words, where)
            if any(p.name == prop.name for p in elements[-1][2]):
                raise InputError(f"{where}: PLY property {short(prop.name)!r} repeated in element {elements[-1][0]!r}")
            elements[-1][2].append(prop)
        else:
            raise InputError(f"{where}: unknown PLY header keyword {short(words[0])!r}")
    else:
        raise InputError(f"{path.name}: PLY header has no end_header within {MAX_HEADER_LINES:,} lines")
    if not encoding:
        raise InputError(f"{path.name}: PLY header has no format line")
    parsed = tuple(Element(name, count, tuple(props)) for name, count, props in elements)
    if not any(e.name == "vertex" for e in parsed):
        raise InputError(f"{path.name}: PLY has no vertex element")
    check_declared_size(parsed, encoding, os.fstat(fh.fileno()).st_size - fh.tell(), path)
    return Header(encoding, parsed)


def _parse_format(words: list[str], where: str) -> str:
    if len(words) != 3 or words[1] not in ("ascii", "binary_little_endian", "binary_big_endian") or words[2] != "1.0":
        raise InputError(
            f"{where}: unsupported PLY format line {short(' '.join(words))!r}, expected e.g. 'format "
            "binary_little_endian 1.0'"
        )
    return words[1]


def _parse_element(words: list[str], seen: list[str], where: str) -> tuple[str, int, list[Property]]:
    if len(words) != 3 or not words[2].isdigit():
        raise InputError(
            f"{where}: malformed PLY element line {short(' '.join(words))!r}, expected 'element NAME COUNT'"
        )
    if len(words[2]) > MAX_COUNT_DIGITS:
        raise InputError(
            f"{where}: PLY element {short(words[1])!r} count of {len(words[2]):,} digits, expected at most "
            f"{MAX_COUNT_DIGITS} (and no more rows than the file holds)"
        )
    if words[1] in seen:
        raise InputError(f"{where}: PLY element {short(words[1])!r} repeated, expected each element once")
    return words[1], int(words[2]), []


def check_declared_size(elements: tuple[Element, ...], encoding: str, available: int, path: Path) -> None:
    """Refuse counts that the data after the header cannot hold, before any row is read or allocated.

    A binary row takes at least its scalars' and list lengths' bytes; an ASCII row at least one character and a
    separator per property. An element with rows but no properties would take no bytes at all, so any count
    would fit: it is refused.
    """
    needed = 0
    for element in elements:
        if element.count and not element.properties:
            raise InputError(f"{path.name}: PLY element {element.name!r} has {element.count:,} rows but no properties")
        if encoding == "ascii":
            row = 2 * len(element.properties)
        else:
            row = sum(np.dtype(p.count_dtype or p.dtype).itemsize for p in element.properties)
        needed += row * element.count
        if needed > available + (1 if encoding == "ascii" else 0):  # the last ASCII value needs no separator
            raise InputError(
                f"{path.name}: PLY element {element.name!r} truncated or its count false: {element.count:,} rows "
                f"need at least {needed:,} bytes of data, the file holds {available:,} after its header"
            )


def _parse_property(words: list[str], where: str) -> Property:
    if len(words) == 3 and words[1] in PLY_TYPES:
        return Property(words[2], PLY_TYPES[words[1]])
    if len(words) == 5 and words[1] == "list" and words[2] in PLY_TYPES and words[3] in PLY_TYPES:
        if np.dtype(PLY_TYPES[words[2]]).kind not in "iu":  # a list length of float type has no meaning
            raise InputError(f"{where}: PLY list length type {words[2]!r}, expected an integer type")
        return Property(words[4], PLY_TYPES[words[3]], count_dtype=PLY_TYPES[words[2]])
    raise InputError(f"{where}: malformed PLY property line {short(' '.join(words))!r}")


def short(text: str) -> str:
    return text if len(text) <= 80 else text[:77] + "..."
