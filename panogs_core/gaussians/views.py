"""Renders of a finished run from any camera: colour, depth, semantic class, instance, and a query's relevance.

Inputs, all in the run's folder (:mod:`panogs_core.io.run_folder` declares them): ``gaussians.ply`` (the Gaussian
scene with its labels), ``cameras.json`` (the bundle's intrinsics, the poses of its frames and of the capture frames
the importer left out, and the run's up direction, so that ``--frame ID`` needs no bundle), ``vocabulary.json``
and ``instances.json`` (for the palette and text queries).

A pose is given as JSON: ``{"T_world_cam": 4x4 camera-to-world (OpenCV axes, docs/conventions.md)}``, optionally
with ``"camera": {"width", "height", "fx", "fy", "cx", "cy"}`` (default: the run's camera) ; ``size`` rescales the
camera to another resolution with the same field of view.

Labels are not blended: each pixel takes the semantic class and instance of the Gaussian with the largest
blending weight there (void where no Gaussian covers it, or where the accumulated opacity is under
``LABEL_MIN_ALPHA``). Colour, depth and relevance are blended.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.run_folder import CAMERAS_JSON, GAUSSIANS_PLY, load_result, load_vocabulary
from panogs_core.io.run_json import read_run_json
from panogs_core.types import Camera

LABEL_MIN_ALPHA = 0.5  # below this accumulated opacity a pixel shows the background, so it gets no label
MAX_PIXELS = 4096 * 4096  # a render larger than this is refused (memory)
OVERLAY_WEIGHT = 0.5  # panoptic colours over the rendered colour


@dataclass(frozen=True)
class ViewPose:
    """A camera to render: intrinsics at a size, and its camera-to-world pose."""

    camera: Camera
    T_world_cam: np.ndarray  # (4, 4) float64


@dataclass(frozen=True)
class ViewImages:
    """One rendered view."""

    color: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) float32 metres, 0 = nothing
    alpha: np.ndarray  # (H, W) float32
    semantic: np.ndarray  # (H, W) int64, -1 void
    instance: np.ndarray  # (H, W) int64, -1 none
    relevance: np.ndarray | None  # (H, W) float32 in [0, 1], with a query


def write_cameras(
    path: Path,
    camera: Camera,
    frames: Any,
    *,
    up: tuple[float, float, float] | None = None,
    up_source: str = "",
    skipped: tuple[tuple[str, np.ndarray], ...] = (),
) -> Path:
    """``cameras.json``: the camera, each frame's id and pose (for renders without the bundle), then the capture
    frames the importer left out (``"skipped": true``, pose only), and the run's ``up`` and ``up_source``."""
    doc: dict[str, Any] = {"camera": {k: getattr(camera, k) for k in ("width", "height", "fx", "fy", "cx", "cy")}}
    if up is not None:
        doc.update(up=list(up), up_source=up_source)
    doc["frames"] = [{"id": f.id, "T_world_cam": np.asarray(f.T_world_cam, float).tolist()} for f in frames] + [
        {"id": frame_id, "T_world_cam": np.asarray(pose, float).tolist(), "skipped": True} for frame_id, pose in skipped
    ]
    path.write_text(json.dumps(doc))
    return path


def parse_up(value: Any, where: str) -> tuple[float, float, float]:
    """A unit up vector from 3 finite numbers, not all 0."""
    try:
        vec = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}: expected 3 numbers, got {value!r}") from exc
    if vec.shape != (3,) or not np.all(np.isfinite(vec)) or not np.linalg.norm(vec) > 1e-9:
        raise InputError(f"{where}: expected 3 finite numbers, not all 0, got {value!r}")
    x, y, z = (float(v) for v in vec / np.linalg.norm(vec))
    return (x, y, z)


def parse_camera(doc: Any, where: str) -> Camera:
    """A :class:`Camera` from ``{"width", "height", "fx", "fy", "cx", "cy"}``, every field checked."""
    if not isinstance(doc, dict):
        raise InputError(f"{where}: expected an object with width, height, fx, fy, cx, cy, got {doc!r}")
    values: dict[str, Any] = {}
    for key in ("width", "height"):
        v = doc.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise InputError(f"{where}.{key}: expected an integer >= 1, got {v!r}")
        values[key] = v
    for key in ("fx", "fy", "cx", "cy"):
        v = doc.get(key)
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise InputError(f"{where}.{key}: expected a finite number, got {v!r}")
        if key in ("fx", "fy") and v <= 0:
            raise InputError(f"{where}.{key}: expected a value > 0, got {v!r}")
        values[key] = float(v)
    return Camera(**values)


def parse_pose(value: Any, where: str) -> np.ndarray:  # (4, 4) float64
    """A 4x4 rigid camera-to-world matrix from nested lists."""
    try:
        pose = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}: expected a 4x4 matrix of numbers, got {value!r}") from exc
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise InputError(f"{where}: expected a finite 4x4 matrix, got shape {pose.shape}")
    if not np.allclose(pose[3], [0, 0, 0, 1]) or not np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-3):
        raise InputError(f"{where}: not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")
    return pose


