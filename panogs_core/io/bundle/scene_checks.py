"""The checks of a bundle's scene-wide files: ``geometry.ply`` (scanned, never held), ``vocabulary.json`` with its
embeddings, and ``gt/labels.npz`` (sizes checked before anything is decompressed).
"""

from __future__ import annotations

import logging
import lzma
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.bounded_json import JsonLimits, read_json_file
from panogs_core.errors import InputError
from panogs_core.io.bundle.file_checks import check_rel_path, npy_header
from panogs_core.io.bundle.format import GT_KEYS, BundleLimits
from panogs_core.io.bundle.problems import reason, short, strip_prefix
from panogs_core.io.npy_header import read_npy_header
from panogs_core.io.ply import scan_ply_positions
from panogs_core.types import ClassKind, Vocabulary

logger = logging.getLogger(__name__)


def check_geometry(root: Path, problems: list[str]) -> int | None:
    """Vertex count of ``geometry.ply``, None when absent or invalid.

    The mesh is scanned in chunks (count and finite positions), never held whole: an upload's 96 MB ASCII mesh
    took the API from 162 to 1,327 MB when it was read at once. The PLY budget bounds vertices, ASCII values and
    rows with list properties before any is parsed.
    """
    path = root / "geometry.ply"
    if path.is_symlink():
        problems.append("geometry.ply: is a symbolic link, not allowed")
        return None
    if not path.exists():
        return None
    try:
        count, finite = scan_ply_positions(path)
    except InputError as exc:
        problems.append(f"geometry.ply: {strip_prefix(str(exc), 'geometry.ply: ')}")
        return None
    if count == 0:
        problems.append("geometry.ply: 0 vertices, expected at least one")
        return None
    if not finite:
        problems.append("geometry.ply: vertex positions contain NaN or infinite values")
    return count


def check_vocabulary(
    root: Path, dim: int | None, limits: JsonLimits, max_classes: int, problems: list[str]
) -> Vocabulary | None:
    path = root / "vocabulary.json"
    if path.is_symlink():
        problems.append("vocabulary.json: is a symbolic link, not allowed")
        return None
    if not path.exists():
        return None
    try:
        doc = read_json_file(path, limits, name="vocabulary.json")
    except InputError as exc:  # not JSON, over a limit, or unreadable: the message names the file and the limit
        problems.append(str(exc))
        return None
    classes = doc.get("classes") if isinstance(doc, dict) else None
    if not isinstance(classes, list) or not classes:
        problems.append(f"vocabulary.json: classes {short(classes)}, expected a non-empty list")
        return None
    if len(classes) > max_classes:
        problems.append(f"vocabulary.json: {len(classes):,} classes, over the limit of {max_classes:,}")
        return None
    n_before = len(problems)
    names: list[str] = []
    seen_names: set[str] = set()  # a set, not the list: the check stays linear (131k classes never finished)
    kinds: list[ClassKind] = []
    for i, item in enumerate(classes):
        name = item.get("name") if isinstance(item, dict) else None
        kind = item.get("kind") if isinstance(item, dict) else None
        if not isinstance(name, str) or not name:
            problems.append(f"vocabulary.json: classes[{i}].name {name!r}, expected a non-empty string")
        elif name in seen_names:
            problems.append(f"vocabulary.json: classes[{i}].name {name!r} repeated, expected unique names")
        if kind not in ("thing", "stuff"):
            problems.append(f"vocabulary.json: classes[{i}].kind {kind!r}, expected 'thing' or 'stuff'")
        names.append(name if isinstance(name, str) else "")
        seen_names.add(names[-1])
        kinds.append(kind if kind in ("thing", "stuff") else "thing")
    embeddings = None
    # Without a valid features.dim (a problem already) the embeddings' declared width is unbounded: not read.
    if isinstance(doc, dict) and doc.get("embeddings") is not None and dim is not None:
        embeddings = load_embeddings(root, doc["embeddings"], len(names), dim, problems)
    if len(problems) > n_before:
        return None
    return Vocabulary(names=tuple(names), kinds=tuple(kinds), embeddings=embeddings)


def load_embeddings(
    root: Path, value: Any, num_classes: int, dim: int | None, problems: list[str]
) -> np.ndarray | None:  # (L, D) float32 unit rows
    rel = check_rel_path(root, value, "vocabulary.json: embeddings", (".npy",), problems)
    if rel is None:
        return None
    header = npy_header(root / rel, rel, problems)
    if header is None:
        return None
    shape, dtype = header.shape, header.dtype
    if dtype.kind != "f":
        problems.append(f"{rel}: dtype {dtype}, expected a float array")
        return None
    expected = (num_classes, dim if dim is not None else shape[-1] if shape else 0)
    if shape != expected:
        problems.append(f"{rel}: shape {shape}, expected {expected} (classes, features.dim)")
        return None
    emb = float32_rows(root / rel)
    norms = np.linalg.norm(emb, axis=1, keepdims=True)
    if not np.all(np.isfinite(emb)) or np.any(norms == 0):
        problems.append(f"{rel}: contains NaN, infinite or all-zero rows, expected finite non-zero embeddings")
        return None
    return emb / norms


