"""The bundle's hash, which every stage key starts from, and the name of the rule that makes it.

Light on purpose (no numpy): the worker reads a scene's kept hash (``worker/shared_checkpoints.py``) in processes
that must not load the numeric libraries before they size their thread pools (``panogs_core/threads.py``).
"""

from __future__ import annotations

import hashlib
from typing import TYPE_CHECKING

from panogs_core.pipeline.lane import background_turn

if TYPE_CHECKING:
    from panogs_core.io.bundle import Bundle

# What :func:`hash_bundle` covers, named, so that a hash kept beside a scene
# (``pipeline.run.SharedCheckpoints.known_input_hash``) is used only by code that would compute the same value.
HASH_RULE = "sha256:scene.json+frames+geometry+vocabulary+gt:v1"


def hash_bundle(scene: Bundle) -> str:
    """SHA-256 over ``scene.json`` and every file it references (streamed, 1 MiB chunks); ``HASH_RULE``.

    Maps computed by the 2D-maps stage (``scene.computed``) are not the bundle's files: their own key covers them
    (the ``maps_2d`` key of the stage table)."""
    digest = hashlib.sha256()
    paths = [scene.root / "scene.json"]
    computed = scene.computed
    for frame in scene.frames:
        features = None if computed is not None and computed.serves("features") else frame.features
        masks = None if computed is not None and computed.serves("masks") else frame.masks
        paths += [scene.root / p for p in (frame.depth, frame.color, features, masks) if p]
    for extra in ("geometry.ply", "vocabulary.json", "vocabulary.npy", "gt/labels.npz"):
        if (scene.root / extra).is_file():
            paths.append(scene.root / extra)
    for path in paths:
        with open(path, "rb") as fh:
            chunk = str(path.relative_to(scene.root)).encode()  # the file's name, then its bytes
            while chunk:
                with background_turn():  # a chunk at a time, in turns with the run's other background work
                    digest.update(chunk)
                    chunk = fh.read(1 << 20)
    return digest.hexdigest()
