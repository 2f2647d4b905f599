"""The 2D-maps stage inside a run: a bundle with colour and depth only (imported from a TUM capture without maps)
through ``panogs run --masks-model --features-model`` with tiny random SAM and CLIP folders, to labels and a text
query; the checkpoint reused by a re-run with other clustering settings; masks-only and features-only bundles; the
errors. Random weights make meaningless maps: these tests assert the wiring, not quality.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("transformers")

from bundle_copies import without_maps
from capture_room import write_tum
from tiny_models import TINY_MAPS, tiny_clip, tiny_sam

from panogs_core.cli.main import main
from panogs_core.errors import InputError
from panogs_core.io.bundle import open_bundle
from panogs_core.io.importers.capture import MapSources
from panogs_core.io.importers.tum import TumOptions, import_tum
from panogs_core.pipeline.config import PipelineConfig
from panogs_core.pipeline.run import run_pipeline
from panogs_core.stages.maps2d import MapModels, ModelLoadError

# Tiny settings: the tiny models' 64 px images, every mask kept, no appearance fit (not what is tested).
SETTINGS = {
    **{f"maps2d.{k}": v for k, v in TINY_MAPS.items()},
    "maps2d.device": "cpu",
    "appearance.enabled": False,
}


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("models2d")
    return tiny_sam(root / "sam"), tiny_clip(root / "clip")


@pytest.fixture(autouse=True)
def offline(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("TRANSFORMERS_OFFLINE", "1")


@pytest.fixture(scope="module")
def capture_bundle(synth_tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny room as a TUM capture, imported without maps: colour and depth only."""
    root = tmp_path_factory.mktemp("capture")
    write_tum(synth_tiny, root / "seq")
    cam = open_bundle(synth_tiny).camera
    (root / "seq" / "intrinsics.txt").write_text(f"{cam.fx!r} {cam.fy!r} {cam.cx!r} {cam.cy!r}\n")
    import_tum(root / "seq", root / "bundle", TumOptions(intrinsics=root / "seq" / "intrinsics.txt", maps=MapSources()))
    return root / "bundle"


def _argv(bundle: Path, out: Path, *extra: str, settings: dict[str, object] | None = None) -> list[str]:
    sets = [f"--set={k}={json.dumps(v)}" for k, v in (settings or SETTINGS).items()]
    return ["run", str(bundle), "--out", str(out), "--tiles", "off", "--quiet", *sets, *extra]


def _report(out: Path) -> dict[str, object]:
    return json.loads((out / "report.json").read_text())


def _stage(out: Path, name: str) -> dict[str, object]:
    return next(s for s in _report(out)["stages"] if s["stage"] == name)  # type: ignore[index, union-attr]


def _manifests(out: Path) -> list[Path]:
    return sorted((out / "stages" / "maps_2d").glob("*/manifest.json"))


