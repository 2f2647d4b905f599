"""PLY files: write binary little-endian vertices (+ optional triangles), read the vertices of any PLY.

The reader understands the three encodings of the format (``ascii``, ``binary_little_endian``,
``binary_big_endian``), skips elements it is not asked for (faces with list properties included) and raises
:class:`InputError` naming the file for anything malformed. Only the ``vertex`` element is ever decoded: its
properties come back as 1-D arrays in file order, with the dtype of the file (native byte order).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from panogs_core.errors import InputError

# PLY scalar type names (both spellings of the spec) -> numpy dtype code (without byte order).
_PLY_TYPES: dict[str, str] = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}  # fmt: skip

# numpy dtype -> PLY name used when writing. int64 is narrowed to int (checked), nothing else is converted.
_WRITE_TYPES: dict[str, str] = {
    "int8": "char",
    "uint8": "uchar",
    "int16": "short",
    "uint16": "ushort",
    "int32": "int",
    "uint32": "uint",
    "float32": "float",
    "float64": "double",
}

# A header longer than this is not a PLY header (guards against reading a whole binary file as header lines).
MAX_HEADER_LINES = 10_000
MAX_HEADER_BYTES = 1024**2  # also bounds one line: a header of comments from any real writer is a few KB
MAX_COUNT_DIGITS = 19  # an element count fits in int64; more digits than that is refused before int() sees it
_SMALL_READ = 65_536  # reads up to this size are not checked against the file size first


@dataclass(frozen=True)
class _Property:
    name: str
    dtype: str  # numpy code, e.g. "f4"; for a list property: the item type
    count_dtype: str | None = None  # list properties only: the type of the length prefix


@dataclass(frozen=True)
class _Element:
    name: str
    count: int
    properties: tuple[_Property, ...]

    @property
    def has_lists(self) -> bool:
        return any(p.count_dtype is not None for p in self.properties)


@dataclass(frozen=True)
class _Header:
    encoding: str  # "ascii" | "binary_little_endian" | "binary_big_endian"
    elements: tuple[_Element, ...]


def write_ply(
    path: str | Path,
    fields: dict[str, np.ndarray],  # name -> (N,) any of the supported dtypes
    faces: np.ndarray | None = None,  # (F, 3) int triangle vertex indices
) -> Path:
    """Write a binary little-endian PLY with one vertex property per array (and optional triangles).

    Args:
        path: Output file.
        fields: Vertex properties in order, e.g. ``{"x": ..., "y": ..., "z": ..., "red": ...}``; every array
            is ``(N,)``. The dtype is kept (float32 -> float, uint8 -> uchar, int32 -> int, float64 -> double,
            int16 -> short, uint16 -> ushort, int8 -> char, uint32 -> uint); int64 is written as int after a
            range check.
        faces: Triangles ``(F, 3)`` of vertex indices in ``[0, N)``, written as
            ``list uchar int vertex_indices``.

    Returns:
        The path written.

    Raises:
        InputError: if an array is not 1-D, the lengths differ, a dtype is unsupported, int64 values do not
            fit in int32, or faces are not ``(F, 3)`` indices in range.
    """
    path = Path(path)
    columns = _write_columns(fields)
    n = len(next(iter(columns.values()))) if columns else 0
    record = np.zeros(n, dtype=[(name, "<" + col.dtype.str[1:]) for name, col in columns.items()])
    for name, col in columns.items():
        record[name] = col
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property {_WRITE_TYPES[col.dtype.name]} {name}" for name, col in columns.items()]
    face_record = None
    if faces is not None:
        face_record = _face_record(faces, n)
        header += [f"element face {len(face_record)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(record.tobytes())
        if face_record is not None:
            fh.write(face_record.tobytes())
    return path


def _write_columns(fields: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Check the vertex arrays and narrow int64 to int32; returns the arrays to write, in order."""
    columns: dict[str, np.ndarray] = {}
    length: int | None = None
    for name, value in fields.items():
        arr = np.asarray(value)
        if arr.ndim != 1:
            raise InputError(f"write_ply: field {name!r} must be 1-D, got shape {arr.shape}")
        if length is not None and len(arr) != length:
            raise InputError(f"write_ply: field {name!r} has {len(arr)} values, expected {length}")
        length = len(arr)
        if not name or any(c.isspace() for c in name):
            raise InputError(f"write_ply: field name {name!r} must be non-empty without spaces")
        if arr.dtype == np.int64:
            if arr.size and (arr.min() < np.iinfo(np.int32).min or arr.max() > np.iinfo(np.int32).max):
                raise InputError(f"write_ply: field {name!r} (int64) has values outside the int32 range")
            arr = arr.astype(np.int32)
        if arr.dtype.name not in _WRITE_TYPES:
            raise InputError(f"write_ply: field {name!r} has unsupported dtype {arr.dtype}")
        columns[name] = arr
    return columns