def parse_size(text: str) -> tuple[int, int]:
    """``"WxH"`` -> (W, H)."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() and int(p) > 0 for p in parts):
        raise InputError(f"--size: expected WIDTHxHEIGHT such as 640x480, got {text!r}")
    return int(parts[0]), int(parts[1])


def resize_camera(camera: Camera, size: tuple[int, int] | None) -> Camera:
    """The camera at ``size`` (same field of view; pixel centres stay at integers), or unchanged.

    Raises:
        InputError: when the size exceeds ``MAX_PIXELS``.
    """
    if size is not None:
        camera = camera.scaled(*size)
    if camera.width * camera.height > MAX_PIXELS:
        raise InputError(f"size {camera.width}x{camera.height}: at most {MAX_PIXELS} pixels per render")
    return camera


def run_camera(run_dir: Path) -> tuple[Camera, dict[str, np.ndarray]]:
    """The run's camera and its frames' poses by id, from ``cameras.json``."""
    path = CAMERAS_JSON.path(run_dir)
    doc = read_run_json(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list):
        raise InputError(f"{path}: expected an object with 'camera' and a 'frames' list")
    camera = parse_camera(doc.get("camera"), f"{path}: camera")
    poses = {
        str(f.get("id")): parse_pose(f.get("T_world_cam"), f"{path}: frame {f.get('id')!r}") for f in doc["frames"]
    }
    return camera, poses


def view_from_frame(run_dir: Path, frame_id: str, size: tuple[int, int] | None) -> ViewPose:
    """The pose of capture frame ``frame_id`` (a bundle frame, or one the importer left out) with the run's camera."""
    camera, poses = run_camera(run_dir)
    if frame_id not in poses:
        some = ", ".join(list(poses)[:5])
        raise InputError(f"--frame {frame_id!r}: no such frame in {CAMERAS_JSON.path(run_dir)} (frames: {some}, ...)")
    return ViewPose(camera=resize_camera(camera, size), T_world_cam=poses[frame_id])


def view_from_pose(doc: Any, default_camera: Camera, size: tuple[int, int] | None, where: str) -> ViewPose:
    """A view from a pose document (module docstring)."""
    if not isinstance(doc, dict) or "T_world_cam" not in doc:
        raise InputError(f"{where}: expected an object with 'T_world_cam' (4x4 camera-to-world)")
    unknown = sorted(set(doc) - {"T_world_cam", "camera"})
    if unknown:
        raise InputError(f"{where}: unknown key(s) {unknown}; known keys are ['T_world_cam', 'camera']")
    pose = parse_pose(doc["T_world_cam"], f"{where}: T_world_cam")
    camera = parse_camera(doc["camera"], f"{where}: camera") if "camera" in doc else default_camera
    return ViewPose(camera=resize_camera(camera, size), T_world_cam=pose)


@dataclass(frozen=True)
class RunScene:
    """What a run's folder holds for rendering."""

    gaussians: Any  # appearance.GaussianScene
    semantic: np.ndarray  # (N,) int64
    instance: np.ndarray  # (N,) int64
    is_thing: np.ndarray  # (L,) bool
    run_dir: Path


def load_run_scene(run_dir: str | Path) -> RunScene:
    """``gaussians.ply`` and the vocabulary's thing/stuff kinds of a finished run."""
    from panogs_core.gaussians.ply import read_gaussian_ply

    root = Path(run_dir)
    ply = GAUSSIANS_PLY.path(root)
    if not ply.is_file():
        raise InputError(f"{ply}: not found (is this a finished run's folder?)")
    gaussians, semantic, instance = read_gaussian_ply(ply)
    vocab, _ = load_vocabulary(root)
    return RunScene(gaussians=gaussians, semantic=semantic, instance=instance, is_thing=vocab.is_thing, run_dir=root)


def instance_relevance(run_dir: Path, query: str, instance: np.ndarray) -> np.ndarray:  # (N,) float32
    """Per Gaussian: its instance's score for ``query`` (panogs_core.language.query), 0 without an instance."""
    from panogs_core.language.query import query_instances

    loaded = load_result(run_dir)
    hits = query_instances(
        loaded.instances,
        loaded.vocabulary,
        query,
        feature_space=loaded.feature_space,
        top_k=max(1, len(loaded.instances)),
        min_score=0.0,
    )
    scores = {hit.instance_id: hit.score for hit in hits}
    ids, inverse = np.unique(instance, return_inverse=True)
    per_id = np.array([scores.get(int(i), 0.0) if i >= 0 else 0.0 for i in ids], dtype=np.float32)
    return per_id[inverse.reshape(-1)]


