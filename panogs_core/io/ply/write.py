"""PLY files written: binary little-endian vertices and optional triangles."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from panogs_core.errors import InputError

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
