"""Validation of a bundle folder: every rule of docs/scene_format.md checked at once, one problem line each.

Validation reads each image's header first (size, channels, bit depth: ``panogs_core.io.image_header``) and
compares it with the camera and the pixel limit; only an image that passes is read, to check the framing of its
compressed data (PNG chunk lengths and CRC-32 up to IEND, a JPEG's end marker), one file at a time; no image is
decoded here (the stages decode what they use). Feature maps are read by their headers only, and the JSON files
through the bounded reader (``panogs_core.bounded_json``). Each check appends problem lines of the form
``<file>: <what was found>, expected <what>`` to one list, so that a broken bundle is reported in one go; every
path in them is relative to the bundle root.
"""

from __future__ import annotations

import logging
import lzma
import math
import os
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.bounded_json import JsonLimits, read_json_file
from panogs_core.errors import BundleError, InputError
from panogs_core.io.bundle.format import (
    FEATURE_DTYPES,
    FORMAT_ID,
    FRAME_FILES,
    FRAME_KEYS,
    GT_KEYS,
    LAST_ROW_TOL,
    ROTATION_TOL,
    SKIPPED_FRAME_KEYS,
    TOP_KEYS,
    BundleLimits,
    max_png_chunks,
)
from panogs_core.io.bundle.reader import Bundle
from panogs_core.io.image_header import ImageHeader, read_image_header
from panogs_core.io.npy_header import NpyHeader, read_npy_header
from panogs_core.io.ply import scan_ply_positions
from panogs_core.types import Camera, ClassKind, Frame, Vocabulary

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Header:
    """What validation learnt from ``scene.json`` that file checks need (None where the field was invalid)."""

    camera: Camera | None
    size: tuple[int, int] | None  # (height, width) of the camera, valid even when the intrinsics are not
    depth_scale: float | None
    feature_dim: int | None
    feature_space: str | None
    has_features: bool = True  # scene.json declares features (dim and space); False: no feature maps at all


def validate(root: Path, *, limits: BundleLimits, source: str | None = None) -> Bundle:
    """Check every rule of docs/scene_format.md; return the Bundle or raise one BundleError listing all problems."""
    problems: list[str] = []
    manifest = _load_manifest(root, limits.json, problems)
    header = (
        _check_header(manifest, limits, problems) if manifest is not None else _Header(None, None, None, None, None)
    )
    frames = _check_frames(root, manifest, header, limits, problems) if manifest is not None else []
    up = _check_up(manifest, problems) if manifest is not None else None
    skipped = _check_skipped_frames(manifest, {f.id for f in frames}, problems) if manifest is not None else ()
    num_vertices = _check_geometry(root, problems)
    vocabulary = _check_vocabulary(root, header.feature_dim, limits.json, limits.max_classes, problems)
    has_gt = _check_ground_truth(root, vocabulary, num_vertices, limits, problems)
    if problems:
        raise BundleError(relative_to_root(problems, root), source=source or root.name)
    # No problem implies every header field parsed; the asserts only narrow the types.
    assert manifest is not None
    assert header.camera is not None
    assert header.depth_scale is not None
    assert not header.has_features or (header.feature_dim is not None and header.feature_space is not None)
    name = manifest.get("name")
    return Bundle(
        root=root,
        name=name if isinstance(name, str) and name else root.name,
        camera=header.camera,
        depth_scale=header.depth_scale,
        feature_dim=header.feature_dim or 0,
        feature_space=header.feature_space or "",
        frames=tuple(frames),
        vocabulary=vocabulary,
        has_geometry=num_vertices is not None,
        has_ground_truth=has_gt,
        up=up,
        skipped_poses=skipped,
    )


def relative_to_root(problems: list[str], root: Path) -> list[str]:
    """The problems with any absolute path of ``root`` (as given or resolved) cut to the bundle-relative rest.

    Every check words its problems with relative paths already; this is the one net under all of them, so that
    a message from a library (an OSError's file name) never shows where the service stores bundles.
    """
    prefixes = sorted({str(root.absolute()), str(root.resolve())} - {"/"}, key=len, reverse=True)
    out = []
    for problem in problems:
        for prefix in prefixes:
            problem = problem.replace(prefix + "/", "").replace(prefix, ".")
        out.append(problem)
    return out


