"""The vertices of a PLY file read in chunks within a budget (binary of either byte order, or ASCII)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.ply.header import Element, Header, Property, read_header, short

_SMALL_READ = 65_536  # reads up to this size are not checked against the file size first
_CHUNK_ROWS = 1 << 18  # vertices decoded at once: 262,144 rows of x, y, z, colour and normal are about 10 MB
# An ASCII body is read 1 MiB at a time and parsed 65,536 rows at a time: its tokens are Python objects of
# about 40 bytes each, so these keep an ASCII chunk near 20 MB.
_ASCII_READ = 1 << 20
_ASCII_CHUNK_ROWS = 1 << 16


@dataclass(frozen=True)
class PlyBudget:
    """The most work one PLY file may ask for; a file over it is refused by name before that work is done.

    Attributes:
        max_vertices: Vertices in the file. A ScanNet mesh has 0.1-0.5 M, a Replica room 1-2 M; a building of
            a few hundred rooms stays under the default.
        max_ascii_values: Numbers of an ASCII body parsed up to and with the vertices (about 4 s at the default:
            a larger scene is written in binary by every mesh tool).
        max_list_rows: Rows parsed one at a time because their element has list properties (faces before the
            vertices, lists on the vertices): 5 M such rows took 77 s; writers put the vertices first.
    """

    max_vertices: int = 100_000_000
    max_ascii_values: int = 40_000_000
    max_list_rows: int = 200_000


def read_ply_vertices(path: str | Path, budget: PlyBudget | None = None) -> dict[str, np.ndarray]:  # name -> (N,)
    """Read the vertex properties of a PLY file (ascii or binary, either byte order).

    Args:
        path: The PLY file.
        budget: What the file may cost (default: :class:`PlyBudget()`).

    Returns:
        Property name -> ``(N,)`` array, in file order, with the file's dtype in native byte order (list
        properties of vertices are dropped).

    Raises:
        InputError: naming the file, if it is not a PLY, its header is malformed, it has no vertex element, its
            data is truncated or does not parse, or it breaks the budget.
    """
    chunks: list[dict[str, np.ndarray]] = []
    for chunk in _vertex_chunks(Path(path), budget or PlyBudget()):
        chunks.append({name: column.copy() for name, column in chunk.items()})  # not views of a read buffer
    return {name: np.concatenate([c[name] for c in chunks]) for name in chunks[0]}


def scan_ply_positions(path: str | Path, budget: PlyBudget | None = None) -> tuple[int, bool]:
    """The vertex count of a PLY file and whether every x, y, z is finite, holding one chunk at a time.

    The checks of :func:`read_ply_vertices`, for a validator that must not hold a large mesh in memory.

    Raises:
        InputError: as :func:`read_ply_vertices`, and when x, y or z is missing.
    """
    path = Path(path)
    count, finite = 0, True
    for chunk in _vertex_chunks(path, budget or PlyBudget()):
        if not {"x", "y", "z"} <= chunk.keys():
            raise InputError(f"{path.name}: vertices need x, y, z properties, found {sorted(chunk)}")
        count += len(chunk["x"])
        finite = finite and all(bool(np.isfinite(chunk[k]).all()) for k in "xyz")
    return count, finite


def _vertex_chunks(path: Path, budget: PlyBudget) -> Iterator[dict[str, np.ndarray]]:
    """The vertex properties in chunks of rows (at least one chunk, empty when there are no vertices)."""
    try:
        with path.open("rb") as fh:
            header = read_header(fh, path)
            _check_budget(header, budget, path)
            if header.encoding == "ascii":
                yield from _ascii_vertex_chunks(_AsciiTokens(fh, path), header, path)
            else:
                yield from _binary_vertex_chunks(fh, header, path)
    except OSError as exc:
        raise InputError(f"{path.name}: cannot read PLY ({exc.strerror or exc})") from exc


def _check_budget(header: Header, budget: PlyBudget, path: Path) -> None:
    """Refuse a file whose header asks for more work than ``budget`` allows, before any row is read."""
    values = list_rows = 0
    for element in header.elements:
        if element.name == "vertex" and element.count > budget.max_vertices:
            raise InputError(
                f"{path.name}: {element.count:,} vertices, over the limit of {budget.max_vertices:,} "
                "(subsample the mesh)"
            )
        if element.has_lists:
            list_rows += element.count
        else:
            values += element.count * len(element.properties)
        if list_rows > budget.max_list_rows:
            raise InputError(
                f"{path.name}: element {element.name!r} has list properties and {element.count:,} rows before the "
                f"vertices are read; at most {budget.max_list_rows:,} such rows are parsed (write the vertex "
                "element first, or drop the lists)"
            )
        if header.encoding == "ascii" and values > budget.max_ascii_values:
            raise InputError(
                f"{path.name}: an ASCII body of {values:,} values up to the vertices, over the limit of "
                f"{budget.max_ascii_values:,} (write the file as binary_little_endian)"
            )
        if element.name == "vertex":
            return


def _binary_vertex_chunks(fh: BinaryIO, header: Header, path: Path) -> Iterator[dict[str, np.ndarray]]:
    order = "<" if header.encoding == "binary_little_endian" else ">"
    for element in header.elements:
        if element.name != "vertex":
            _skip_binary_element(fh, element, order, path)
            continue
        if element.has_lists:
            rows = [_read_binary_row(fh, element, order, path) for _ in range(element.count)]
            yield _columns_from_rows(element, rows)
            return
        dtype = np.dtype([(p.name, order + p.dtype) for p in element.properties])
        _require_bytes(fh, dtype.itemsize * element.count, path, element.name)
        for start in range(0, max(element.count, 1), _CHUNK_ROWS):
            chunk_rows = min(_CHUNK_ROWS, element.count - start)
            record = np.frombuffer(fh.read(dtype.itemsize * chunk_rows), dtype=dtype)
            yield {p.name: record[p.name].astype(p.dtype) for p in element.properties}
        return
    raise InputError(f"{path.name}: PLY has no vertex element")  # unreachable: the header checked it


def _skip_binary_element(fh: BinaryIO, element: Element, order: str, path: Path) -> None:
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


def _read_binary_row(fh: BinaryIO, element: Element, order: str, path: Path) -> list[float | list[float]]:
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


def _columns_from_rows(element: Element, rows: list[list[float | list[float]]]) -> dict[str, np.ndarray]:
    """Scalar properties of row-parsed vertices; list properties on vertices are dropped."""
    out: dict[str, np.ndarray] = {}
    for i, prop in enumerate(element.properties):
        if prop.count_dtype is None:
            out[prop.name] = np.array([row[i] for row in rows], dtype=prop.dtype).reshape(-1)
    return out


class _AsciiTokens:
    """The whitespace-separated tokens of an ASCII PLY body, read in chunks (never the whole file at once)."""

    def __init__(self, fh: BinaryIO, path: Path) -> None:
        self._fh = fh
        self._path = path
        self._tokens: list[bytes] = []
        self._pos = 0
        self._tail = b""  # a token cut by the end of the last read

    def take(self, n: int) -> list[bytes]:
        """The next ``n`` tokens; fewer only at the end of the file."""
        while len(self._tokens) - self._pos < n and self._fill():
            pass
        out = self._tokens[self._pos : self._pos + n]
        self._pos += len(out)
        return out

    def _fill(self) -> bool:
        """Read the next chunk into the tokens; False at the end of the file."""
        data = self._fh.read(_ASCII_READ)
        if not data and not self._tail:
            return False
        data = self._tail + data
        cut = len(data) if len(data) == len(self._tail) else len(data.rstrip(_NOT_SPACE))
        whole, self._tail = data[:cut], data[cut:]
        if len(self._tail) > _ASCII_READ:
            raise InputError(f"{self._path.name}: ASCII PLY body has a token longer than {_ASCII_READ:,} bytes")
        self._tokens = self._tokens[self._pos :] + whole.split()
        self._pos = 0
        return True


# Every byte but ASCII whitespace: rstrip(_NOT_SPACE) cuts a chunk after its last whitespace byte.
_NOT_SPACE = bytes(b for b in range(256) if b not in b" \t\r\n\x0b\x0c")


def _ascii_vertex_chunks(tokens: _AsciiTokens, header: Header, path: Path) -> Iterator[dict[str, np.ndarray]]:
    """Parse the body as a stream of tokens (one element per line by the spec, but lines carry no meaning)."""
    for element in header.elements:
        if element.has_lists:
            rows = [_ascii_row(tokens, element, path) for _ in range(element.count)]
            if element.name == "vertex":
                yield _columns_from_rows(element, rows)
                return
            continue
        n_props = len(element.properties)
        for start in range(0, max(element.count, 1), _ASCII_CHUNK_ROWS):
            rows_now = min(_ASCII_CHUNK_ROWS, element.count - start)
            table = _ascii_table(tokens.take(rows_now * n_props), rows_now, n_props, element, path)
            if element.name == "vertex":  # the elements before it are parsed (they must be numbers) and dropped
                yield {p.name: _cast_ascii(table[:, i], p, path) for i, p in enumerate(element.properties)}
        if element.name == "vertex":
            return
    raise InputError(f"{path.name}: PLY has no vertex element")  # unreachable: the header checked it


def _ascii_table(
    values: list[bytes], rows: int, n_props: int, element: Element, path: Path
) -> np.ndarray:  # (rows, n_props) float64
    if len(values) != rows * n_props:
        raise InputError(f"{path.name}: PLY {element.name} data truncated")
    try:
        return np.array(values, dtype=np.float64).reshape(rows, n_props)
    except ValueError as exc:
        raise InputError(f"{path.name}: PLY {element.name} data is not numeric") from exc


def _ascii_row(tokens: _AsciiTokens, element: Element, path: Path) -> list[float | list[float]]:
    row: list[float | list[float]] = []
    for prop in element.properties:
        first = tokens.take(1)
        if not first:
            raise InputError(f"{path.name}: PLY element {element.name!r} truncated")
        try:
            if prop.count_dtype is None:
                row.append(float(first[0]))
                continue
            n = int(first[0])
            values = tokens.take(n) if n >= 0 else []
            if n < 0 or len(values) != n:
                raise InputError(f"{path.name}: PLY element {element.name!r} has a bad list length")
            row.append([float(t) for t in values])
        except InputError:
            raise
        except ValueError as exc:
            raise InputError(f"{path.name}: PLY element {element.name!r} is not numeric") from exc
    return row


def _cast_ascii(column: np.ndarray, prop: Property, path: Path) -> np.ndarray:
    if np.dtype(prop.dtype).kind in "iu":
        if not np.all(np.isfinite(column)) or np.any(column != np.round(column)):
            raise InputError(f"{path.name}: PLY property {short(prop.name)!r} must hold integers")
        info = np.iinfo(prop.dtype)
        if column.size and (column.min() < info.min or column.max() > info.max):  # a cast would wrap silently
            raise InputError(
                f"{path.name}: PLY property {short(prop.name)!r} has values in [{column.min():g}, "
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
            header = read_header(fh, path)
    except OSError as exc:
        raise InputError(f"{path.name}: cannot read PLY ({exc.strerror or exc})") from exc
    return next(e.count for e in header.elements if e.name == "vertex")
