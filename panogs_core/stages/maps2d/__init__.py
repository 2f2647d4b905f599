"""The 2D-maps stage (numpy entry): instance masks and language feature maps of the key frames, computed here.

For each key frame (docs/method.md §17): class-agnostic masks by a Segment-Anything-family model in automatic mode,
painted into one id map (0 = no mask, ids per frame), and a per-cell language feature map in the image tower's
space of a CLIP-family model, pooled per mask (:mod:`.masks`, :mod:`.features`, the torch half). The maps have the
bundle's conventions (docs/scene_format.md §1, §2.3), so the stages that read maps read these the same way.

Frames are streamed: one frame's image and maps are in memory at a time, each frame's maps are written as soon as
they are computed, and both models load once, before the first frame, so a model that cannot load fails the run
before any work. Progress is reported per frame; a callback that raises ``Cancelled`` stops between frames, and
a later call on the same folder with the same models and settings continues after the frames already written.

Checkpoint folder (``out_dir``)::

    manifest.json          format, models (identity hashes, space, dim), settings, key, frames written so far
    masks/<n>.png          16-bit single-channel id map, long side mask_long_side      (when a masks model ran)
    features/<n>.npy       (Hf, Wf, D) float16, unit rows, long side feature_long_side (when a features model ran)

``<n>`` is the frame's place in the manifest (six digits), not its id: a bundle's frame ids are any printable
text (a space or a slash included), which is no safe file name; the manifest maps each id to its files.

Importing this module imports no torch; :func:`compute_2d_maps` imports the torch half when it runs.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections.abc import Iterable, Sized
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.errors import InputError, ShapeError
from panogs_core.language.model_identity import (
    ModelLoadError,
    clip_space,
    model_hash,
    resolve_model_dir,
)
from panogs_core.progress import ProgressFn, report
from panogs_core.stages.maps2d.config import Maps2DConfig

__all__ = [
    "MANIFEST",
    "FrameImage",
    "MapModels",
    "Maps2DConfig",
    "Maps2DResult",
    "ModelIdentity",
    "ModelLoadError",
    "compute_2d_maps",
    "identify_models",
]

FORMAT_ID = "panogs-maps2d/1"
MANIFEST = "manifest.json"


@dataclass(frozen=True)
class MapModels:
    """The models a run computes missing 2D maps with: a folder (Hugging Face layout) or a hub name each.

    None: that kind of map comes from the bundle (a bundle without it then fails the run at once, naming the
    option to pass). A kind the bundle brings is never recomputed: the bundle's maps are the scene's.
    ``allow_download`` lets a hub name missing from the local cache be fetched (never a folder).
    """

    masks: str | None = None
    features: str | None = None
    allow_download: bool = False


@dataclass(frozen=True)
class FrameImage:
    """One key frame's input: its id, its colour image and, for a features-only run, its own mask id map."""

    id: str  # becomes a file name: letters, digits, '.', '_', '-', at most 128 characters
    color: np.ndarray  # (H, W, 3) uint8 RGB
    masks: np.ndarray | None = None  # (Hm, Wm) integer id map, 0 = no mask; required when no masks model runs


@dataclass(frozen=True)
class ModelIdentity:
    """What identifies a model in a checkpoint key: a hash of its files, never its path."""

    kind: str  # "masks" or "features"
    sha256: str  # panogs_core.language.model_identity.model_hash of its folder
    space: str | None = None  # features only: the feature space it writes (features.space of the scene)


@dataclass(frozen=True)
class FrameMaps:
    """One frame's files in the checkpoint folder (relative to it) and its mask count."""

    id: str
    masks: str | None
    features: str | None
    mask_count: int