def _load_manifest(root: Path, limits: JsonLimits, problems: list[str]) -> dict[str, Any] | None:
    path = root / "scene.json"
    if path.is_symlink():
        problems.append("scene.json: is a symbolic link, expected a regular file")
        return None
    if not path.is_file():
        problems.append("scene.json: missing, expected the manifest at the bundle root")
        return None
    try:
        doc = read_json_file(path, limits, name="scene.json")
    except InputError as exc:  # not JSON, over a limit, or unreadable: the message names the file and the limit
        problems.append(str(exc))
        return None
    if not isinstance(doc, dict):
        problems.append(f"scene.json: top level is {type(doc).__name__}, expected an object")
        return None
    unknown = sorted(set(doc) - TOP_KEYS)
    if unknown:
        logger.warning("scene.json: ignoring unknown keys %s", unknown)
    return doc


def _check_header(doc: dict[str, Any], limits: BundleLimits, problems: list[str]) -> _Header:
    if doc.get("format") != FORMAT_ID:
        problems.append(f"scene.json: format {doc.get('format')!r}, expected {FORMAT_ID!r}")
    if "name" in doc and not isinstance(doc["name"], str):
        problems.append(f"scene.json: name {doc['name']!r}, expected a string")
    camera, size = _check_camera(doc.get("camera"), problems)
    if size is not None and size[0] * size[1] > limits.max_image_pixels:
        problems.append(
            f"scene.json: camera {size[1]}x{size[0]} ({size[0] * size[1]:,} pixels), over the pixel limit of "
            f"{limits.max_image_pixels:,}"
        )
        camera, size = None, None
    depth_scale = _number(doc.get("depth_scale"))
    if depth_scale is None or depth_scale <= 0:
        problems.append(f"scene.json: depth_scale {doc.get('depth_scale')!r}, expected a finite number > 0")
        depth_scale = None
    features = doc.get("features")
    dim: int | None = None
    space: str | None = None
    if features is None:
        # A bundle without feature maps (the 2D-maps stage computes them): no space, no width. A frame that
        # brings a feature map anyway is refused by the frame checks.
        return _Header(camera, size, depth_scale, None, None, has_features=False)
    if not isinstance(features, dict):
        problems.append(f"scene.json: features {features!r}, expected an object with dim and space")
    else:
        dim = _integer(features.get("dim"))
        if dim is None or dim <= 0:
            problems.append(f"scene.json: features.dim {features.get('dim')!r}, expected an integer > 0")
            dim = None
        elif dim > limits.max_feature_dim:
            problems.append(f"scene.json: features.dim {dim:,}, over the limit of {limits.max_feature_dim:,}")
            dim = None
        space = features.get("space")
        if not isinstance(space, str) or not space:
            problems.append(f"scene.json: features.space {space!r}, expected a non-empty string")
            space = None
    return _Header(camera, size, depth_scale, dim, space)


def _check_camera(cam: Any, problems: list[str]) -> tuple[Camera | None, tuple[int, int] | None]:
    """The camera, and its (height, width) on its own so that depth sizes are checked even if fx is bad."""
    if not isinstance(cam, dict):
        problems.append(f"scene.json: camera {_short(cam)}, expected an object with width, height, fx, fy, cx, cy")
        return None, None
    width, height = _integer(cam.get("width")), _integer(cam.get("height"))
    fx, fy, cx, cy = (_number(cam.get(k)) for k in ("fx", "fy", "cx", "cy"))
    checks = [
        ("width", width, True, "an integer > 0"),
        ("height", height, True, "an integer > 0"),
        ("fx", fx, True, "a finite number > 0"),
        ("fy", fy, True, "a finite number > 0"),
        ("cx", cx, False, "a finite number"),
        ("cy", cy, False, "a finite number"),
    ]
    for key, value, positive, want in checks:
        if value is None or (positive and value <= 0):
            problems.append(f"scene.json: camera.{key} {_short(cam.get(key))}, expected {want}")
    size = (height, width) if height is not None and width is not None and height > 0 and width > 0 else None
    if size is None or fx is None or fy is None or cx is None or cy is None or fx <= 0 or fy <= 0:
        return None, size
    return Camera(width=size[1], height=size[0], fx=fx, fy=fy, cx=cx, cy=cy), size


