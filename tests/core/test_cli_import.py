"""``panogs import <source> SRC DST``: one subcommand per entry of ``IMPORT_SOURCES``, each with only its own
options and an example in its help; the spellings of before (options before the source, another source's option)
run with a note or fail naming the spelling that works."""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import pytest

from panogs_core.cli import build_parser
from panogs_core.cli.commands import import_
from panogs_core.cli.commands.import_sources import IMPORT_SOURCES, ImportSource
from panogs_core.cli.main import main as cli_main
from panogs_core.io.bundle import open_bundle
from panogs_core.io.importers.common import ImportReport

SHARED = {"-h", "--help", "--stride", "--vocabulary", "--feature-space"}
OWN = {
    "scannet": {"--geometry", "--gt"},
    "replica": {"--geometry", "--gt", "--depth-scale"},
    "sevenscenes": {"--features", "--masks", "--placeholder-maps"},
}


def _source_parsers() -> dict[str, argparse.ArgumentParser]:
    (top,) = (a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    (sources,) = (a for a in top.choices["import"]._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sources.choices)


def _options(parser: argparse.ArgumentParser) -> set[str]:
    return {option for action in parser._actions for option in action.option_strings}


def _replica(root: Path, frames: int = 4) -> Path:
    """A NICE-SLAM layout of a few 12 x 8 frames, each with a feature map and a mask."""
    rng = np.random.default_rng(0)
    for sub in ("results", "features", "masks"):
        (root / sub).mkdir(parents=True)
    poses = []
    for i in range(frames):
        digits = f"{i:06d}"
        assert cv2.imwrite(str(root / "results" / f"depth{digits}.png"), rng.integers(500, 3000, (8, 12), np.uint16))
        np.save(root / "features" / f"frame{digits}.npy", rng.normal(size=(2, 3, 4)).astype(np.float32))
        assert cv2.imwrite(str(root / "masks" / f"frame{digits}.png"), rng.integers(0, 3, (8, 12), np.uint16))
        pose = np.eye(4)
        pose[0, 3] = 0.1 * i
        poses.append(" ".join(f"{v:.6f}" for v in pose.reshape(-1)))
    (root / "traj.txt").write_text("\n".join(poses) + "\n")
    return root


def test_each_source_is_a_subcommand_with_only_its_own_options_and_an_example() -> None:
    parsers = _source_parsers()
    assert list(parsers) == [source.name for source in IMPORT_SOURCES]
    assert set(OWN) <= set(parsers)
    for source in IMPORT_SOURCES:
        parser = parsers[source.name]
        assert SHARED <= _options(parser), source.name
        assert _options(parser) == SHARED | OWN.get(source.name, _options(parser) - SHARED), source.name
        assert source.example.startswith(f"panogs import {source.name} ")
        assert source.example in parser.format_help()
        args = build_parser().parse_args(source.example.split()[1:])  # the example parses as written
        assert args.import_source is source


def test_the_new_spelling_parses_each_sources_options() -> None:
    args = build_parser().parse_args(["import", "replica", "in", "out", "--stride", "3", "--depth-scale", "1000"])
    assert (args.source, args.src, args.dst, args.stride, args.depth_scale) == ("replica", "in", "out", 3, 1000.0)
    args = build_parser().parse_args(["import", "sevenscenes", "in", "out", "--placeholder-maps"])
    assert args.placeholder_maps
    assert args.stride == 1


def test_the_replica_import_runs_with_its_own_option(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = _replica(tmp_path / "room0")
    assert cli_main(["import", "replica", str(src), str(tmp_path / "b"), "--depth-scale", "1000"]) == 0
    assert "wrote 4 frames" in capsys.readouterr().out
    scene = open_bundle(tmp_path / "b")
    assert scene.depth_scale == 1000.0
    assert len(scene.frames) == 4


def test_options_before_the_source_still_run_and_the_note_gives_todays_spelling(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src, dst = _replica(tmp_path / "room0"), tmp_path / "b"
    assert cli_main(["-v", "import", "--stride", "2", "replica", str(src), str(dst)]) == 0
    captured = capsys.readouterr()
    assert f"panogs import replica --stride 2 {src} {dst}" in captured.err
    assert "wrote 2 frames" in captured.out
    assert len(open_bundle(dst).frames) == 2


@pytest.mark.parametrize(
    ("argv", "takers"),
    [
        (["scannet", "a", "b", "--depth-scale", "1000"], ["--depth-scale is an option of `panogs import replica`"]),
        (["sevenscenes", "a", "b", "--gt", "gt.npz"], ["`panogs import scannet` and `panogs import replica`"]),
        (["replica", "a", "b", "--placeholder-maps", "--features=f"], ["--placeholder-maps is", "--features is"]),
    ],
)
def test_another_sources_option_is_refused_naming_the_sources_that_take_it(
    argv: list[str], takers: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    """Once silently ignored (``--depth-scale`` on ScanNet), now refused before anything is read or written."""
    with pytest.raises(SystemExit) as exit_:
        cli_main(["import", *argv])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert f"usage: panogs import {argv[0]} " in err
    assert f"not of `panogs import {argv[0]}`" in err
    for taker in takers:
        assert taker in err


def test_an_option_no_source_takes_gets_the_plain_message(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        cli_main(["import", "scannet", "a", "b", "--no-such-option"])
    err = capsys.readouterr().err
    assert "unrecognized arguments: --no-such-option" in err
    assert "is an option of" not in err


@pytest.mark.parametrize(
    "argv",
    [
        ["run", "b", "--out", "o"],
        ["import", "scannet", "a", "b", "--stride", "2"],
        ["import", "--help"],
        ["import", "--stride", "2"],  # no source at all: argparse says what is wrong
    ],
)
def test_other_command_lines_are_not_rewritten(argv: list[str]) -> None:
    assert import_.options_before_source(argv) == argv


def test_a_new_source_is_one_entry(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """What an importer added to the table gets: its subcommand, its options, the shared ones, the vocabulary."""
    calls: list[tuple[argparse.Namespace, object]] = []

    def add_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--frame-rate", type=float, default=0.001)

    def run(args: argparse.Namespace, vocabulary: object) -> ImportReport:
        calls.append((args, vocabulary))
        return ImportReport(bundle=Path(args.dst), frames_written=7)

    example = "panogs import madeup capture bundle --frame-rate 0.0002"
    madeup = ImportSource(name="madeup", help="a made-up layout", example=example, add_options=add_options, run=run)
    monkeypatch.setattr(import_, "IMPORT_SOURCES", (*IMPORT_SOURCES, madeup))
    assert "madeup" in _source_parsers()
    dst = tmp_path / "bundle"
    assert (
        cli_main(["import", "madeup", "capture", str(dst), "--frame-rate", "0.0002", "--vocabulary", "scannet20"]) == 0
    )
    assert capsys.readouterr().out.startswith(f"wrote 7 frames to {dst}")
    ((args, vocabulary),) = calls
    assert (args.src, args.frame_rate, args.stride, args.feature_space) == ("capture", 0.0002, 1, "clip-vit-b32")
    assert vocabulary.names[:2] == ("wall", "floor")  # type: ignore[attr-defined]
    with pytest.raises(SystemExit):
        cli_main(["import", "scannet", "a", "b", "--frame-rate", "1"])
    assert "--frame-rate is an option of `panogs import madeup`" in capsys.readouterr().err


def test_the_readme_shows_every_source_in_its_spelling() -> None:
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    for source in IMPORT_SOURCES:
        assert f"panogs import {source.name} SRC DST" in readme, f"README.md's command list lacks {source.name}"
        assert f"`panogs import {source.name} " in readme, f"README.md's own-data list has no example of {source.name}"
