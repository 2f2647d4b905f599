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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.bounded_json import JsonLimits, read_json_file
from panogs_core.errors import BundleError, InputError
from panogs_core.io.bundle.file_checks import check_features, check_image, check_rel_path
from panogs_core.io.bundle.format import (
    FORMAT_ID,
    FRAME_FILES,
    FRAME_KEYS,
    LAST_ROW_TOL,
    MAX_FRAME_ID_CHARS,
    ROTATION_TOL,
    SKIPPED_FRAME_KEYS,
    TOP_KEYS,
    BundleLimits,
)
from panogs_core.io.bundle.problems import CpuBudget, OverBudget, integer, number, short
from panogs_core.io.bundle.reader import Bundle
from panogs_core.io.bundle.scene_checks import check_geometry, check_ground_truth, check_vocabulary
from panogs_core.types import Camera, Frame, Vocabulary

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


def validate(root: Path, *, limits: BundleLimits, source: str | None = None, budget: CpuBudget | None = None) -> Bundle:
    """Check every rule of docs/scene_format.md; return the Bundle or raise one BundleError listing all problems.

    ``budget`` is the CPU clock of the whole opening (default: one started here, of ``limits.max_cpu_s``); it is
    looked at before each frame entry and each distinct file, and once spent the problems found so far are
    reported with one more naming where validation stopped.
    """
    budget = budget or CpuBudget(limits.max_cpu_s)
    problems: list[str] = []
    try:
        checked = _check_all(root, limits, budget, problems)
    except OverBudget as exc:
        problems.append(str(exc))
    if problems:
        raise BundleError(relative_to_root(problems, root), source=source or root.name)
    return _bundle(root, *checked)


def _check_all(root: Path, limits: BundleLimits, budget: CpuBudget, problems: list[str]) -> _Checked:
    manifest = _load_manifest(root, limits.json, problems)
    header = (
        _check_header(manifest, limits, problems) if manifest is not None else _Header(None, None, None, None, None)
    )
    frames = _check_frames(root, manifest, header, limits, budget, problems) if manifest is not None else []
    up = _check_up(manifest, problems) if manifest is not None else None
    skipped = _check_skipped_frames(manifest, {f.id for f in frames}, problems) if manifest is not None else ()
    budget.check("geometry.ply")
    num_vertices = check_geometry(root, problems)
    budget.check("vocabulary.json")
    vocabulary = check_vocabulary(root, header.feature_dim, limits.json, limits.max_classes, problems)
    budget.check("gt/labels.npz")
    has_gt = check_ground_truth(root, vocabulary, num_vertices, limits, problems)
    return manifest, header, frames, up, skipped, num_vertices, vocabulary, has_gt


# What the checks found, in the order _bundle takes it.
_Checked = tuple[
    dict[str, Any] | None,
    _Header,
    list[Frame],
    tuple[float, float, float] | None,
    tuple[tuple[str, np.ndarray], ...],
    int | None,
    Vocabulary | None,
    bool,
]


def _bundle(
    root: Path,
    manifest: dict[str, Any] | None,
    header: _Header,
    frames: list[Frame],
    up: tuple[float, float, float] | None,
    skipped: tuple[tuple[str, np.ndarray], ...],
    num_vertices: int | None,
    vocabulary: Vocabulary | None,
    has_gt: bool,
) -> Bundle:
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
    depth_scale = number(doc.get("depth_scale"))
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
        dim = integer(features.get("dim"))
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
        problems.append(f"scene.json: camera {short(cam)}, expected an object with width, height, fx, fy, cx, cy")
        return None, None
    width, height = integer(cam.get("width")), integer(cam.get("height"))
    fx, fy, cx, cy = (number(cam.get(k)) for k in ("fx", "fy", "cx", "cy"))
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
            problems.append(f"scene.json: camera.{key} {short(cam.get(key))}, expected {want}")
    size = (height, width) if height is not None and width is not None and height > 0 and width > 0 else None
    if size is None or fx is None or fy is None or cx is None or cy is None or fx <= 0 or fy <= 0:
        return None, size
    return Camera(width=size[1], height=size[0], fx=fx, fy=fy, cx=cx, cy=cy), size