def _check_frames(
    root: Path, doc: dict[str, Any], header: _Header, limits: BundleLimits, problems: list[str]
) -> list[Frame]:
    entries = doc.get("frames")
    if not isinstance(entries, list) or not entries:
        problems.append(f"scene.json: frames {_short(entries)}, expected a non-empty list")
        return []
    frames: list[Frame] = []
    seen: set[str] = set()
    checked: set[tuple[str, str]] = set()  # (kind, path): frames may share a file, which is checked once
    for i, entry in enumerate(entries):
        frame = _check_frame_entry(root, i, entry, seen, problems)
        if frame is None:
            continue
        frames.append(frame)
        _check_frame_files(root, frame, header, limits, checked, problems)
    _check_maps_present(frames, header, problems)
    return frames


def _check_maps_present(frames: list[Frame], header: _Header, problems: list[str]) -> None:
    """Maps are optional (the 2D-maps stage computes the missing kind from the colour frames), but a kind the
    bundle lacks needs a colour image to be computed from, and feature maps need the header that describes them."""
    with_color = any(f.color is not None for f in frames)
    has_features = any(f.features is not None for f in frames)
    if has_features and not header.has_features:
        problems.append("scene.json: frames have feature maps but no features object (dim and space) describes them")
    for kind, present in (("feature maps", has_features), ("masks", any(f.masks is not None for f in frames))):
        if frames and not present and not with_color:
            problems.append(
                f"scene.json: no frame has {kind} nor a colour image to compute them from; give maps "
                "(docs/scene_format.md §2.3) or colour frames for the 2D-maps stage"
            )


def _check_frame_entry(root: Path, i: int, entry: Any, seen: set[str], problems: list[str]) -> Frame | None:
    """Manifest-level checks of one frame (id, pose, paths); the files are checked by the caller."""
    where = f"scene.json: frames[{i}]"
    if not isinstance(entry, dict):
        problems.append(f"{where}: {_short(entry)}, expected an object")
        return None
    unknown = sorted(set(entry) - FRAME_KEYS)
    if unknown:
        logger.warning("%s: ignoring unknown keys %s", where, unknown)
    frame_id = entry.get("id")
    if not isinstance(frame_id, str) or not frame_id:
        problems.append(f"{where}.id: {frame_id!r}, expected a non-empty string")
        frame_id = f"#{i}"
    elif frame_id in seen:
        problems.append(f"{where}.id: {frame_id!r} used by an earlier frame, expected unique ids")
    seen.add(frame_id)
    pose = _check_pose(entry.get("pose"), f"{where}.pose", problems)
    paths: dict[str, str | None] = {}
    for key, exts in FRAME_FILES.items():
        value = entry.get(key)
        if value is None and key != "depth":
            paths[key] = None
            continue
        paths[key] = _check_rel_path(root, value, f"{where}.{key}", exts, problems)
    if pose is None or paths["depth"] is None:
        return None
    return Frame(frame_id, pose, paths["depth"], paths["color"], paths["features"], paths["masks"])  # type: ignore[arg-type]


def _check_up(doc: dict[str, Any], problems: list[str]) -> tuple[float, float, float] | None:
    """``up`` (§2.5): absent, or 3 finite numbers not all 0, returned normalised to unit length."""
    if "up" not in doc:
        return None
    value = doc["up"]
    numbers = [_number(v) for v in value] if isinstance(value, list) and len(value) == 3 else None
    if numbers is None or any(v is None for v in numbers):
        problems.append(f"scene.json: up {_short(value)}, expected a list of 3 finite numbers")
        return None
    vec = np.asarray(numbers, dtype=np.float64)
    norm = float(np.linalg.norm(vec))
    if not norm > 1e-9:
        problems.append(f"scene.json: up {_short(value)} has no direction, expected a non-zero vector")
        return None
    x, y, z = (float(v) for v in vec / norm)
    return (x, y, z)