@dataclass(frozen=True)
class Maps2DResult:
    """The checkpoint folder's manifest: the models, the settings, the frames written."""

    root: Path
    key: str  # hex SHA-256 of the models' identities and the settings (frames excluded: they accumulate)
    masks_model: ModelIdentity | None
    features_model: ModelIdentity | None
    feature_dim: int | None
    settings: dict[str, Any]
    frames: tuple[FrameMaps, ...] = field(default_factory=tuple)
    complete: bool = False

    def serves(self, kind: str) -> bool:
        """Whether these maps hold ``kind`` (``masks`` or ``features``): its model ran."""
        return (self.masks_model if kind == "masks" else self.features_model) is not None

    @property
    def space(self) -> str | None:
        """``features.space`` of the feature maps, None without a features model."""
        return self.features_model.space if self.features_model else None

    def read_masks(self, frame_id: str) -> np.ndarray:  # (Hm, Wm) uint16
        """A frame's mask id map."""
        import cv2

        entry = self._entry(frame_id)
        if entry.masks is None:
            raise InputError(f"{self.root}: frame {frame_id!r} has no mask map here (no masks model ran)")
        image = cv2.imread(str(self.root / entry.masks), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise InputError(f"{self.root / entry.masks}: unreadable")
        return image

    def read_features(self, frame_id: str) -> np.ndarray:  # (Hf, Wf, D) float16
        """A frame's feature map."""
        entry = self._entry(frame_id)
        if entry.features is None:
            raise InputError(f"{self.root}: frame {frame_id!r} has no feature map here (no features model ran)")
        return np.load(self.root / entry.features, allow_pickle=False)

    def _entry(self, frame_id: str) -> FrameMaps:
        for entry in self.frames:
            if entry.id == frame_id:
                return entry
        raise InputError(f"{self.root}: no frame {frame_id!r} in {MANIFEST}")

    def save(self) -> None:
        """Write ``manifest.json`` atomically (a crash leaves the previous one)."""
        doc = {
            "format": FORMAT_ID,
            "key": self.key,
            "masks_model": asdict(self.masks_model) if self.masks_model else None,
            "features_model": asdict(self.features_model) if self.features_model else None,
            "feature_dim": self.feature_dim,
            "settings": self.settings,
            "frames": [asdict(f) for f in self.frames],
            "complete": self.complete,
        }
        _write_atomic(self.root / MANIFEST, json.dumps(doc, indent=1).encode())

    @classmethod
    def load(cls, root: str | Path) -> Maps2DResult:
        """Read a checkpoint folder's manifest.

        Raises:
            InputError: no manifest, or not this format.
        """
        root = Path(root)
        try:
            doc = json.loads((root / MANIFEST).read_text())
        except (OSError, ValueError) as exc:
            raise InputError(f"{root / MANIFEST}: unreadable: {exc}") from exc
        if not isinstance(doc, dict) or doc.get("format") != FORMAT_ID:
            raise InputError(f"{root / MANIFEST}: not a {FORMAT_ID} manifest")
        masks, feats = doc["masks_model"], doc["features_model"]
        return cls(
            root=root,
            key=doc["key"],
            masks_model=ModelIdentity(**masks) if masks else None,
            features_model=ModelIdentity(**feats) if feats else None,
            feature_dim=doc["feature_dim"],
            settings=doc["settings"],
            frames=tuple(FrameMaps(**f) for f in doc["frames"]),
            complete=bool(doc["complete"]),
        )


def identify_models(
    masks_model: str | Path | None,
    features_model: str | Path | None,
    *,
    allow_download: bool = False,
) -> tuple[ModelIdentity | None, ModelIdentity | None]:
    """The identities of the models a run would load (hashes of their files, the features' space), without
    loading them or importing torch: what a pipeline needs to key the checkpoint before it runs the stage.

    Raises:
        ModelLoadError: a model's folder is missing or incomplete, naming it and what is missing.
    """
    masks = None
    if masks_model is not None:
        masks = ModelIdentity("masks", model_hash(resolve_model_dir(masks_model, allow_download=allow_download)))
    feats = None
    if features_model is not None:
        folder = resolve_model_dir(features_model, allow_download=allow_download)
        feats = ModelIdentity("features", model_hash(folder, with_tokenizer=True), clip_space(folder))
    return masks, feats


def checkpoint_key(
    masks: ModelIdentity | None, features: ModelIdentity | None, cfg: Maps2DConfig
) -> str:  # hex SHA-256
    """The key of a checkpoint folder's contents: the models' identities and the settings their maps depend on."""
    doc = {
        "format": FORMAT_ID,
        "masks": asdict(masks) if masks else None,
        "features": asdict(features) if features else None,
        "settings": _settings(cfg, masks, features),
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def compute_2d_maps(
    frames: Iterable[FrameImage],
    out_dir: str | Path,
    cfg: Maps2DConfig | None = None,
    *,
    masks_model: str | Path | None = None,
    features_model: str | Path | None = None,
    allow_download: bool = False,
    total: int | None = None,
    on_progress: ProgressFn | None = None,
) -> Maps2DResult:
    """Compute and write the mask and feature maps of key frames, one frame at a time.

    Args:
        frames: The key frames, streamed (a generator is fine; only one frame is held at a time).
        out_dir: The checkpoint folder (created; a manifest with another key is replaced, one with the same key
            is continued: frames already written are skipped).
        cfg: Settings; default ``Maps2DConfig()``.
        masks_model: Folder (Hugging Face layout) or hub name of a SAM-family model; None: the frames bring their
            own masks (``FrameImage.masks``) and only features are computed.
        features_model: Folder or hub name of a CLIP model; None: masks only.
        allow_download: Let a hub name missing from the local cache be fetched (never for folders).
        total: The number of frames, for progress, when ``frames`` has no ``len``.
        on_progress: Called as ``on_progress(done, total)`` after each frame; may raise ``Cancelled``.

    Returns:
        The manifest of the folder, ``complete`` when every frame was written.

    Raises:
        ModelLoadError: a model does not load (before any frame is read), naming it and what is missing.
        InputError: neither model given, a bad or repeated frame id, a frame without the masks a
            features-only run needs.
        ShapeError: a colour image that is not ``(H, W, 3)`` uint8.
    """
    cfg = cfg or Maps2DConfig()
    if masks_model is None and features_model is None:
        raise InputError("compute_2d_maps: neither masks_model nor features_model given; nothing to compute")
    masks_id, feats_id = identify_models(masks_model, features_model, allow_download=allow_download)
    from panogs_core.stages.maps2d import runner  # the torch half, imported only to run

    models = runner.load_models(
        resolve_model_dir(masks_model, allow_download=allow_download) if masks_model is not None else None,
        resolve_model_dir(features_model, allow_download=allow_download) if features_model is not None else None,
        cfg,
    )
    result = _start(Path(out_dir), masks_id, feats_id, models.feature_dim, cfg)
    done = {f.id for f in result.frames}
    count = total if total is not None else (len(frames) if isinstance(frames, Sized) else 0)
    entries = list(result.frames)
    seen: set[str] = set()
    with runner.threads(cfg):
        for frame in frames:
            _check_frame(frame, seen, need_masks=masks_model is None)
            if frame.id not in done:
                maps = runner.process_frame(models, frame.color, frame.masks, cfg)
                entries.append(_write_frame(result.root, frame.id, len(entries), maps))
                result = _replace_frames(result, entries, complete=False)
                result.save()
            report(on_progress, len(seen), max(count, len(seen)))
    result = _replace_frames(result, entries, complete=True)
    result.save()
    return result


def _settings(cfg: Maps2DConfig, masks: ModelIdentity | None, features: ModelIdentity | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if masks is not None:
        out.update(cfg.mask_settings())
    if features is not None:
        out.update(cfg.feature_settings())
    return out


def _start(
    root: Path, masks: ModelIdentity | None, feats: ModelIdentity | None, dim: int | None, cfg: Maps2DConfig
) -> Maps2DResult:
    """The folder's manifest to continue, or a fresh one (an old one with another key and its maps removed)."""
    key = checkpoint_key(masks, feats, cfg)
    if (root / MANIFEST).is_file():
        try:
            old = Maps2DResult.load(root)
        except (InputError, KeyError, TypeError):
            old = None
        if old is not None and old.key == key:
            present = tuple(f for f in old.frames if _files_present(root, f))
            return _replace_frames(old, list(present), complete=False)
    for sub in ("masks", "features"):
        shutil.rmtree(root / sub, ignore_errors=True)
    root.mkdir(parents=True, exist_ok=True)
    fresh = Maps2DResult(root, key, masks, feats, dim, _settings(cfg, masks, feats))
    fresh.save()
    return fresh


def _files_present(root: Path, entry: FrameMaps) -> bool:
    return all(rel is None or (root / rel).is_file() for rel in (entry.masks, entry.features))


def _replace_frames(result: Maps2DResult, entries: list[FrameMaps], *, complete: bool) -> Maps2DResult:
    return Maps2DResult(
        result.root,
        result.key,
        result.masks_model,
        result.features_model,
        result.feature_dim,
        result.settings,
        tuple(entries),
        complete,
    )


def _check_frame(frame: FrameImage, seen: set[str], *, need_masks: bool) -> None:
    if not isinstance(frame.id, str) or not frame.id or not frame.id.isprintable():
        raise InputError(f"frame id {frame.id!r}: expected non-empty printable text (the bundle's rule)")
    if frame.id in seen:
        raise InputError(f"frame id {frame.id!r} appears twice")
    seen.add(frame.id)
    color = frame.color
    if not isinstance(color, np.ndarray) or color.dtype != np.uint8 or color.ndim != 3 or color.shape[2] != 3:
        what = f"{color.dtype} {color.shape}" if isinstance(color, np.ndarray) else type(color).__name__
        raise ShapeError(f"frame {frame.id}: colour {what}, expected (H, W, 3) uint8 RGB")
    if need_masks:
        masks = frame.masks
        if masks is None:
            raise InputError(
                f"frame {frame.id}: no mask map, and no masks model was given to compute one (features-only run)"
            )
        if masks.ndim != 2 or not np.issubdtype(masks.dtype, np.integer) or (masks.size and masks.min() < 0):
            raise ShapeError(f"frame {frame.id}: masks {masks.dtype} {masks.shape}, expected a 2D id map >= 0")


def _write_frame(root: Path, frame_id: str, place: int, maps: Any) -> FrameMaps:
    """Write one frame's maps (each file atomically, named by its ``place`` in the manifest) and return its
    manifest entry."""
    import cv2

    masks_rel = features_rel = None
    if maps.masks is not None:
        masks_rel = f"masks/{place:06d}.png"
        ok, data = cv2.imencode(".png", maps.masks.astype(np.uint16), [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:  # pragma: no cover - OpenCV encodes any uint16 array
            raise InputError(f"{root / masks_rel}: PNG encoding failed")
        _write_atomic(root / masks_rel, data.tobytes())
    if maps.features is not None:
        features_rel = f"features/{place:06d}.npy"
        target = root / features_rel
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(target.name + ".tmp")
        with open(tmp, "wb") as fh:
            np.save(fh, np.ascontiguousarray(maps.features, dtype=np.float16), allow_pickle=False)
        os.replace(tmp, target)
    return FrameMaps(frame_id, masks_rel, features_rel, int(maps.mask_count))


def _write_atomic(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)
