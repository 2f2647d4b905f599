"""A finished run folder as the viewer's binary scene: one JSON header and typed arrays, no JSON per point.

Layout (little-endian), read by ``web/src/scene.js``::

    bytes 0..3    magic b"PGSV"
    bytes 4..7    uint32 format version (1)
    bytes 8..11   uint32 header length H
    bytes 12..    H bytes of UTF-8 JSON, padded with spaces to a multiple of 4
    then          the arrays, each at the byte offset the header names (offsets count from the body start and
                  are multiples of 4, so the browser maps them as typed arrays without copying)

Arrays: ``position`` float32 (N, 3), ``color`` uint8 (N, 3) camera colour, ``semantic`` int16 (N,) class index or
-1, ``instance`` int32 (N,) instance id or -1, ``scale`` float32 (N,) the primitive's radius in metres: the
Gaussian's mean axis, at most its neighbour-spacing radius (``point_radii``).

The header carries the classes (name, kind, palette colour, primitive count), the instances of ``instances.json``
(with their colour), the bounds, the primitive count before decimation, and ``up``: the run's up direction from
``cameras.json`` (a unit vector in world coordinates; absent for a run without one, which the viewer takes as +z),
so that the first view is upright before anything else is fetched. Built from ``gaussians.ply`` (colour
and scale, read by the core's Gaussian PLY reader) and ``vocabulary.json``/``instances.json``, as
``panogs_core.io.run_folder`` declares them; numpy only, so ``panogs view`` needs no pipeline.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.errors import InputError
from panogs_core.gaussians.ply import read_gaussian_ply
from panogs_core.gaussians.views import parse_up
from panogs_core.io.run_folder import CAMERAS_JSON, GAUSSIANS_PLY, INSTANCES_JSON, VOCABULARY_JSON
from panogs_core.io.run_json import read_run_json
from panogs_core.palette import VOID_COLOR, class_color, instance_color

MAGIC = b"PGSV"
FORMAT_VERSION = 1
DECIMATION_SEED = 0  # the same run decimated twice keeps the same primitives


@dataclass(frozen=True)
class ViewerScene:
    """The encoded scene and what callers report about it."""

    data: bytes
    count: int  # primitives in the file
    total: int  # primitives in the run


def _read_primitives(run_dir: Path) -> dict[str, np.ndarray]:
    """Per Gaussian: position, DC colour in [0, 1], log scales, class and instance."""
    path = GAUSSIANS_PLY.path(run_dir)
    if not path.is_file():
        raise InputError(f"{path}: missing; is {run_dir} the --out folder of a finished run?")
    gaussians, semantic, instance = read_gaussian_ply(path)
    return {
        "position": gaussians.means,
        "color": gaussians.dc_colors(),
        "log_scale": gaussians.log_scales,
        "semantic": semantic,
        "instance": instance,
    }


def decimation_indices(total: int, limit: int | None) -> np.ndarray | None:
    """Sorted indices of ``limit`` primitives drawn evenly at random, or None when all fit."""
    if limit is None or total <= limit:
        return None
    rng = np.random.default_rng(DECIMATION_SEED)
    return np.sort(rng.choice(total, size=limit, replace=False))


def build_scene(
    run_dir: str | Path, *, max_primitives: int | None = None, extra: dict[str, Any] | None = None
) -> ViewerScene:
    """Encode a finished run folder for the viewer.

    Args:
        run_dir: The ``--out`` folder of a run (or a job's result folder).
        max_primitives: Keep at most this many primitives (a seeded random subset); None keeps all.
        extra: More header fields (``title``, the precomputed class queries of an offline file).

    Raises:
        InputError: a file of the run is missing or does not match the others.
    """
    run = Path(run_dir)
    vocabulary = read_run_json(VOCABULARY_JSON.path(run))
    instances = read_run_json(INSTANCES_JSON.path(run))
    if isinstance(instances, dict):
        instances = instances.get("instances", [])
    v = _read_primitives(run)
    total = int(v["position"].shape[0])
    keep = decimation_indices(total, max_primitives)

    def column(name: str) -> np.ndarray:
        return v[name] if keep is None else v[name][keep]

    position = column("position").astype(np.float32)
    color = (column("color") * 255.0 + 0.5).astype(np.uint8)
    scale: np.ndarray = point_radii(position, column("log_scale"))
    semantic = column("semantic").astype(np.int16)
    instance = column("instance").astype(np.int32)

    classes = vocabulary.get("classes", []) if isinstance(vocabulary, dict) else []
    counts = np.bincount(semantic[semantic >= 0].astype(np.int64), minlength=len(classes))
    header: dict[str, Any] = {
        "count": int(position.shape[0]),
        "total": total,
        "bounds": _bounds(position),
        "classes": [
            {"index": i, "name": c["name"], "kind": c["kind"], "color": class_color(i), "count": int(counts[i])}
            for i, c in enumerate(classes)
        ],
        "void": {"color": VOID_COLOR, "count": int((semantic < 0).sum())},
        "instances": [{**row, "color": instance_color(int(row["id"]))} for row in instances],
        **_up(run),
        **(extra or {}),
    }
    arrays: dict[str, np.ndarray] = {
        "position": position,
        "color": color,
        "semantic": semantic,
        "instance": instance,
        "scale": scale,
    }
    return ViewerScene(data=encode(header, arrays), count=int(position.shape[0]), total=total)


def point_radii(
    position: np.ndarray,  # (N, 3) float32
    log_scales: np.ndarray,  # (N, 3) float, the Gaussians' log scales
) -> np.ndarray:  # (N,) float32, metres
    """The radius each primitive is drawn with in the point modes: its mean axis, at most its spacing radius.

    The fit lets a Gaussian grow (up to ``appearance.max_scale_growth``, 4x, over its neighbour-spacing start) to
    cover the gaps between centres with a soft, often faint edge; the points are opaque hard discs, and at the
    fitted size the tiny room's first view was big overlapping discs (median radius 0.049 m after the fit against
    0.018 m before, at a spacing of about 0.08 m). Capped at the radius the fit starts from (the primitives stage's
    ``gaussian_log_scales`` of the same centres), a fitted scene draws like the unfitted one; a decimated scene's
    wider spacing lets its points keep their fitted size.
    """
    from panogs_core.stages.primitives import gaussian_log_scales

    fitted: np.ndarray = np.exp(np.asarray(log_scales, np.float64)).mean(axis=1)
    if position.shape[0] >= 2:
        spacing = np.exp(gaussian_log_scales(position)[:, 0].astype(np.float64))
        fitted = np.minimum(fitted, spacing)
    return fitted.astype(np.float32)


def _up(run: Path) -> dict[str, list[float]]:
    """``{"up": [x, y, z]}`` from the run's ``cameras.json``, or nothing for a run that has none (older runs)."""
    path = CAMERAS_JSON.path(run)
    if not path.is_file():
        return {}
    doc = read_run_json(path)
    if not isinstance(doc, dict) or "up" not in doc:
        return {}
    return {"up": list(parse_up(doc["up"], f"{path}: up"))}