def _check_skipped_frames(
    doc: dict[str, Any], frame_ids: set[str], problems: list[str]
) -> tuple[tuple[str, np.ndarray], ...]:
    """``skipped_frames`` (§2.6): frames of the capture with a pose only, ids unique among all frames."""
    entries = doc.get("skipped_frames", [])
    if not isinstance(entries, list):
        problems.append(f"scene.json: skipped_frames {_short(entries)}, expected a list")
        return ()
    seen = set(frame_ids)
    out: list[tuple[str, np.ndarray]] = []
    for i, entry in enumerate(entries):
        where = f"scene.json: skipped_frames[{i}]"
        if not isinstance(entry, dict):
            problems.append(f"{where}: {_short(entry)}, expected an object with id and pose")
            continue
        unknown = sorted(set(entry) - SKIPPED_FRAME_KEYS)
        if unknown:
            logger.warning("%s: ignoring unknown keys %s", where, unknown)
        frame_id = entry.get("id")
        if not isinstance(frame_id, str) or not frame_id:
            problems.append(f"{where}.id: {frame_id!r}, expected a non-empty string")
            continue
        if frame_id in seen:
            problems.append(f"{where}.id: {frame_id!r} used by another frame, expected unique ids")
            continue
        seen.add(frame_id)
        pose = _check_pose(entry.get("pose"), f"{where}.pose", problems)
        if pose is not None:
            out.append((frame_id, pose))
    return tuple(out)