def render_view(run: RunScene, view: ViewPose, relevance: np.ndarray | None = None) -> ViewImages:
    """Render one view of the run's Gaussian scene (module docstring)."""
    import torch

    from panogs_core.gaussians.rasterizer import Gaussians3D, PinholeCamera, rasterize
    from panogs_core.gaussians.spherical_harmonics import sh_to_color

    g = run.gaussians
    cam = PinholeCamera.from_camera(view.camera, torch.as_tensor(view.T_world_cam))
    means = torch.as_tensor(g.means)
    gauss = Gaussians3D(
        means=means,
        quats=torch.as_tensor(g.quats),
        log_scales=torch.as_tensor(g.log_scales),
        opacity_logits=torch.as_tensor(g.opacity_logits),
    )
    centre = torch.as_tensor(view.T_world_cam[:3, 3], dtype=means.dtype)
    channels = [sh_to_color(torch.as_tensor(g.sh), means, centre, g.sh_degree)]
    if relevance is not None:
        channels.append(torch.as_tensor(relevance, dtype=means.dtype)[:, None])
    with torch.no_grad():
        out = rasterize(gauss, torch.cat(channels, dim=1), cam, with_top_index=True)
    feats = out.features.numpy()
    alpha = out.alpha.numpy()
    top = out.top_index.numpy() if out.top_index is not None else np.full(alpha.shape, -1)
    labelled = (top >= 0) & (alpha >= LABEL_MIN_ALPHA)
    pick = np.where(labelled, top, 0)
    semantic = np.where(labelled, run.semantic[pick], -1)
    instance = np.where(labelled, run.instance[pick], -1)
    rel = None
    if relevance is not None:
        rel = np.clip(feats[..., 3] / np.maximum(alpha, 1e-6) * (alpha > 0), 0, 1).astype(np.float32)
    return ViewImages(
        color=np.clip(np.round(feats[..., :3] * 255), 0, 255).astype(np.uint8),
        depth=out.depth.numpy().astype(np.float32),
        alpha=alpha.astype(np.float32),
        semantic=semantic.astype(np.int64),
        instance=instance.astype(np.int64),
        relevance=rel,
    )


def view_pngs(images: ViewImages, is_thing: np.ndarray) -> dict[str, bytes]:
    """PNG files of a view, by name: colour, depth (uint16 millimetres), depth_vis, semantic, instance,
    panoptic (the labels' colours over the colour) and, with a query, relevance (a colour map)."""
    import cv2

    from panogs_core.palette import class_colors, instance_colors, panoptic_colors

    def png(rgb_or_gray: np.ndarray) -> bytes:
        img = rgb_or_gray[..., ::-1] if rgb_or_gray.ndim == 3 else rgb_or_gray  # OpenCV writes BGR
        ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
        if not ok:
            raise InputError("render: PNG encoding failed")
        return bytes(buf)

    h, w = images.depth.shape
    flat_sem, flat_inst = images.semantic.reshape(-1), images.instance.reshape(-1)
    sem_rgb = class_colors(flat_sem).reshape(h, w, 3)
    sem_rgb[images.semantic < 0] = 0
    inst_rgb = instance_colors(flat_inst).reshape(h, w, 3)
    inst_rgb[images.instance < 0] = 0
    pan = panoptic_colors(flat_sem, flat_inst, is_thing).reshape(h, w, 3)
    labelled = (images.semantic >= 0)[..., None]
    blend = (1 - OVERLAY_WEIGHT) * images.color + OVERLAY_WEIGHT * pan
    overlay = np.where(labelled, blend, images.color).round().astype(np.uint8)
    depth_mm = np.clip(np.round(images.depth * 1000), 0, 65535).astype(np.uint16)
    finite = images.depth[images.depth > 0]
    far = float(np.percentile(finite, 99)) if finite.size else 1.0
    depth_vis = cv2.applyColorMap(np.clip(images.depth / far * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    depth_vis[images.depth <= 0] = 0
    files = {
        "color.png": png(images.color),
        "depth.png": png(depth_mm),
        "depth_vis.png": png(depth_vis[..., ::-1]),
        "semantic.png": png(sem_rgb),
        "instance.png": png(inst_rgb),
        "panoptic.png": png(overlay),
    }
    if images.relevance is not None:
        heat = cv2.applyColorMap(np.round(images.relevance * 255).astype(np.uint8), cv2.COLORMAP_JET)[..., ::-1]
        files["relevance.png"] = png(np.where((images.alpha > 0)[..., None], heat, 0).astype(np.uint8))
    return files


def render_to_dir(
    run_dir: str | Path,
    out_dir: str | Path,
    *,
    frame: str | None = None,
    pose: Any = None,
    pose_where: str = "pose",
    size: tuple[int, int] | None = None,
    query: str | None = None,
) -> dict[str, Path]:
    """Render one view of a run (by capture frame id or pose document) and write its PNGs into ``out_dir``."""
    root = Path(run_dir)
    if (frame is None) == (pose is None):
        raise InputError("render: give exactly one of a frame id or a pose")
    if frame is not None:
        view = view_from_frame(root, frame, size)
    else:
        camera, _ = run_camera(root)
        view = view_from_pose(pose, camera, size, pose_where)
    run = load_run_scene(root)
    relevance = instance_relevance(root, query, run.instance) if query else None
    files = view_pngs(render_view(run, view, relevance), run.is_thing)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = {}
    for name, data in files.items():
        (out / name).write_bytes(data)
        written[name] = out / name
    return written
