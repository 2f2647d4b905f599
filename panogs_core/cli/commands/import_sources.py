"""The capture layouts ``panogs import`` converts: one :class:`ImportSource` per layout in :data:`IMPORT_SOURCES`.

Each entry becomes the subcommand ``panogs import <name> SRC DST``, with the options every source shares
(``--stride``, ``--vocabulary``, ``--feature-space``, added by the command), the source's own options (its
``add_options``) and its example under ``--help``. A new layout is one importer module under
``panogs_core/io/importers/`` and one entry here: two functions and the entry.

The capture importers (nerfstudio, Record3D, TUM RGB-D) declare their options once, as data
(:data:`~panogs_core.io.importers.source_cli.CAPTURE_CLIS`); :func:`capture_source` turns each into an entry, so
that their options are not written a second time here.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import TYPE_CHECKING, Any

from panogs_core.io.importers.source_cli import CAPTURE_CLIS, CliOption, SourceCli

if TYPE_CHECKING:
    from panogs_core.io.importers.capture import CaptureReport
    from panogs_core.io.importers.common import ImportReport
    from panogs_core.types import Vocabulary


@dataclass(frozen=True)
class ImportSource:
    """One layout of ``panogs import``.

    Attributes:
        name: The subcommand, ``panogs import <name> SRC DST``; lower case, one word.
        help: One line for ``panogs import --help`` and the top of ``panogs import <name> --help``.
        example: A whole command line, ``panogs import <name> ...``, shown under the subcommand's help.
        add_options: Adds the source's own options to its parser (``SRC``, ``DST`` and the shared options are
            there already); their values reach ``run`` as attributes of ``args``.
        run: Converts ``args.src`` into a bundle at ``args.dst`` and returns the importer's report (anything
            with a ``summary()``). Called with the parsed arguments and the vocabulary of ``--vocabulary`` (read
            and checked; None without it). It imports its importer inside, so that ``panogs --help`` loads no
            numeric library.
        description: More of the subcommand's help, after ``help`` (units, axes, what is refused); may be empty.
    """

    name: str
    help: str
    example: str
    add_options: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace, Vocabulary | None], ImportReport | CaptureReport]
    description: str = ""


def add_geometry_options(p: argparse.ArgumentParser) -> None:
    """``--geometry`` and ``--gt``, for the layouts whose scans come with a mesh and annotations."""
    p.add_argument("--geometry", metavar="MESH.ply", help="mesh or point cloud whose vertices become the primitives")
    p.add_argument(
        "--gt",
        metavar="FILE",
        help="ground truth for evaluation: .npz (semantic, instance[, points]) or ScanNet's "
        "<scene>_vh_clean_2.labels.ply (+ aggregation.json and segs.json beside it; vocabulary scannet20)",
    )


def _shared_arguments(args: argparse.Namespace, vocabulary: Vocabulary | None) -> dict[str, Any]:
    """The keyword arguments every research importer takes: the options the command adds to every source."""
    return {"stride": args.stride, "vocabulary": vocabulary, "feature_space": args.feature_space}


def _run_scannet(args: argparse.Namespace, vocabulary: Vocabulary | None) -> ImportReport:
    from panogs_core.io.importers.scannet import import_scannet

    shared = _shared_arguments(args, vocabulary)
    return import_scannet(args.src, args.dst, geometry=args.geometry, ground_truth=args.gt, **shared)


def _add_replica_options(p: argparse.ArgumentParser) -> None:
    add_geometry_options(p)
    p.add_argument(
        "--depth-scale",
        type=float,
        default=6553.5,
        metavar="VALUE",
        help="depth PNG value per metre (default: NICE-SLAM's 6553.5)",
    )


def _run_replica(args: argparse.Namespace, vocabulary: Vocabulary | None) -> ImportReport:
    from panogs_core.io.importers.replica import import_replica

    shared = _shared_arguments(args, vocabulary)
    return import_replica(
        args.src, args.dst, geometry=args.geometry, ground_truth=args.gt, depth_scale=args.depth_scale, **shared
    )


def _add_sevenscenes_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--features", metavar="DIR", help="folder of <i>.npy feature maps")
    p.add_argument("--masks", metavar="DIR", help="folder of <i>.png instance masks")
    p.add_argument(
        "--placeholder-maps",
        action="store_true",
        help="without --features: a constant feature map and a one-segment mask on the first frame, enough to "
        "open the bundle for the photometric benchmark (no meaningful labels)",
    )


def _run_sevenscenes(args: argparse.Namespace, vocabulary: Vocabulary | None) -> ImportReport:
    from panogs_core.io.importers.sevenscenes import import_sevenscenes

    shared = _shared_arguments(args, vocabulary)
    maps = {"features": args.features, "masks": args.masks, "placeholder_maps": args.placeholder_maps}
    return import_sevenscenes(args.src, args.dst, **maps, **shared)


# The options ``panogs import`` adds to every source itself (import_.add_command): a capture source's entry for
# the same flag is not added again, and its value is read from the command's own destination.
COMMAND_OPTIONS = {"--stride": "stride", "--feature-space": "feature_space", "--vocabulary": "vocabulary"}
_TYPES: dict[str, Callable[[str], Any]] = {"int": int, "float": float, "str": str, "path": str}
_METAVARS = {"int": "N", "float": "VALUE", "str": "NAME", "path": "PATH"}


def _dest(option: CliOption) -> str:
    """Where the parsed value of a capture option lands in ``args`` (its field, dots as ``__``)."""
    return COMMAND_OPTIONS.get(option.flag) or option.field.replace(".", "__")


def add_capture_options(cli: SourceCli, p: argparse.ArgumentParser) -> None:
    """The options of a capture source's table entry, but those the command adds to every source."""
    for option in cli.options:
        if option.flag in COMMAND_OPTIONS:
            continue
        if option.kind in ("switch", "switch_off"):
            action = "store_true" if option.kind == "switch" else "store_false"
            p.add_argument(option.flag, dest=_dest(option), action=action, default=option.default, help=option.help)
            continue
        default = "" if option.default is None else " (default %(default)s)"
        p.add_argument(
            option.flag,
            dest=_dest(option),
            type=_TYPES[option.kind],
            default=option.default,
            choices=list(option.choices) or None,
            metavar=None if option.choices else _METAVARS[option.kind],
            help=option.help + default,
        )


