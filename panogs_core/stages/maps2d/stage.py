"""The 2D-maps stage of a run: the kinds of map a bundle lacks, computed from its colour frames, and the bundle
seen with them (docs/method.md §17).

A kind the bundle brings is its own and is never recomputed; a kind it lacks is computed by the model the caller
names (:class:`~panogs_core.stages.maps2d.MapModels`) for every frame with a colour image. The maps go to a
checkpoint folder under the run's ``stages/maps_2d/``, named by a key of the frame ids, the models' identities
(hashes of their files, not their paths) and the settings the maps depend on: a re-run that changes any other
setting finds the folder complete and loads no model, and with a shared store (the service's, per scene) the
scene's other jobs fetch the folder, packed as one archive, instead of computing it. The bundle returned serves the
computed maps through :attr:`Bundle.computed <panogs_core.io.bundle.Bundle>`, so the stages after it read them as
the bundle's own.

Importing this module imports no torch (the computation imports it when it runs).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import shutil
import tarfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Protocol

from panogs_core.errors import InputError
from panogs_core.io.bundle import Bundle
from panogs_core.progress import ProgressFn
from panogs_core.stages.maps2d import (
    MANIFEST,
    FrameImage,
    MapModels,
    Maps2DConfig,
    Maps2DResult,
    checkpoint_key,
    compute_2d_maps,
    identify_models,
)
from panogs_core.types import Frame

log = logging.getLogger(__name__)

MAPS_FOLDER = "maps_2d"  # under the run's stages/: one folder per key

# What each kind of map needs from the caller when the bundle lacks it: the ``panogs run`` option and the model.
_OPTION = {"masks": "--masks-model (a Segment Anything model)", "features": "--features-model (a CLIP model)"}


class SharedFolders(Protocol):
    """What this stage uses of a run's shared checkpoints (``panogs_core.pipeline.checkpoints.SharedCheckpoints``):
    a miss in ``fetch`` makes this run the one that computes the key, and it stores what it computed."""

    def fetch(self, stage: str, key: str, dest: Path) -> bool: ...

    def store(self, stage: str, key: str, path: Path) -> None: ...


def forget_maps(checkpoints: Path) -> None:
    """Remove the computed maps under a run's ``stages/`` (a run that must recompute every stage)."""
    shutil.rmtree(checkpoints / MAPS_FOLDER, ignore_errors=True)


def missing_kinds(bundle: Bundle) -> tuple[str, ...]:
    """The kinds of map no frame of the bundle brings (``masks``, ``features``)."""
    kinds = (("masks", bundle.mask_frames), ("features", bundle.feature_frames))
    return tuple(kind for kind, frames in kinds if not frames)


def with_computed_maps(
    bundle: Bundle,
    checkpoints: Path,
    cfg: Maps2DConfig,
    models: MapModels | None,
    progress: ProgressFn,
    *,
    shared: SharedFolders | None = None,
    on_reused: Callable[[], None] | None = None,
) -> Bundle:
    """The bundle with the kinds it lacks computed (the bundle itself when it lacks none).

    Args:
        bundle: The validated bundle.
        checkpoints: The run's ``stages/`` folder; the maps go to ``maps_2d/<key>/`` in it.
        cfg: The stage's settings.
        models: The models that compute the missing kinds.
        progress: ``progress(done, total)`` per frame; may raise ``Cancelled`` (between frames).
        shared: Checkpoints kept beyond the run folder: the maps' folder is fetched from there when this run
            lacks it, and stored there when this run computes it.
        on_reused: Called when the maps were not computed but found complete (here or in ``shared``).

    Raises:
        InputError: a missing kind without a model to compute it (naming the option to pass), or no frame that
            can get maps.
        ModelLoadError: a model does not load, before any frame is computed.
    """
    missing = missing_kinds(bundle)
    if not missing:
        return bundle
    models = models or MapModels()
    named = {"masks": models.masks, "features": models.features}
    unnamed = [kind for kind in missing if named[kind] is None]
    if unnamed:
        raise InputError(
            f"{bundle.root / 'scene.json'}: the bundle has no {' nor '.join(_noun(k) for k in unnamed)}; pass "
            + " and ".join(_OPTION[k] for k in unnamed)
            + " to compute them from the colour frames (a folder or a hub name; README, 'From your own capture')"
        )
    masks_model = models.masks if "masks" in missing else None
    features_model = models.features if "features" in missing else None
    frames = _frames_to_compute(bundle, need_own_masks=masks_model is None, stride=cfg.frame_stride)
    masks_id, feats_id = identify_models(masks_model, features_model, allow_download=models.allow_download)
    ids = [f.id for f in frames]
    content_key = checkpoint_key(masks_id, feats_id, cfg)
    key = _folder_key(content_key, ids)
    folder = checkpoints / MAPS_FOLDER / key
    result = _complete(folder, content_key, ids)
    lease_held = False
    if result is None and shared is not None:
        lease_held = not shared.fetch(MAPS_FOLDER, key, _archive(folder))
        if not lease_held:
            result = _unpacked(folder, content_key, ids)
    if result is None:
        result = compute_2d_maps(
            _images(bundle, frames, own_masks=masks_model is None),
            folder,
            cfg,
            masks_model=masks_model,
            features_model=features_model,
            allow_download=models.allow_download,
            total=len(frames),
            on_progress=progress,
        )
        if shared is not None and lease_held:
            _share(shared, folder)
    else:
        log.info("maps_2d: the maps of %d frames are in %s already", len(ids), folder)
        if on_reused is not None:
            on_reused()
    return _view(bundle, result)