def _check_pose(value: Any, where: str, problems: list[str]) -> np.ndarray | None:  # (4, 4) float64
    try:
        pose = np.array(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        pose = None
    if pose is None or pose.shape != (4, 4):
        problems.append(f"{where}: {_short(value)}, expected a 4x4 list of numbers")
        return None
    if not np.all(np.isfinite(pose)):
        problems.append(f"{where}: contains NaN or infinite values, expected finite numbers")
        return None
    if np.max(np.abs(pose[3] - [0.0, 0.0, 0.0, 1.0])) > LAST_ROW_TOL:
        problems.append(f"{where}: last row {pose[3].tolist()}, expected [0, 0, 0, 1]")
    rot = pose[:3, :3]
    ortho_err = float(np.max(np.abs(rot.T @ rot - np.eye(3))))
    det = float(np.linalg.det(rot))
    if ortho_err > ROTATION_TOL or abs(det - 1.0) > ROTATION_TOL:
        problems.append(
            f"{where}: rotation not orthonormal with det 1 (max |R^T R - I| = {ortho_err:.3g}, "
            f"det = {det:.4f}), expected within {ROTATION_TOL}"
        )
    return pose


def _check_rel_path(root: Path, value: Any, where: str, exts: tuple[str, ...], problems: list[str]) -> str | None:
    """A referenced path must be relative, stay in the root, avoid links, exist and be a regular file."""
    if not isinstance(value, str) or not value:
        problems.append(f"{where}: {value!r}, expected a relative path")
        return None
    if value.startswith("/") or "\\" in value or (len(value) > 1 and value[1] == ":"):
        problems.append(f"{value}: absolute or non-posix path ({where}), expected a path relative to the root")
        return None
    parts = value.split("/")
    if ".." in parts or "" in parts:
        problems.append(f"{value}: leaves the bundle root or has empty parts ({where})")
        return None
    if not value.lower().endswith(exts):
        problems.append(f"{value}: extension not allowed ({where}), expected {' or '.join(exts)}")
        return None
    current = root
    for part in parts:
        current = current / part
        if current.is_symlink():
            problems.append(f"{value}: {current.relative_to(root)} is a symbolic link ({where}), not allowed")
            return None
    if not current.exists():
        problems.append(f"{value}: missing ({where})")
        return None
    if not current.is_file():
        problems.append(f"{value}: not a regular file ({where})")
        return None
    if not current.resolve().is_relative_to(root.resolve()):  # belt and braces after the symlink walk
        problems.append(f"{value}: resolves outside the bundle root ({where})")
        return None
    return value


def _check_frame_files(
    root: Path, frame: Frame, header: _Header, limits: BundleLimits, checked: set[tuple[str, str]], problems: list[str]
) -> None:
    """Check each file of one frame not checked yet, one at a time: the image's header, then its data's framing."""
    for kind, rel in (("depth", frame.depth), ("color", frame.color), ("masks", frame.masks)):
        if rel is not None and (kind, rel) not in checked:
            checked.add((kind, rel))
            _check_image(root, rel, kind, header.size, limits, problems)
    if frame.features is not None and ("features", frame.features) not in checked:
        checked.add(("features", frame.features))
        _check_features(root, frame.features, header.feature_dim, limits, problems)


def _check_image(
    root: Path, rel: str, kind: str, camera_size: tuple[int, int] | None, limits: BundleLimits, problems: list[str]
) -> None:
    """The header's rules (:func:`_header_problem`), then the data's framing (:func:`_data_problem`).

    No image is decoded here (docs/scene_format.md §5): the header already fixes size, channels and bit depth,
    and a truncated or altered file breaks the framing (a PNG chunk's length or CRC-32, its IEND; a JPEG's end
    marker). An image well framed that still fails to decode is refused by the stage that reads it, naming the
    file. The stages decode each image they use anyway; decoding all of them here was most of the validation's
    time (docs/benchmarks.md, "Speed at ScanNet size").
    """
    try:
        info = read_image_header(root / rel, name=rel)
    except InputError as exc:
        problems.append(str(exc))
        return
    problem = _header_problem(rel, kind, info, camera_size, limits.max_image_pixels)
    if problem is None:
        problem = _data_problem(root, rel)
    if problem is not None:
        problems.append(problem)


def _header_problem(
    rel: str, kind: str, info: ImageHeader, camera_size: tuple[int, int] | None, max_pixels: int
) -> str | None:
    """What is wrong with an image by its header (format, pixel limit, camera size, channels, bits), or None.

    The same rules as the checks after decoding (docs/scene_format.md §1), so that an image that would be
    refused anyway is refused without allocating its pixels.
    """
    want_format = "JPEG" if rel.lower().endswith((".jpg", ".jpeg")) else "PNG"
    if info.format != want_format:
        return f"{rel}: holds {info.format} data, expected {want_format} (by its first bytes)"
    if info.pixels > max_pixels:
        return f"{rel}: {info.width}x{info.height} ({info.pixels:,} pixels), over the pixel limit of {max_pixels:,}"
    if kind == "depth":
        if camera_size is not None and (info.height, info.width) != camera_size:
            return f"{rel}: {info.width}x{info.height}, expected {camera_size[1]}x{camera_size[0]} (camera)"
        if info.channels != 1 or info.bit_depth != 16:
            return f"{rel}: {info.describe()}, expected 16-bit single channel"
    elif kind == "masks" and info.channels != 1:
        return f"{rel}: {info.describe()}, expected 8- or 16-bit single channel"
    elif kind == "color" and (
        info.bit_depth != 8 or info.channels not in (3, 4) or (info.channels == 4 and info.format == "PNG")
    ):
        # A JPEG of 4 components is CMYK, which the decoder turns into 3 channels; a PNG of 4 is RGBA.
        return f"{rel}: {info.describe()}, expected 8-bit 3 channels"
    return None


def _data_problem(root: Path, rel: str) -> str | None:
    """What breaks the framing of an image's data (truncation, altered bytes), or None."""
    try:
        data = (root / rel).read_bytes()
    except OSError as exc:
        return f"{rel}: cannot be read ({_reason(exc)})"
    if rel.lower().endswith((".jpg", ".jpeg")):
        if not _jpeg_complete(data):
            # libjpeg decodes a truncated JPEG with only a warning and grey fill: look for the end marker instead.
            return f"{rel}: truncated JPEG (no end-of-image marker after the image data)"
        return None
    problem = _png_framing_problem(data, max_png_chunks(len(data)))
    return None if problem is None else f"{rel}: does not decode as an image ({problem})"


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png_framing_problem(data: bytes, max_chunks: int) -> str | None:
    """Why a PNG's chunks are not whole (a length past the end, a CRC-32 that does not match, no IEND), or None.

    Every byte of a PNG after its signature is inside a chunk whose CRC covers its type and data, so a truncated
    or altered file fails here without inflating the image. The walk stops after ``max_chunks`` chunks: each one
    costs a Python step, and no encoder writes that many for the file's size (``format.max_png_chunks``).
    """
    if not data.startswith(_PNG_SIGNATURE):
        return "not a PNG signature"
    view = memoryview(data)
    pos = len(_PNG_SIGNATURE)
    chunks = 0
    while pos + 12 <= len(data):
        chunks += 1
        if chunks > max_chunks:
            return f"more than {max_chunks:,} chunks in {len(data):,} bytes, expected at most that many"
        length = int.from_bytes(data[pos : pos + 4], "big")
        kind = bytes(data[pos + 4 : pos + 8])
        end = pos + 12 + length
        if end > len(data):
            return f"truncated PNG: its {kind.decode('latin-1')!r} chunk runs past the end of the file"
        if zlib.crc32(view[pos + 4 : end - 4]) != int.from_bytes(data[end - 4 : end], "big"):
            return f"corrupt PNG: the CRC of its {kind.decode('latin-1')!r} chunk does not match"
        if kind == b"IEND":
            return None
        pos = end
    return "truncated PNG: no IEND chunk"


def _jpeg_complete(data: bytes) -> bool:
    """True unless a JPEG's main image data lacks its end-of-image marker (EOI, ``FF D9``).

    The header segments are skipped by their lengths up to the first start-of-scan, so that the EOI of an EXIF
    thumbnail does not count; entropy-coded data never holds ``FF D9``. Data after the EOI (phones append
    trailers) is allowed. A file that is not a JPEG at all is left to the decoder to refuse.
    """
    if not data.startswith(b"\xff\xd8"):
        return True
    pos = 2
    while pos + 4 <= len(data) and data[pos] == 0xFF:
        marker = data[pos + 1]
        if marker == 0xDA:  # start of scan: the image data follows
            return data.find(b"\xff\xd9", pos) != -1
        if marker == 0xFF:  # fill byte
            pos += 1
        elif 0xD0 <= marker <= 0xD8 or marker == 0x01:  # markers without a length
            pos += 2
        else:
            pos += 2 + int.from_bytes(data[pos + 2 : pos + 4], "big")
    return False


def _check_features(root: Path, rel: str, dim: int | None, limits: BundleLimits, problems: list[str]) -> None:
    header = _npy_header(root / rel, rel, problems)
    if header is None:
        return
    shape, dtype = header.shape, header.dtype
    if dtype not in FEATURE_DTYPES:
        problems.append(f"{rel}: dtype {dtype}, expected float16 or float32")
    if len(shape) != 3 or min(shape, default=0) < 1:
        problems.append(f"{rel}: shape {shape}, expected (Hf, Wf, D) with every size >= 1")
    else:
        if dim is not None and shape[2] != dim:
            problems.append(f"{rel}: last dimension {shape[2]}, expected {dim} (features.dim)")
        if shape[0] * shape[1] > limits.max_image_pixels:
            problems.append(
                f"{rel}: {shape[1]}x{shape[0]} cells ({shape[0] * shape[1]:,}), over the pixel limit of "
                f"{limits.max_image_pixels:,}"
            )
    if header.fortran_order:
        problems.append(f"{rel}: Fortran order, expected C order")


def _npy_header(path: Path, rel: str, problems: list[str]) -> NpyHeader | None:
    """The header of a .npy, when it is valid and the file holds exactly the data it declares; else a problem.

    Only the header is read. Declared sizes are exact Python integers compared with the file's real size, so a
    shape that multiplies past int64 is refused, never wrapped to a small size that matches.
    """
    try:
        with path.open("rb") as fh:
            header = read_npy_header(fh, rel)
            available = os.fstat(fh.fileno()).st_size - header.offset
    except InputError as exc:
        problems.append(str(exc))
        return None
    except OSError as exc:
        problems.append(f"{rel}: cannot be read ({_reason(exc)})")
        return None
    problem = header.size_problem(available)
    if problem is not None:
        problems.append(f"{rel}: {problem}")
        return None
    return header


def _check_geometry(root: Path, problems: list[str]) -> int | None:
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
        problems.append(f"geometry.ply: {_strip_prefix(str(exc), 'geometry.ply: ')}")
        return None
    if count == 0:
        problems.append("geometry.ply: 0 vertices, expected at least one")
        return None
    if not finite:
        problems.append("geometry.ply: vertex positions contain NaN or infinite values")
    return count


def _check_vocabulary(
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
        problems.append(f"vocabulary.json: classes {_short(classes)}, expected a non-empty list")
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
        embeddings = _load_embeddings(root, doc["embeddings"], len(names), dim, problems)
    if len(problems) > n_before:
        return None
    return Vocabulary(names=tuple(names), kinds=tuple(kinds), embeddings=embeddings)


def _load_embeddings(
    root: Path, value: Any, num_classes: int, dim: int | None, problems: list[str]
) -> np.ndarray | None:  # (L, D) float32 unit rows
    rel = _check_rel_path(root, value, "vocabulary.json: embeddings", (".npy",), problems)
    if rel is None:
        return None
    header = _npy_header(root / rel, rel, problems)
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
    emb = _float32_rows(root / rel)
    norms = np.linalg.norm(emb, axis=1, keepdims=True)
    if not np.all(np.isfinite(emb)) or np.any(norms == 0):
        problems.append(f"{rel}: contains NaN, infinite or all-zero rows, expected finite non-zero embeddings")
        return None
    return emb / norms


def _float32_rows(path: Path, rows_at_once: int = 256) -> np.ndarray:  # (L, D) float32
    """A 2-D float ``.npy`` as float32, cast a few rows at a time from a memory map (never a float64 copy whole)."""
    stored = np.load(path, mmap_mode="r", allow_pickle=False)
    out = np.empty(stored.shape, np.float32)
    for start in range(0, len(stored), rows_at_once):
        out[start : start + rows_at_once] = stored[start : start + rows_at_once]
    return out


def _check_ground_truth(
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
    arrays = _load_npz(path, rel, limits.max_ground_truth_bytes, problems)
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


def _load_npz(path: Path, rel: str, max_bytes: int, problems: list[str]) -> dict[str, np.ndarray] | None:
    """The arrays of ``gt/labels.npz`` named in :data:`GT_KEYS` (other members are not read).

    Every member's header is read first and its declared size compared, as an exact integer, with the member's
    uncompressed size in the zip (which the zip reader never reads past) and the sum with ``max_bytes``: an
    array that claims more than its member holds, or members that would expand past the limit (a zip bomb),
    are refused before anything is decompressed beyond the headers.
    """
    try:
        with zipfile.ZipFile(path) as zf:
            members = _npz_members(zf, rel, problems)
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
        problems.append(f"{rel}: not a valid .npz file ({_reason(exc)})")
        return None


def _npz_members(zf: zipfile.ZipFile, rel: str, problems: list[str]) -> dict[str, zipfile.ZipInfo] | None:
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


def _number(value: Any) -> float | None:
    """A finite JSON number as float, else None (booleans are not numbers here)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        number = float(value)
    except OverflowError:  # JSON integers have no size limit
        return None
    return number if math.isfinite(number) else None


def _integer(value: Any) -> int | None:
    """A JSON integer (or an integral float such as 640.0), else None."""
    number = _number(value)
    if number is None or number != int(number):
        return None
    return int(number)


def _reason(exc: BaseException) -> str:
    """An exception's reason without the file name an OSError carries (an absolute path on the host)."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc)


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _strip_prefix(text: str, prefix: str) -> str:
    return text[len(prefix) :] if text.startswith(prefix) else text