def _check_frames(
    root: Path, doc: dict[str, Any], header: _Header, limits: BundleLimits, budget: CpuBudget, problems: list[str]
) -> list[Frame]:
    entries = doc.get("frames")
    if not isinstance(entries, list) or not entries:
        problems.append(f"scene.json: frames {short(entries)}, expected a non-empty list")
        return []
    frames: list[Frame] = []
    seen: set[str] = set()
    checked: set[tuple[str, str]] = set()  # (kind, path): frames may share a file, which is checked once
    for i, entry in enumerate(entries):
        budget.check(f"scene.json: frames[{i}]")
        frame = _check_frame_entry(root, i, entry, seen, problems)
        if frame is None:
            continue
        frames.append(frame)
        _check_frame_files(root, frame, header, limits, budget, checked, problems)
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
        problems.append(f"{where}: {short(entry)}, expected an object")
        return None
    unknown = sorted(set(entry) - FRAME_KEYS)
    if unknown:
        logger.warning("%s: ignoring unknown keys %s", where, unknown)
    frame_id = _frame_id(entry.get("id"), where, problems)
    if frame_id is None:
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
        paths[key] = check_rel_path(root, value, f"{where}.{key}", exts, problems)
    if pose is None or paths["depth"] is None:
        return None
    return Frame(frame_id, pose, paths["depth"], paths["color"], paths["features"], paths["masks"])  # type: ignore[arg-type]


def _frame_id(value: Any, where: str, problems: list[str]) -> str | None:
    """A frame's id: a non-empty printable string of at most ``MAX_FRAME_ID_CHARS``; else a problem and None."""
    if not isinstance(value, str) or not value:
        problems.append(f"{where}.id: {short(value)}, expected a non-empty string")
        return None
    if len(value) > MAX_FRAME_ID_CHARS:
        problems.append(
            f"{where}.id: {short(value)} has {len(value):,} characters, expected at most {MAX_FRAME_ID_CHARS}"
        )
        return None
    if not value.isprintable():
        problems.append(f"{where}.id: {value!r} holds control or non-printable characters, expected printable text")
        return None
    return value


def _check_up(doc: dict[str, Any], problems: list[str]) -> tuple[float, float, float] | None:
    """``up`` (§2.5): absent, or 3 finite numbers not all 0, returned normalised to unit length."""
    if "up" not in doc:
        return None
    value = doc["up"]
    numbers = [number(v) for v in value] if isinstance(value, list) and len(value) == 3 else None
    if numbers is None or any(v is None for v in numbers):
        problems.append(f"scene.json: up {short(value)}, expected a list of 3 finite numbers")
        return None
    vec = np.asarray(numbers, dtype=np.float64)
    norm = float(np.linalg.norm(vec))
    if not norm > 1e-9:
        problems.append(f"scene.json: up {short(value)} has no direction, expected a non-zero vector")
        return None
    x, y, z = (float(v) for v in vec / norm)
    return (x, y, z)


def _check_skipped_frames(
    doc: dict[str, Any], frame_ids: set[str], problems: list[str]
) -> tuple[tuple[str, np.ndarray], ...]:
    """``skipped_frames`` (§2.6): frames of the capture with a pose only, ids unique among all frames."""
    entries = doc.get("skipped_frames", [])
    if not isinstance(entries, list):
        problems.append(f"scene.json: skipped_frames {short(entries)}, expected a list")
        return ()
    seen = set(frame_ids)
    out: list[tuple[str, np.ndarray]] = []
    for i, entry in enumerate(entries):
        where = f"scene.json: skipped_frames[{i}]"
        if not isinstance(entry, dict):
            problems.append(f"{where}: {short(entry)}, expected an object with id and pose")
            continue
        unknown = sorted(set(entry) - SKIPPED_FRAME_KEYS)
        if unknown:
            logger.warning("%s: ignoring unknown keys %s", where, unknown)
        frame_id = _frame_id(entry.get("id"), where, problems)
        if frame_id is None:
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
        problems.append(f"{where}: {short(value)}, expected a 4x4 list of numbers")
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


def _check_frame_files(
    root: Path,
    frame: Frame,
    header: _Header,
    limits: BundleLimits,
    budget: CpuBudget,
    checked: set[tuple[str, str]],
    problems: list[str],
) -> None:
    """Check each file of one frame not checked yet, one at a time: the image's header, then its data's framing."""
    for kind, rel in (("depth", frame.depth), ("color", frame.color), ("masks", frame.masks)):
        if rel is not None and (kind, rel) not in checked:
            budget.check(rel)
            checked.add((kind, rel))
            check_image(root, rel, kind, header.size, limits, problems)
    if frame.features is not None and ("features", frame.features) not in checked:
        budget.check(frame.features)
        checked.add(("features", frame.features))
        check_features(root, frame.features, header.feature_dim, limits, problems)