def _bounds(position: np.ndarray) -> dict[str, list[float]]:
    if position.shape[0] == 0:
        return {"min": [0.0, 0.0, 0.0], "max": [0.0, 0.0, 0.0]}
    return {"min": position.min(axis=0).tolist(), "max": position.max(axis=0).tolist()}


def encode(header: dict[str, Any], arrays: dict[str, np.ndarray]) -> bytes:
    """The file: magic, version, header (with each array's dtype, shape and offset), then the arrays."""
    layout: dict[str, dict[str, Any]] = {}
    offset = 0
    for name, array in arrays.items():
        layout[name] = {"dtype": array.dtype.name, "shape": list(array.shape), "offset": offset}
        offset += _padded(array.nbytes)
    text = json.dumps({**header, "arrays": layout}, separators=(",", ":")).encode()
    text += b" " * (_padded(len(text)) - len(text))
    parts = [MAGIC, struct.pack("<II", FORMAT_VERSION, len(text)), text]
    for array in arrays.values():
        raw = np.ascontiguousarray(array).astype(array.dtype.newbyteorder("<"), copy=False).tobytes()
        parts.append(raw + b"\0" * (_padded(len(raw)) - len(raw)))
    return b"".join(parts)


def decode(data: bytes) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Header and arrays of an encoded scene (the reader the tests and tools use; the browser has its own)."""
    if data[:4] != MAGIC:
        raise InputError(f"not a panogs viewer scene (magic {data[:4]!r}, expected {MAGIC!r})")
    version, length = struct.unpack("<II", data[4:12])
    if version != FORMAT_VERSION:
        raise InputError(f"viewer scene format version {version}; this reader knows {FORMAT_VERSION}")
    header = json.loads(data[12 : 12 + length])
    body = 12 + length
    arrays = {}
    for name, spec in header["arrays"].items():
        dtype = np.dtype(spec["dtype"]).newbyteorder("<")
        count = int(np.prod(spec["shape"]))
        start = body + spec["offset"]
        arrays[name] = np.frombuffer(data, dtype=dtype, count=count, offset=start).reshape(spec["shape"])
    return header, arrays


def _padded(n: int) -> int:
    return (n + 3) // 4 * 4