def _face_record(faces: np.ndarray, num_vertices: int) -> np.ndarray:  # (F,) structured
    tri = np.asarray(faces)
    if tri.ndim != 2 or tri.shape[1] != 3 or not np.issubdtype(tri.dtype, np.integer):
        raise InputError(f"write_ply: faces must be (F, 3) integers, got {tri.dtype} {tri.shape}")
    if tri.size and (tri.min() < 0 or tri.max() >= num_vertices):
        raise InputError(f"write_ply: face indices must lie in [0, {num_vertices})")
    record = np.zeros(len(tri), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    record["n"] = 3
    record["v"] = tri
    return record


def read_ply_vertices(path: str | Path) -> dict[str, np.ndarray]:  # name -> (N,)
    """Read the vertex properties of a PLY file (ascii or binary, either byte order).

    Args:
        path: The PLY file.

    Returns:
        Property name -> ``(N,)`` array, in file order, with the file's dtype in native byte order.

    Raises:
        InputError: naming the file, if it is not a PLY, its header is malformed, it has no vertex element, or
            its data is truncated or does not parse.
    """
    path = Path(path)
    try:
        with path.open("rb") as fh:
            header = _read_header(fh, path)
            if header.encoding == "ascii":
                return _read_ascii(fh, header, path)
            return _read_binary(fh, header, path)
    except OSError as exc:
        raise InputError(f"{path.name}: cannot read PLY ({exc.strerror or exc})") from exc


def _read_header(fh: BinaryIO, path: Path) -> _Header:
    """Parse the header up to ``end_header``, leaving ``fh`` at the first data byte.

    Every number in it is bounded before it is used: the header's length (:data:`MAX_HEADER_LINES`,
    :data:`MAX_HEADER_BYTES`), each element count's digits, and the data the counts declare against the bytes
    the file holds after the header. Messages name the file and the header line.
    """
    if fh.readline(MAX_HEADER_BYTES).strip() != b"ply":
        raise InputError(f"{path.name}: not a PLY file (first line is not 'ply')")
    encoding = ""
    elements: list[tuple[str, int, list[_Property]]] = []
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
                raise InputError(f"{where}: PLY property {_short(prop.name)!r} repeated in element {elements[-1][0]!r}")
            elements[-1][2].append(prop)
        else:
            raise InputError(f"{where}: unknown PLY header keyword {_short(words[0])!r}")
    else:
        raise InputError(f"{path.name}: PLY header has no end_header within {MAX_HEADER_LINES:,} lines")
    if not encoding:
        raise InputError(f"{path.name}: PLY header has no format line")
    parsed = tuple(_Element(name, count, tuple(props)) for name, count, props in elements)
    if not any(e.name == "vertex" for e in parsed):
        raise InputError(f"{path.name}: PLY has no vertex element")
    _check_declared_size(parsed, encoding, os.fstat(fh.fileno()).st_size - fh.tell(), path)
    return _Header(encoding, parsed)


def _parse_format(words: list[str], where: str) -> str:
    if len(words) != 3 or words[1] not in ("ascii", "binary_little_endian", "binary_big_endian") or words[2] != "1.0":
        raise InputError(
            f"{where}: unsupported PLY format line {_short(' '.join(words))!r}, expected e.g. 'format "
            "binary_little_endian 1.0'"
        )
    return words[1]


def _parse_element(words: list[str], seen: list[str], where: str) -> tuple[str, int, list[_Property]]:
    if len(words) != 3 or not words[2].isdigit():
        raise InputError(
            f"{where}: malformed PLY element line {_short(' '.join(words))!r}, expected 'element NAME COUNT'"
        )
    if len(words[2]) > MAX_COUNT_DIGITS:
        raise InputError(
            f"{where}: PLY element {_short(words[1])!r} count of {len(words[2]):,} digits, expected at most "
            f"{MAX_COUNT_DIGITS} (and no more rows than the file holds)"
        )
    if words[1] in seen:
        raise InputError(f"{where}: PLY element {_short(words[1])!r} repeated, expected each element once")
    return words[1], int(words[2]), []


def _check_declared_size(elements: tuple[_Element, ...], encoding: str, available: int, path: Path) -> None:
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


def _parse_property(words: list[str], where: str) -> _Property:
    if len(words) == 3 and words[1] in _PLY_TYPES:
        return _Property(words[2], _PLY_TYPES[words[1]])
    if len(words) == 5 and words[1] == "list" and words[2] in _PLY_TYPES and words[3] in _PLY_TYPES:
        if np.dtype(_PLY_TYPES[words[2]]).kind not in "iu":  # a list length of float type has no meaning
            raise InputError(f"{where}: PLY list length type {words[2]!r}, expected an integer type")
        return _Property(words[4], _PLY_TYPES[words[3]], count_dtype=_PLY_TYPES[words[2]])
    raise InputError(f"{where}: malformed PLY property line {_short(' '.join(words))!r}")


def _short(text: str) -> str:
    return text if len(text) <= 80 else text[:77] + "..."


def _read_binary(fh: BinaryIO, header: _Header, path: Path) -> dict[str, np.ndarray]:
    order = "<" if header.encoding == "binary_little_endian" else ">"
    for element in header.elements:
        if element.name == "vertex":
            if element.has_lists:
                rows = [_read_binary_row(fh, element, order, path) for _ in range(element.count)]
                return _columns_from_rows(element, rows)
            dtype = np.dtype([(p.name, order + p.dtype) for p in element.properties])
            _require_bytes(fh, dtype.itemsize * element.count, path, element.name)
            record = np.frombuffer(fh.read(dtype.itemsize * element.count), dtype=dtype)
            return {p.name: record[p.name].astype(p.dtype) for p in element.properties}
        _skip_binary_element(fh, element, order, path)
    raise InputError(f"{path.name}: PLY has no vertex element")  # unreachable: the header checked it


def _skip_binary_element(fh: BinaryIO, element: _Element, order: str, path: Path) -> None:
    """Move past an element that is not wanted (row by row when it has list properties)."""
    if element.has_lists:
        for _ in range(element.count):
            _read_binary_row(fh, element, order, path)
        return
    size = sum(np.dtype(p.dtype).itemsize for p in element.properties) * element.count
    _require_bytes(fh, size, path, element.name)
    fh.seek(size, os.SEEK_CUR)


def _require_bytes(fh: BinaryIO, size: int, path: Path, element: str) -> None:
    """Refuse before reading: a header may declare far more data than the file holds (or memory allows)."""
    left = os.fstat(fh.fileno()).st_size - fh.tell()
    if size > left:
        raise InputError(f"{path.name}: PLY element {element!r} truncated ({left} of {size} bytes)")


def _read_binary_row(fh: BinaryIO, element: _Element, order: str, path: Path) -> list[float | list[float]]:
    row: list[float | list[float]] = []
    for prop in element.properties:
        if prop.count_dtype is None:
            row.append(_unpack(fh, order, prop.dtype, 1, path, element.name)[0])
            continue
        n = int(_unpack(fh, order, prop.count_dtype, 1, path, element.name)[0])
        if n < 0:
            raise InputError(f"{path.name}: PLY element {element.name!r} has a negative list length")
        if n * np.dtype(prop.dtype).itemsize > _SMALL_READ:  # a large read allocates its size before it reads
            _require_bytes(fh, n * np.dtype(prop.dtype).itemsize, path, element.name)
        row.append(list(_unpack(fh, order, prop.dtype, n, path, element.name)))
    return row


def _unpack(fh: BinaryIO, order: str, code: str, n: int, path: Path, element: str) -> tuple[float, ...]:
    size = np.dtype(code).itemsize * n
    data = fh.read(size)
    if len(data) != size:
        raise InputError(f"{path.name}: PLY element {element!r} truncated")
    return tuple(np.frombuffer(data, dtype=order + code).tolist())


def _columns_from_rows(element: _Element, rows: list[list[float | list[float]]]) -> dict[str, np.ndarray]:
    """Scalar properties of row-parsed vertices; list properties on vertices are dropped."""
    out: dict[str, np.ndarray] = {}
    for i, prop in enumerate(element.properties):
        if prop.count_dtype is None:
            out[prop.name] = np.array([row[i] for row in rows], dtype=prop.dtype).reshape(-1)
    return out


def _read_ascii(fh: BinaryIO, header: _Header, path: Path) -> dict[str, np.ndarray]:
    """Parse the body as a stream of tokens (one element per line by the spec, but lines carry no meaning)."""
    try:
        tokens = fh.read().decode("ascii").split()
    except UnicodeDecodeError as exc:
        raise InputError(f"{path.name}: ASCII PLY body is not ASCII") from exc
    pos = 0
    for element in header.elements:
        if element.name == "vertex" and not element.has_lists:
            n_props = len(element.properties)
            end = pos + n_props * element.count
            if end > len(tokens):
                raise InputError(f"{path.name}: PLY vertex data truncated")
            try:
                table = np.array(tokens[pos:end], dtype=np.float64).reshape(element.count, n_props)
            except ValueError as exc:
                raise InputError(f"{path.name}: PLY vertex data is not numeric") from exc
            return {p.name: _cast_ascii(table[:, i], p, path) for i, p in enumerate(element.properties)}
        rows: list[list[float | list[float]]] = []
        for _ in range(element.count):
            row, pos = _ascii_row(tokens, pos, element, path)
            rows.append(row)
        if element.name == "vertex":
            return _columns_from_rows(element, rows)
    raise InputError(f"{path.name}: PLY has no vertex element")  # unreachable: the header checked it


def _ascii_row(tokens: list[str], pos: int, element: _Element, path: Path) -> tuple[list[float | list[float]], int]:
    row: list[float | list[float]] = []
    try:
        for prop in element.properties:
            if prop.count_dtype is None:
                row.append(float(tokens[pos]))
                pos += 1
                continue
            n = int(tokens[pos])
            if n < 0 or pos + 1 + n > len(tokens):
                raise InputError(f"{path.name}: PLY element {element.name!r} has a bad list length")
            row.append([float(t) for t in tokens[pos + 1 : pos + 1 + n]])
            pos += 1 + n
    except IndexError as exc:
        raise InputError(f"{path.name}: PLY element {element.name!r} truncated") from exc
    except ValueError as exc:
        raise InputError(f"{path.name}: PLY element {element.name!r} is not numeric") from exc
    return row, pos


def _cast_ascii(column: np.ndarray, prop: _Property, path: Path) -> np.ndarray:
    if np.dtype(prop.dtype).kind in "iu":
        if not np.all(np.isfinite(column)) or np.any(column != np.round(column)):
            raise InputError(f"{path.name}: PLY property {_short(prop.name)!r} must hold integers")
        info = np.iinfo(prop.dtype)
        if column.size and (column.min() < info.min or column.max() > info.max):  # a cast would wrap silently
            raise InputError(
                f"{path.name}: PLY property {_short(prop.name)!r} has values in [{column.min():g}, "
                f"{column.max():g}], outside its type's range [{info.min}, {info.max}]"
            )
    return column.astype(prop.dtype)


def vertex_count(path: str | Path) -> int:
    """Number of vertices declared by a PLY header (reads the header only).

    Raises:
        InputError: if the header is malformed or has no vertex element.
    """
    path = Path(path)
    try:
        with path.open("rb") as fh:
            header = _read_header(fh, path)
    except OSError as exc:
        raise InputError(f"{path.name}: cannot read PLY ({exc.strerror or exc})") from exc
    return next(e.count for e in header.elements if e.name == "vertex")
