"""``panogs synth``: a synthetic scene bundle (a room, or a building of rooms) with known answers."""

from __future__ import annotations

import argparse
from typing import Any


def add_command(sub: Any) -> None:
    """Add ``synth`` to an argparse subparsers object."""
    p = sub.add_parser("synth", help="make a synthetic scene bundle")
    p.add_argument("out", help="output bundle folder")
    p.add_argument("--preset", default="tiny", choices=["tiny", "small", "default", "large", "scan", "building"])
    p.add_argument(
        "--rooms",
        type=_room_grid,
        default=(2, 2),
        metavar="N|NxM",
        help="building only: rooms along x and y (N: N x N; default 2)",
    )
    p.add_argument(
        "--room-preset",
        default="large",
        choices=["tiny", "small", "default", "large"],
        help="building only: the kind of each room (default large)",
    )
    p.add_argument("--difficulty", default="default", choices=["easy", "default", "hard"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--space",
        default=None,
        choices=["minilm-l6", "clip-vit-b32"],
        help="feature space of the 2D features (default: the preset's; large is clip-vit-b32)",
    )
    p.add_argument("--no-geometry", action="store_true", help="omit geometry.ply (primitives by TSDF)")
    p.set_defaults(func=run_synth)


def run_synth(args: argparse.Namespace) -> int:
    """Write the scene or the building and say what was written."""
    from panogs_core.synthetic import make_building, make_scene

    if args.preset == "building":
        path = make_building(
            args.out,
            rooms=args.rooms,
            room=args.room_preset,
            difficulty=args.difficulty,
            seed=args.seed,
            feature_space=args.space,
            with_geometry=not args.no_geometry,
        )
        rooms = f"{args.rooms[0]}x{args.rooms[1]} {args.room_preset} rooms"
        print(f"wrote synthetic building ({rooms}, {args.difficulty}, seed {args.seed}) to {path}")
        return 0
    path = make_scene(
        args.out,
        preset=args.preset,
        difficulty=args.difficulty,
        seed=args.seed,
        feature_space=args.space,
        with_geometry=not args.no_geometry,
    )
    print(f"wrote synthetic scene ({args.preset}, {args.difficulty}, seed {args.seed}) to {path}")
    return 0


def _room_grid(text: str) -> tuple[int, int]:
    parts = text.split("x")
    if len(parts) in (1, 2) and all(p.isdigit() and 1 <= int(p) <= 16 for p in parts):
        return (int(parts[0]), int(parts[-1]))
    raise argparse.ArgumentTypeError(f"expected N or NxM rooms (1-16 each), got {text!r}")
