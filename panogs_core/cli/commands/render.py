"""``panogs render``: PNG views of a finished run's Gaussian scene (panogs_core/gaussians/views.py)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


def add_command(sub: Any) -> None:
    """Add ``render`` to an argparse subparsers object."""
    p = sub.add_parser("render", help="render a view of a run: colour, depth, semantic, instance, query relevance")
    p.add_argument("run", help="the --out folder of a run")
    view = p.add_mutually_exclusive_group(required=True)
    view.add_argument(
        "--frame",
        help="a frame id of the capture (its pose and the run's camera): any bundle frame, or one the import's "
        "stride or key-frame rule left out (cameras.json lists them all)",
    )
    view.add_argument("--pose", metavar="FILE.json", help='{"T_world_cam": 4x4 camera-to-world[, "camera": {...}]}')
    p.add_argument("--size", metavar="WxH", help="render size (same field of view), e.g. 640x480")
    p.add_argument("--query", nargs="+", metavar="TEXT", help="also write relevance.png for this text")
    p.add_argument("--out", required=True, help="output folder for the PNGs")
    p.set_defaults(func=run_render)


def run_render(args: argparse.Namespace) -> int:
    """Render the view and name the PNGs written."""
    from panogs_core.errors import InputError
    from panogs_core.gaussians.views import parse_size, render_to_dir

    pose = None
    if args.pose:
        try:
            pose = json.loads(Path(args.pose).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"--pose {args.pose}: cannot read a JSON pose ({exc})") from exc
    size = parse_size(args.size) if args.size else None
    query = " ".join(args.query) if args.query else None
    written = render_to_dir(
        args.run, args.out, frame=args.frame, pose=pose, pose_where=args.pose or "pose", size=size, query=query
    )
    print(f"wrote {', '.join(sorted(written))} to {args.out}")
    return 0
