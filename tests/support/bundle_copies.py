"""Copies of a test bundle with parts taken out: the inputs of the runs that compute 2D maps."""

from __future__ import annotations

import json
import shutil
from pathlib import Path


def without_maps(bundle: Path, dst: Path, kinds: tuple[str, ...] = ("masks", "features")) -> Path:
    """A copy of ``bundle`` at ``dst`` whose frames bring none of ``kinds`` (``masks``, ``features``): with both,
    posed RGB-D alone (the vocabulary and the ground truth, which name the features' space, go too)."""
    shutil.copytree(bundle, dst)
    doc = json.loads((dst / "scene.json").read_text())
    for frame in doc["frames"]:
        for kind in kinds:
            frame.pop(kind, None)
    if "features" in kinds:
        doc.pop("features", None)
    (dst / "scene.json").write_text(json.dumps(doc))
    for kind in kinds:
        shutil.rmtree(dst / kind)
    if set(kinds) == {"masks", "features"}:
        shutil.rmtree(dst / "gt", ignore_errors=True)
        for name in ("vocabulary.json", "vocabulary.npy"):
            (dst / name).unlink(missing_ok=True)
    return dst