def _archive(folder: Path) -> Path:
    """Where a maps folder travels to and from a shared store as one file (beside the folder)."""
    return folder.with_name(f"{folder.name}.tar")


def _share(shared: SharedFolders, folder: Path) -> None:
    """Store the computed folder in ``shared`` as one archive (the store keeps whole files, one per key)."""
    archive = _archive(folder)
    tmp = archive.with_name(f".{archive.name}.tmp")
    with tarfile.open(tmp, "w") as tar:
        for path in sorted(p for p in folder.rglob("*") if p.is_file()):
            tar.add(path, arcname=path.relative_to(folder).as_posix())
    tmp.replace(archive)
    shared.store(MAPS_FOLDER, folder.name, archive)
    archive.unlink()  # the store has its own copy (or link); the run folder keeps the unpacked maps


def _unpacked(folder: Path, maps_key: str, frame_ids: list[str]) -> Maps2DResult | None:
    """The maps of an archive fetched from a shared store, unpacked into ``folder``; None when they are not
    complete for this key and these frames (then this run computes them)."""
    archive = _archive(folder)
    shutil.rmtree(folder, ignore_errors=True)
    try:
        with tarfile.open(archive) as tar:
            tar.extractall(folder, filter="data")  # plain files inside the folder only
    except (tarfile.TarError, OSError) as exc:
        log.warning("maps_2d: the shared maps %s could not be unpacked (%s); computing them", archive, exc)
        shutil.rmtree(folder, ignore_errors=True)
        return None
    finally:
        archive.unlink(missing_ok=True)
    return _complete(folder, maps_key, frame_ids)


def _noun(kind: str) -> str:
    return "masks" if kind == "masks" else "feature maps"


def _frames_to_compute(bundle: Bundle, *, need_own_masks: bool, stride: int = 1) -> list[Frame]:
    """The frames that get computed maps: those with a colour image (and their own masks for features only), then
    every ``stride``-th of them from the first (``maps2d.frame_stride``); the others keep no map of the kinds
    computed, which the stages after this one read as non-key frames."""
    frames = [f for f in bundle.frames if f.color is not None and (f.masks is not None or not need_own_masks)]
    if not frames:
        need = "a colour image and masks" if need_own_masks else "a colour image"
        raise InputError(f"{bundle.root / 'scene.json'}: no frame has {need} to compute 2D maps from")
    return frames[::stride]


def _images(bundle: Bundle, frames: list[Frame], *, own_masks: bool) -> Iterator[FrameImage]:
    """The frames' inputs, one at a time (the stage holds one image at a time)."""
    for frame in frames:
        color = bundle.read_color(frame)
        assert color is not None  # _frames_to_compute keeps frames with colour
        yield FrameImage(frame.id, color, bundle.read_masks(frame) if own_masks else None)


def _folder_key(maps_key: str, frame_ids: list[str]) -> str:
    """The checkpoint folder's name: the maps' key and the frames they are computed for."""
    blob = json.dumps([maps_key, frame_ids]).encode()
    return hashlib.sha256(blob).hexdigest()[:20]


def _complete(folder: Path, maps_key: str, frame_ids: list[str]) -> Maps2DResult | None:
    """The folder's maps when they are complete for these frames and this key (no model is then loaded)."""
    if not (folder / MANIFEST).is_file():
        return None
    try:
        result = Maps2DResult.load(folder)
    except (InputError, KeyError, TypeError):
        return None
    if not result.complete or result.key != maps_key or [f.id for f in result.frames] != frame_ids:
        return None
    return result


def _view(bundle: Bundle, result: Maps2DResult) -> Bundle:
    """The bundle whose missing kinds are served by ``result`` (frame paths relative to its folder)."""
    by_id = {entry.id: entry for entry in result.frames}
    frames = []
    for frame in bundle.frames:
        entry = by_id.get(frame.id)
        masks = entry.masks if entry is not None and result.serves("masks") else frame.masks
        features = entry.features if entry is not None and result.serves("features") else frame.features
        if result.serves("masks") and entry is None:
            masks = None
        if result.serves("features") and entry is None:
            features = None
        frames.append(dataclasses.replace(frame, masks=masks, features=features))
    changes: dict[str, object] = {"frames": tuple(frames), "computed": result}
    if result.serves("features"):
        assert result.space is not None
        assert result.feature_dim is not None
        changes.update(feature_space=result.space, feature_dim=result.feature_dim)
    return dataclasses.replace(bundle, **changes)  # type: ignore[arg-type]


def maps_key(bundle: Bundle) -> str:
    """What the keys of the stages reading maps take from the computed maps: their folder's key ("bundle" when
    every map is the bundle's, which the bundle's own hash covers)."""
    computed = bundle.computed
    if isinstance(computed, Maps2DResult):
        return computed.root.name
    return "bundle"