def run_capture(cli: SourceCli, args: argparse.Namespace, vocabulary: Vocabulary | None) -> CaptureReport:
    """Build the source's options from the parsed values and run its importer."""
    from panogs_core.io.importers.sources import CAPTURE_SOURCES, options_from_values

    source = CAPTURE_SOURCES[cli.name]
    values = {option.field: getattr(args, _dest(option)) for option in cli.options}
    values["maps.vocabulary"] = vocabulary  # resolved by the command from a name or a file
    return source.run(args.src, args.dst, options_from_values(source.options, values))


def capture_source(cli: SourceCli) -> ImportSource:
    """The entry of a capture importer, from its text in the importers' table."""
    return ImportSource(
        name=cli.name,
        help=cli.help,
        example=cli.example,
        add_options=partial(add_capture_options, cli),
        run=partial(run_capture, cli),
        description=cli.description,
    )


IMPORT_SOURCES: tuple[ImportSource, ...] = (
    ImportSource(
        name="scannet",
        help="a ScanNet export (SensReader: color/, depth/, pose/, intrinsic/; optional features/, masks/)",
        example="panogs import scannet scans/scene0000_00 bundles/scene0000_00 --vocabulary scannet20 "
        "--geometry scans/scene0000_00/scene0000_00_vh_clean_2.ply "
        "--gt scans/scene0000_00/scene0000_00_vh_clean_2.labels.ply",
        add_options=add_geometry_options,
        run=_run_scannet,
    ),
    ImportSource(
        name="replica",
        help="a Replica scene in the NICE-SLAM layout (results/frame*.jpg, results/depth*.png, traj.txt)",
        example="panogs import replica Replica/room0 bundles/room0 --vocabulary matterport21 --geometry room0_mesh.ply",
        add_options=_add_replica_options,
        run=_run_replica,
    ),
    ImportSource(
        name="sevenscenes",
        help="a 7-Scenes / 3DMatch / SUN3D sequence (frame-<i>.color.jpg, .depth.png, .pose.txt)",
        example="panogs import sevenscenes 7scenes/chess/seq-01 bundles/chess --stride 10 --placeholder-maps",
        add_options=_add_sevenscenes_options,
        run=_run_sevenscenes,
    ),
    *(capture_source(cli) for cli in CAPTURE_CLIS),
)