def float32_rows(path: Path, rows_at_once: int = 256) -> np.ndarray:  # (L, D) float32
    """A 2-D float ``.npy`` as float32, cast a few rows at a time from a memory map (never a float64 copy whole)."""
    stored = np.load(path, mmap_mode="r", allow_pickle=False)
    out = np.empty(stored.shape, np.float32)
    for start in range(0, len(stored), rows_at_once):
        out[start : start + rows_at_once] = stored[start : start + rows_at_once]
    return out


def check_ground_truth(
    root: Path, vocabulary: Vocabulary | None, num_vertices: int | None, limits: BundleLimits, problems: list[str]
) -> bool:
    """True when ``gt/labels.npz`` is present and valid."""
    rel = "gt/labels.npz"
    path = root / rel
    if path.is_symlink() or (root / "gt").is_symlink():
        problems.append(f"{rel}: is or lies in a symbolic link, not allowed")
        return False
    if not path.exists():
        return False
    n_before = len(problems)
    arrays = load_npz(path, rel, limits.max_ground_truth_bytes, problems)
    if arrays is None:
        return False
    sem, ins, pts = arrays.get("semantic"), arrays.get("instance"), arrays.get("points")
    for key, arr in (("semantic", sem), ("instance", ins)):
        if arr is None:
            problems.append(f"{rel}: key {key!r} missing, expected (G,) int64")
        elif arr.ndim != 1 or not np.issubdtype(arr.dtype, np.integer):
            problems.append(f"{rel}: {key} {arr.dtype} {arr.shape}, expected (G,) integers")
    if len(problems) > n_before or sem is None or ins is None:
        return False
    g = len(sem)
    if len(ins) != g:
        problems.append(f"{rel}: instance has {len(ins)} values, expected {g} (as semantic)")
    if np.any(ins < -1):
        problems.append(f"{rel}: instance has values below -1, expected ids >= -1")
    if vocabulary is None:
        problems.append(f"{rel}: semantic labels need vocabulary.json, which is missing or invalid")
    elif g and (sem.min() < -1 or sem.max() >= len(vocabulary.names)):
        problems.append(f"{rel}: semantic in [{sem.min()}, {sem.max()}], expected [-1, {len(vocabulary.names)})")
    if pts is not None:
        if pts.shape != (g, 3) or pts.dtype.kind != "f" or not np.all(np.isfinite(pts)):
            problems.append(f"{rel}: points {pts.dtype} {pts.shape}, expected ({g}, 3) finite floats")
    elif num_vertices is None:
        problems.append(f"{rel}: no points and no valid geometry.ply, expected one of them")
    elif g != num_vertices:
        problems.append(f"{rel}: {g} labels, expected {num_vertices} (geometry.ply vertices)")
    return len(problems) == n_before


def load_npz(path: Path, rel: str, max_bytes: int, problems: list[str]) -> dict[str, np.ndarray] | None:
    """The arrays of ``gt/labels.npz`` named in :data:`GT_KEYS` (other members are not read).

    Every member's header is read first and its declared size compared, as an exact integer, with the member's
    uncompressed size in the zip (which the zip reader never reads past) and the sum with ``max_bytes``: an
    array that claims more than its member holds, or members that would expand past the limit (a zip bomb),
    are refused before anything is decompressed beyond the headers.
    """
    try:
        with zipfile.ZipFile(path) as zf:
            members = npz_members(zf, rel, problems)
            if members is None:
                return None
            total = sum(info.file_size for info in members.values())
            if total > max_bytes:
                problems.append(
                    f"{rel}: arrays expand to {total:,} bytes, over the ground-truth limit of {max_bytes:,} bytes"
                )
                return None
            arrays = {}
            for key, info in members.items():
                with zf.open(info) as fh:
                    arrays[key] = np.lib.format.read_array(fh, allow_pickle=False)
            return arrays
    except InputError as exc:
        problems.append(str(exc))
        return None
    except (
        zipfile.BadZipFile, ValueError, OSError, EOFError, RuntimeError, NotImplementedError, zlib.error,
        lzma.LZMAError,
    ) as exc:  # fmt: skip
        # RuntimeError: an encrypted member; NotImplementedError: a compression method zipfile lacks.
        problems.append(f"{rel}: not a valid .npz file ({reason(exc)})")
        return None


def npz_members(zf: zipfile.ZipFile, rel: str, problems: list[str]) -> dict[str, zipfile.ZipInfo] | None:
    """Key -> member of the wanted arrays, each with a valid header that matches its member's size."""
    members: dict[str, zipfile.ZipInfo] = {}
    for info in zf.infolist():
        key = info.filename.removesuffix(".npy")
        if key not in GT_KEYS:
            continue
        if key in members:
            problems.append(f"{rel}: member {info.filename!r} appears twice, expected one array per key")
            return None
        with zf.open(info) as fh:
            header = read_npy_header(fh, f"{rel}: {info.filename}")
        problem = header.size_problem(info.file_size - header.offset)
        if problem is not None:
            problems.append(f"{rel}: {info.filename}: {problem}")
            return None
        members[key] = info
    return members