# Runs the tiny room's pipeline with model folders (10-40 s here).
@pytest.mark.slow
def test_a_capture_without_maps_gets_labels_and_answers_a_text_query(
    capture_bundle: Path, models: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sam, clip = models
    out = tmp_path / "run"
    assert main(_argv(capture_bundle, out, "--masks-model", str(sam), "--features-model", str(clip))) == 0
    labels = np.load(out / "labels.npz")
    assert labels["semantic"].size > 0
    stage = _stage(out, "maps_2d")
    assert stage["device"] == "cpu"
    assert stage["wall_s"] > 0
    (manifest,) = _manifests(out)
    doc = json.loads(manifest.read_text())
    assert doc["complete"]
    assert len(doc["frames"]) == len(open_bundle(capture_bundle).frames)
    assert doc["feature_dim"] == 12
    assert doc["features_model"]["space"].startswith("clip-vit-")
    assert (out / "instances.json").is_file()
    capsys.readouterr()
    assert main(["query", str(out), "a soft chair", "--model-path", str(clip), "--min-score", "-1"]) == 0
    assert "a soft chair" in capsys.readouterr().out

    # Other clustering settings: the maps are reused, no model is loaded.
    from panogs_core.stages.maps2d import runner

    def no_loading(*_args: object) -> None:
        raise AssertionError("the maps checkpoint was not reused: a model was loaded")

    before = manifest.stat().st_mtime_ns
    monkeypatch = pytest.MonkeyPatch()
    monkeypatch.setattr(runner, "load_models", no_loading)
    try:
        argv = _argv(capture_bundle, out, "--masks-model", str(sam), "--features-model", str(clip),
                     settings={**SETTINGS, "clustering.thresholds": [0.8, 0.6]})  # fmt: skip
        assert main(argv) == 0
    finally:
        monkeypatch.undo()
    assert _manifests(out) == [manifest]
    assert manifest.stat().st_mtime_ns == before
    assert _stage(out, "maps_2d")["wall_s"] < 1.0
    assert _stage(out, "maps_2d")["cached"] is True  # report.json (and a job's status) says it was reused


def test_masks_only_keeps_the_bundles_features(synth_tiny: Path, models: tuple[Path, Path], tmp_path: Path) -> None:
    bundle = without_maps(synth_tiny, tmp_path / "b", ("masks",))
    out = tmp_path / "run"
    result = run_pipeline(bundle, out, PipelineConfig().with_overrides(_nested(SETTINGS)),
                          map_models=MapModels(masks=str(models[0]), features=str(models[1])))  # fmt: skip
    assert result.num_primitives > 0
    (manifest,) = _manifests(out)
    doc = json.loads(manifest.read_text())
    assert doc["masks_model"] is not None
    assert doc["features_model"] is None  # the bundle's features are its own: never recomputed
    assert _report(out)["feature_space"] == open_bundle(synth_tiny).feature_space


def test_features_only_reads_the_bundles_masks(synth_tiny: Path, models: tuple[Path, Path], tmp_path: Path) -> None:
    bundle = without_maps(synth_tiny, tmp_path / "b", ("features",))
    out = tmp_path / "run"
    run_pipeline(bundle, out, PipelineConfig().with_overrides(_nested(SETTINGS)),
                 map_models=MapModels(features=str(models[1])))  # fmt: skip
    (manifest,) = _manifests(out)
    doc = json.loads(manifest.read_text())
    assert doc["masks_model"] is None
    assert doc["features_model"] is not None
    assert all(f["masks"] is None and f["features"] for f in doc["frames"])
    assert _report(out)["feature_space"] == doc["features_model"]["space"]


# Runs the tiny room's pipeline with model folders (10-40 s here).
@pytest.mark.slow
def test_a_tiled_run_computes_the_maps_once_for_every_tile(
    synth_tiny: Path, models: tuple[Path, Path], tmp_path: Path
) -> None:
    from panogs_core.tiling.runner import run_tiled

    bundle = without_maps(synth_tiny, tmp_path / "b", ("masks",))
    out = tmp_path / "run"
    result = run_tiled(bundle, out, PipelineConfig().with_overrides(_nested(SETTINGS)), tiles=(2, 1),
                       map_models=MapModels(masks=str(models[0])))  # fmt: skip
    assert result.num_primitives > 0
    assert len(_manifests(out)) == 1  # the scene's, before the plan
    assert not list((out / "tiles").glob("*/stages/maps_2d"))  # no tile computed maps of its own
    assert "maps_2d" in [s["stage"] for s in _report(out)["stages"]]


# Runs the tiny room's pipeline with model folders (10-40 s here).
@pytest.mark.slow
def test_errors_come_before_any_frame(capture_bundle: Path, models: tuple[Path, Path], tmp_path: Path) -> None:
    cfg = PipelineConfig().with_overrides(_nested(SETTINGS))
    with pytest.raises(InputError, match=r"no masks nor feature maps; pass --masks-model .* and --features-model"):
        run_pipeline(capture_bundle, tmp_path / "a", cfg)
    with pytest.raises(InputError, match="pass --features-model"):
        run_pipeline(capture_bundle, tmp_path / "b", cfg, map_models=MapModels(masks=str(models[0])))
    bad = tmp_path / "not-a-model"
    bad.mkdir()
    with pytest.raises(ModelLoadError, match=str(bad)):
        run_pipeline(capture_bundle, tmp_path / "c", cfg, map_models=MapModels(masks=str(bad), features=str(models[1])))
    assert not list((tmp_path / "c").rglob("masks/*.png"))


@pytest.mark.slow  # tiny models on half the tiny capture's frames (2-6 s here)
def test_a_frame_stride_computes_every_kth_frame_and_leaves_the_others_without_maps(
    capture_bundle: Path, models: tuple[Path, Path], tmp_path: Path
) -> None:
    from panogs_core.stages.maps2d.config import Maps2DConfig
    from panogs_core.stages.maps2d.stage import with_computed_maps

    bundle = open_bundle(capture_bundle)
    settings = {k.removeprefix("maps2d."): v for k, v in SETTINGS.items() if k.startswith("maps2d.")}
    cfg = Maps2DConfig(**settings, frame_stride=3)  # type: ignore[arg-type]
    seen = with_computed_maps(bundle, tmp_path, cfg, MapModels(str(models[0]), str(models[1])), lambda d, t: None)
    every = [f.id for f in bundle.frames if f.color is not None]
    assert len(every) >= 4
    assert [f.id for f in seen.mask_frames] == every[::3]
    assert [f.id for f in seen.feature_frames] == every[::3]
    assert [f.id for f in seen.computed.frames] == every[::3]  # type: ignore[union-attr]
    assert all(f.masks is None and f.features is None for f in seen.frames if f.id not in every[::3])
    # Another stride is another folder: the frames computed are in its key.
    other = with_computed_maps(
        bundle, tmp_path, Maps2DConfig(**settings, frame_stride=2), MapModels(str(models[0]), str(models[1])),  # type: ignore[arg-type]
        lambda d, t: None,
    )  # fmt: skip
    assert other.computed.root != seen.computed.root  # type: ignore[union-attr]
    assert [f.id for f in other.mask_frames] == every[::2]


def _nested(flat: dict[str, object]) -> dict[str, object]:
    out: dict[str, dict[str, object]] = {}
    for key, value in flat.items():
        section, name = key.split(".", 1)
        out.setdefault(section, {})[name] = value
    return dict(out)


@pytest.mark.parametrize(
    ("points_per_side", "device", "grid"),
    [
        (None, "cpu", 8),  # the CPU default (docs/method.md §17), in the CLI and in a worker alike
        (None, "cuda", 32),  # SAM's automatic mode on a GPU
        (12, "cpu", 12),  # the user's choice wins
        (12, "cuda", 12),
    ],
)
def test_the_prompt_grid_is_chosen_by_device_unless_set(points_per_side: int | None, device: str, grid: int) -> None:
    import torch

    from panogs_core.stages.maps2d.config import Maps2DConfig
    from panogs_core.stages.maps2d.masks import grid_side

    cfg = Maps2DConfig(points_per_side=points_per_side)
    assert grid_side(cfg, torch.device(device)) == grid


def test_the_cli_passes_the_named_models() -> None:
    from panogs_core.cli.commands.run import _map_models, _settings
    from panogs_core.cli.main import build_parser

    args = build_parser().parse_args(["run", "b", "--out", "o", "--masks-model", "some/sam"])
    cfg, _ = _settings(args)
    assert cfg.maps2d.points_per_side is None  # chosen by the stage on its device
    models = _map_models(args)
    assert models is not None
    assert (models.masks, models.features, models.allow_download) == ("some/sam", None, False)
