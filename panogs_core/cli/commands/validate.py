"""``panogs validate``: check a bundle against the format; every problem is listed, each naming file, field and
value (the bundle reader's :class:`~panogs_core.errors.PanoGSError`, printed by ``main``)."""

from __future__ import annotations

import argparse
from typing import Any


def add_command(sub: Any) -> None:
    """Add ``validate`` to an argparse subparsers object."""
    p = sub.add_parser("validate", help="check a bundle against the format and list every problem")
    p.add_argument("bundle")
    p.set_defaults(func=run_validate)


def run_validate(args: argparse.Namespace) -> int:
    """Open the bundle (which validates it) and print one line on what it holds."""
    from panogs_core.io.bundle import open_bundle

    scene = open_bundle(args.bundle)
    print(
        f"{args.bundle}: valid {scene.name}: {len(scene.frames)} frames "
        f"({len(scene.feature_frames)} with features, {len(scene.mask_frames)} with masks), "
        f"camera {scene.camera.width}x{scene.camera.height}, features {scene.feature_dim}-d "
        f"{scene.feature_space}, geometry {'yes' if scene.has_geometry else 'no (TSDF)'}, "
        f"ground truth {'yes' if scene.has_ground_truth else 'no'}"
    )
    return 0
