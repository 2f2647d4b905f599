"""The 2D-maps stage through real model code: tiny SAM and CLIP models with random weights, saved as
``save_pretrained`` saves a real checkpoint and loaded through exactly the path a user's folder takes.

Random weights give meaningless masks and features: these tests assert the plumbing (shapes, dtypes, id
conventions, unit rows, determinism, progress, cancel, resume, errors), not quality.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("transformers")
pytest.importorskip("PIL")

from tiny_models import tiny_clip, tiny_sam

from panogs_core.errors import Cancelled, InputError, ShapeError
from panogs_core.language.model_identity import clip_space, model_hash
from panogs_core.stages.maps2d import (
    FrameImage,
    Maps2DConfig,
    Maps2DResult,
    ModelLoadError,
    compute_2d_maps,
    identify_models,
)

pytestmark = pytest.mark.slow  # imports transformers and loads models (1-8 s a test here)

# Random weights score every mask near 0: keep them all, so that the painting and the crops run.
KEEP_ALL = {"pred_iou_thresh": -1.0, "stability_score_thresh": 0.0, "min_mask_fraction": 0.0}


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("models2d")
    return tiny_sam(root / "sam"), tiny_clip(root / "clip")


@pytest.fixture(autouse=True)
def offline(monkeypatch: pytest.MonkeyPatch) -> None:
    """No network: loading must work from local files only."""
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("TRANSFORMERS_OFFLINE", "1")


def _frames(count: int = 3, size: tuple[int, int] = (36, 48)) -> list[FrameImage]:
    rng = np.random.default_rng(7)
    out = []
    for i in range(count):
        image = np.zeros((*size, 3), dtype=np.uint8)
        image[: size[0] // 2] = (200, 40, 40)  # two halves and a box: structure, not noise alone
        image[size[0] // 2 :] = (40, 40, 200)
        image[8:20, 10 + 4 * i : 26 + 4 * i] = (30, 200, 30)
        image = np.clip(image + rng.integers(0, 20, image.shape), 0, 255).astype(np.uint8)
        out.append(FrameImage(f"{i:06d}", image))
    return out


# float32 whatever the CPU ("auto" is bfloat16 on one with native bfloat16): the same numbers on every machine.
CFG = Maps2DConfig(
    points_per_side=4, points_per_batch=5, max_masks=6, mask_long_side=32, feature_long_side=8, device="cpu",
    cpu_precision="float32", **KEEP_ALL,
)  # fmt: skip


class TestMaps2DWithModels:
    def test_smoke(self, models: tuple[Path, Path], tmp_path: Path) -> None:
        sam, clip = models
        calls: list[tuple[int, int]] = []
        result = compute_2d_maps(
            iter(_frames()),
            tmp_path / "maps",
            CFG,
            masks_model=sam,
            features_model=clip,
            total=3,
            on_progress=lambda d, t: calls.append((d, t)),
        )
        assert calls == [(1, 3), (2, 3), (3, 3)]
        assert result.complete
        assert [f.id for f in result.frames] == ["000000", "000001", "000002"]
        assert result.space == clip_space(clip)
        assert result.space.startswith("clip-vit-w16p8-16@")  # a 16-wide tower is no published size
        assert result.feature_dim == 12
        for entry in result.frames:
            ids = result.read_masks(entry.id)
            assert ids.shape == (24, 32)  # 36x48 scaled to a long side of 32
            assert ids.dtype == np.uint16
            present = np.unique(ids[ids > 0])
            assert present.tolist() == list(range(1, entry.mask_count + 1))  # consecutive ids from 1
            assert 1 <= entry.mask_count <= CFG.max_masks
            feats = result.read_features(entry.id)
            assert feats.shape == (6, 8, 12)
            assert feats.dtype == np.float16
            np.testing.assert_allclose(np.linalg.norm(feats.astype(np.float32), axis=-1), 1.0, atol=2e-3)
        # The files the manifest names, the bundle's names.
        assert (tmp_path / "maps" / "masks" / "000001.png").is_file()
        assert (tmp_path / "maps" / "features" / "000001.npy").is_file()
        again = Maps2DResult.load(tmp_path / "maps")
        assert again == result

    def test_deterministic(self, models: tuple[Path, Path], tmp_path: Path) -> None:
        sam, clip = models
        a = compute_2d_maps(_frames(2), tmp_path / "a", CFG, masks_model=sam, features_model=clip)
        b = compute_2d_maps(_frames(2), tmp_path / "b", CFG, masks_model=sam, features_model=clip)
        assert a.key == b.key
        for entry in a.frames:
            np.testing.assert_array_equal(a.read_masks(entry.id), b.read_masks(entry.id))
            np.testing.assert_array_equal(a.read_features(entry.id), b.read_features(entry.id))

    def test_cancel_between_frames_then_resume(self, models: tuple[Path, Path], tmp_path: Path) -> None:
        sam, clip = models

        def stop_after_two(done: int, total: int) -> None:
            if done == 2:
                raise Cancelled("stop")

        with pytest.raises(Cancelled):
            compute_2d_maps(
                _frames(), tmp_path / "m", CFG, masks_model=sam, features_model=clip, on_progress=stop_after_two
            )
        partial = Maps2DResult.load(tmp_path / "m")
        assert not partial.complete
        assert [f.id for f in partial.frames] == ["000000", "000001"]  # both written before the cancel
        first = partial.read_features("000000").copy()
        computed: list[str] = []
        frames = _frames()

        def recording() -> Iterator[FrameImage]:
            for f in frames:
                computed.append(f.id)
                yield f

        mtime = (tmp_path / "m" / "features" / "000000.npy").stat().st_mtime_ns
        done = compute_2d_maps(recording(), tmp_path / "m", CFG, masks_model=sam, features_model=clip)
        assert done.complete
        assert len(done.frames) == 3
        assert (tmp_path / "m" / "features" / "000000.npy").stat().st_mtime_ns == mtime  # not recomputed
        np.testing.assert_array_equal(done.read_features("000000"), first)

    def test_other_settings_start_over(self, models: tuple[Path, Path], tmp_path: Path) -> None:
        sam, clip = models
        a = compute_2d_maps(_frames(1), tmp_path / "m", CFG, masks_model=sam, features_model=clip)
        other = Maps2DConfig(**{**CFG.__dict__, "feature_long_side": 4})
        b = compute_2d_maps(_frames(1), tmp_path / "m", other, masks_model=sam, features_model=clip)
        assert a.key != b.key
        assert b.read_features("000000").shape == (3, 4, 12)

    def test_prompts_per_call_change_no_mask(self, models: tuple[Path, Path], tmp_path: Path) -> None:
        # One prompt a call, the CPU's default and SAM's 64, with a candidate cap small enough that the best
        # candidates are picked several times over the grid: the same masks each time.
        sam, _ = models
        maps = []
        for batch in (1, None, 64):
            cfg = replace(CFG, points_per_batch=batch, max_candidates=7)
            result = compute_2d_maps(_frames(2), tmp_path / f"m{batch}", cfg, masks_model=sam)
            maps.append([result.read_masks(f.id) for f in result.frames])
        assert maps[0][0].max() >= 2  # masks, not an empty map
        for other in maps[1:]:
            for a, b in zip(maps[0], other, strict=True):
                np.testing.assert_array_equal(a, b)

    def test_bfloat16_on_a_cpu(self, models: tuple[Path, Path], tmp_path: Path) -> None:
        # Both models run in bfloat16 (the CPU default where the CPU has it natively); the maps keep their formats,
        # and the checkpoint key tells them from float32's, so neither continues the other's folder.
        import torch

        from panogs_core.stages.maps2d import runner

        sam, clip = models
        cfg = replace(CFG, cpu_precision="bfloat16")
        loaded = runner.load_models(sam, clip, cfg)
        assert loaded.sam is not None
        assert loaded.clip is not None
        assert loaded.sam.model.dtype == loaded.clip.model.dtype == torch.bfloat16
        half = compute_2d_maps(_frames(1), tmp_path / "m", cfg, masks_model=sam, features_model=clip)
        ids = half.read_masks("000000")
        assert ids.dtype == np.uint16
        assert np.unique(ids[ids > 0]).tolist() == list(range(1, half.frames[0].mask_count + 1))
        assert half.frames[0].mask_count >= 1
        feats = half.read_features("000000")
        assert feats.dtype == np.float16
        np.testing.assert_allclose(np.linalg.norm(feats.astype(np.float32), axis=-1), 1.0, atol=2e-3)
        full = compute_2d_maps(_frames(1), tmp_path / "m", CFG, masks_model=sam, features_model=clip)
        assert full.key != half.key

    def test_image_tower_alone(self, models: tuple[Path, Path]) -> None:
        # The stage builds CLIP's image tower only, with the whole model's projection width (12 here, where the
        # vision section's own default is 512), and embeds as the whole model does.
        import torch
        from transformers import CLIPModel

        from panogs_core.stages.maps2d.models import load_clip

        _, clip = models
        loaded = load_clip(clip, "cpu")
        assert not hasattr(loaded.model, "text_model")
        whole = CLIPModel.from_pretrained(clip).eval()
        pixels = torch.randn(3, 3, 16, 16)
        with torch.inference_mode():
            expected = whole.get_image_features(pixel_values=pixels)
            expected = expected if isinstance(expected, torch.Tensor) else expected.pooler_output
            got = loaded.model(pixel_values=pixels).image_embeds
        assert got.shape == (3, 12)
        torch.testing.assert_close(got, expected)

    def test_masks_only(self, models: tuple[Path, Path], tmp_path: Path) -> None:
        sam, _ = models
        result = compute_2d_maps(_frames(2), tmp_path / "m", CFG, masks_model=sam)
        assert result.features_model is None
        assert result.space is None
        assert result.feature_dim is None
        assert result.read_masks("000000").dtype == np.uint16
        assert not (tmp_path / "m" / "features").exists()
        with pytest.raises(InputError, match="no feature map here"):
            result.read_features("000000")

    def test_features_only_from_the_frames_masks(self, models: tuple[Path, Path], tmp_path: Path) -> None:
        _, clip = models
        frames = []
        for f in _frames(2):
            ids = np.zeros((12, 16), dtype=np.uint8)
            ids[:6] = 7  # sparse ids, as an 8-bit bundle map has them
            ids[8:, 4:12] = 255
            frames.append(FrameImage(f.id, f.color, ids))
        result = compute_2d_maps(frames, tmp_path / "m", CFG, features_model=clip)
        assert result.masks_model is None
        feats = result.read_features("000000").astype(np.float32)
        assert feats.shape == (6, 8, 12)
        top, bottom_box, uncovered = feats[0, 0], feats[5, 3], feats[4, 0]
        assert np.allclose(feats[:3], top, atol=1e-3)  # one mask: one feature on all its cells
        assert not np.allclose(top, bottom_box, atol=1e-3)
        assert not np.allclose(top, uncovered, atol=1e-3)
        assert not np.allclose(bottom_box, uncovered, atol=1e-3)
        assert result.frames[0].mask_count == 2

    def test_any_printable_frame_id_is_written_inside_the_folder(
        self, models: tuple[Path, Path], tmp_path: Path
    ) -> None:
        # A bundle's frame ids are any printable text; the maps' files are named by their place in the manifest, so
        # an id with a slash or a space neither escapes the folder nor fails the run.
        sam, _clip = models
        frame = _frames(1)[0]
        odd = FrameImage("../seq 1/frame 7", frame.color)
        result = compute_2d_maps([odd], tmp_path / "m", CFG, masks_model=sam)
        assert [f.masks for f in result.frames] == ["masks/000000.png"]
        assert result.read_masks("../seq 1/frame 7").shape[0] > 0
        assert not (tmp_path / "seq 1").exists()

    def test_features_only_needs_masks(self, models: tuple[Path, Path], tmp_path: Path) -> None:
        _, clip = models
        with pytest.raises(InputError, match="frame 000000: no mask map, and no masks model"):
            compute_2d_maps(_frames(1), tmp_path / "m", CFG, features_model=clip)

    def test_exception(self, models: tuple[Path, Path], tmp_path: Path) -> None:
        sam, _clip = models
        with pytest.raises(InputError, match="neither masks_model nor features_model"):
            compute_2d_maps(_frames(1), tmp_path / "m", CFG)
        bad = [FrameImage("a\x00b", _frames(1)[0].color)]
        with pytest.raises(InputError, match=r"frame id 'a\\x00b': expected non-empty printable text"):
            compute_2d_maps(bad, tmp_path / "m", CFG, masks_model=sam)
        twice = [_frames(1)[0], _frames(1)[0]]
        with pytest.raises(InputError, match="appears twice"):
            compute_2d_maps(twice, tmp_path / "m", CFG, masks_model=sam)
        grey = [FrameImage("a", np.zeros((8, 8), dtype=np.uint8))]
        with pytest.raises(ShapeError, match=r"frame a: colour uint8 \(8, 8\), expected \(H, W, 3\) uint8"):
            compute_2d_maps(grey, tmp_path / "m", CFG, masks_model=sam)


class TestModelErrors:
    """A model that cannot load fails before any frame is read, naming its place and what is missing."""

    @staticmethod
    def _never() -> Iterator[FrameImage]:
        raise AssertionError("a frame was read before the models loaded")
        yield  # pragma: no cover

    def test_missing_folder(self, tmp_path: Path, models: tuple[Path, Path]) -> None:
        with pytest.raises(ModelLoadError, match="not a folder, and not a hub name"):
            compute_2d_maps(self._never(), tmp_path / "m", CFG, masks_model=str(tmp_path / "nope"))

    def test_hub_name_not_cached(self, tmp_path: Path) -> None:
        with pytest.raises(ModelLoadError, match="facebook/no-such-model: not in the local hub cache"):
            compute_2d_maps(self._never(), tmp_path / "m", CFG, masks_model="facebook/no-such-model")

    def test_no_weights(self, tmp_path: Path, models: tuple[Path, Path]) -> None:
        folder = tmp_path / "sam"
        folder.mkdir()
        (folder / "config.json").write_text((models[0] / "config.json").read_text())
        with pytest.raises(ModelLoadError, match=r"sam: no weights \(\*.safetensors"):
            compute_2d_maps(self._never(), tmp_path / "m", CFG, masks_model=folder)

    def test_no_config(self, tmp_path: Path) -> None:
        folder = tmp_path / "sam"
        folder.mkdir()
        (folder / "model.safetensors").write_bytes(b"x")
        with pytest.raises(ModelLoadError, match=r"sam: no config\.json"):
            compute_2d_maps(self._never(), tmp_path / "m", CFG, masks_model=folder)

    def test_no_processor(self, tmp_path: Path, models: tuple[Path, Path]) -> None:
        import shutil

        folder = tmp_path / "sam"
        shutil.copytree(models[0], folder)
        (folder / "preprocessor_config.json").unlink()
        with pytest.raises(ModelLoadError, match=r"no preprocessor_config\.json; save the SAM processor"):
            compute_2d_maps(self._never(), tmp_path / "m", CFG, masks_model=folder)

    def test_wrong_family(self, tmp_path: Path, models: tuple[Path, Path]) -> None:
        sam, clip = models
        with pytest.raises(ModelLoadError, match="model_type 'clip', expected a Segment Anything model"):
            compute_2d_maps(self._never(), tmp_path / "m", CFG, masks_model=clip)
        with pytest.raises(ModelLoadError, match="model_type 'sam', expected a CLIP model"):
            compute_2d_maps(self._never(), tmp_path / "m", CFG, features_model=sam)

    def test_corrupt_weights(self, tmp_path: Path, models: tuple[Path, Path]) -> None:
        import shutil

        folder = tmp_path / "clip"
        shutil.copytree(models[1], folder)
        (folder / "model.safetensors").write_bytes(b"not a safetensors file")
        with pytest.raises(ModelLoadError, match="the CLIP model does not load"):
            compute_2d_maps(self._never(), tmp_path / "m", CFG, features_model=folder)


class TestIdentity:
    def test_hash_follows_the_files_not_the_path(self, tmp_path: Path, models: tuple[Path, Path]) -> None:
        import shutil

        sam, clip = models
        copy = tmp_path / "elsewhere" / "sam"
        shutil.copytree(sam, copy)
        assert model_hash(copy) == model_hash(sam)
        other = tiny_sam(tmp_path / "sam_seed1", seed=1)
        assert model_hash(other) != model_hash(sam)
        masks_id, feats_id = identify_models(sam, clip)
        assert masks_id is not None
        assert masks_id.sha256 == model_hash(sam)
        assert feats_id is not None
        assert feats_id.space == clip_space(clip)
        assert feats_id.space.endswith("@" + feats_id.sha256[:16])

    def test_space_names_the_architecture(self, tmp_path: Path) -> None:
        folder = tmp_path / "c"
        folder.mkdir()
        (folder / "model.safetensors").write_bytes(b"w")
        vision = {"hidden_size": 768, "patch_size": 16, "image_size": 224}
        (folder / "config.json").write_text(json.dumps({"model_type": "clip", "vision_config": vision}))
        assert clip_space(folder).startswith("clip-vit-b16@")
        vision = {"hidden_size": 1024, "patch_size": 14, "image_size": 336}
        (folder / "config.json").write_text(json.dumps({"model_type": "clip", "vision_config": vision}))
        assert clip_space(folder).startswith("clip-vit-l14-336@")
        (folder / "config.json").write_text(json.dumps({"model_type": "sam"}))
        with pytest.raises(ModelLoadError, match="expected a CLIP model"):
            clip_space(folder)
