"""The 2D-maps stage without models: settings, the mask post-processing (stability, NMS, painting) and the
mask-pooled feature painting, on hand-made inputs whose right answer is known."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from panogs_core.errors import ConfigError
from panogs_core.stages.maps2d.config import Maps2DConfig, scaled_size


class TestConfig:
    def test_defaults(self) -> None:
        cfg = Maps2DConfig()
        assert cfg.points_per_side is None  # by device: masks.grid_side
        assert cfg.pred_iou_thresh == 0.88
        assert cfg.stability_score_thresh == 0.95
        assert set(cfg.mask_settings()).isdisjoint(cfg.feature_settings())

    @pytest.mark.parametrize(
        ("field", "value", "message"),
        [
            ("points_per_side", 0, r"maps2d.points_per_side: expected None or >= 1, found 0"),
            ("points_per_batch", 0, r"maps2d.points_per_batch: expected None or >= 1, found 0"),
            ("pred_iou_thresh", 1.5, r"maps2d.pred_iou_thresh: expected in \[-1, 1\], found 1.5"),
            ("stability_score_thresh", float("nan"), r"maps2d.stability_score_thresh: expected in \[0, 1\]"),
            ("nms_iou_thresh", 0.0, r"maps2d.nms_iou_thresh: expected in \(0, 1\], found 0.0"),
            ("min_mask_fraction", -0.1, r"maps2d.min_mask_fraction"),
            ("max_masks", 70000, r"maps2d.max_masks: expected in \[1, 65535\], found 70000"),
            ("crop_margins", (), r"maps2d.crop_margins: expected at least one margin"),
            ("crop_margins", (0.1, -1.0), r"maps2d.crop_margins: expected margins in \[0, 10\]"),
            ("global_mix", 2.0, r"maps2d.global_mix"),
            ("device", "gpu", r"maps2d.device: expected auto, cpu, cuda or cuda:N, found 'gpu'"),
            ("cpu_threads", 0, r"maps2d.cpu_threads"),
            ("feature_long_side", 0, r"maps2d.feature_long_side"),
            ("frame_stride", 0, r"maps2d.frame_stride: expected >= 1, found 0"),
            ("cpu_precision", "float16", r"maps2d.cpu_precision: expected auto or float32 or bfloat16"),
        ],
    )
    def test_exception(self, field: str, value: object, message: str) -> None:
        with pytest.raises(ConfigError, match=message):
            Maps2DConfig(**{field: value})  # type: ignore[arg-type]

    def test_prompts_per_call_by_device(self) -> None:
        torch = pytest.importorskip("torch")
        from panogs_core.stages.maps2d.masks import prompts_per_call

        assert Maps2DConfig().points_per_batch is None
        assert prompts_per_call(Maps2DConfig(), torch.device("cpu")) == 4
        assert prompts_per_call(Maps2DConfig(), torch.device("cuda")) == 64
        assert prompts_per_call(Maps2DConfig(points_per_batch=16), torch.device("cpu")) == 16

    def test_cpu_precision(self, monkeypatch: pytest.MonkeyPatch) -> None:
        # "auto": bfloat16 only where the CPU has it natively; a setting forces either; both settings dicts carry it
        # (a features-only run's key too).
        torch = pytest.importorskip("torch")
        from panogs_core.stages.maps2d import models

        assert Maps2DConfig().cpu_precision == "auto"
        assert "cpu_precision" in Maps2DConfig().mask_settings()
        assert "features_cpu_precision" in Maps2DConfig().feature_settings()
        monkeypatch.setattr(models, "cpu_has_native_bfloat16", lambda: True)
        assert models.pick_device("cpu", "auto") == (torch.device("cpu"), torch.bfloat16)
        assert models.pick_device("cpu", "float32")[1] == torch.float32
        monkeypatch.setattr(models, "cpu_has_native_bfloat16", lambda: False)
        assert models.pick_device("cpu", "auto")[1] == torch.float32
        assert models.pick_device("cpu", "bfloat16")[1] == torch.bfloat16

    def test_scaled_size(self) -> None:
        assert scaled_size(968, 1296, 640) == (478, 640)
        assert scaled_size(480, 640, 1000) == (480, 640)  # never upscaled
        assert scaled_size(3, 1000, 10) == (1, 10)

    def test_entry_imports_no_torch(self) -> None:
        code = (
            "import sys; import panogs_core.stages.maps2d, panogs_core.stages.maps2d.config, "
            "panogs_core.language.model_identity; print('torch' in sys.modules)"
        )
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
        assert out.stdout.strip() == "False"


torch = pytest.importorskip("torch")
masks_mod = pytest.importorskip("panogs_core.stages.maps2d.masks")
features_mod = pytest.importorskip("panogs_core.stages.maps2d.features")


def _rect(shape: tuple[int, int], r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    m = np.zeros(shape, dtype=bool)
    m[r0:r1, c0:c1] = True
    return m


class TestMaskPostProcessing:
    def test_point_grid(self) -> None:
        grid = masks_mod.point_grid(2)
        np.testing.assert_allclose(grid, [[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]])

    def test_stability(self) -> None:
        logits = torch.full((3, 4, 4), -5.0)
        logits[0, :2] = 5.0  # sharp: the same mask at +1 and -1
        logits[1, :2] = 0.5  # soft: 8 pixels above -1, none above +1
        logits[1, 2:] = -0.5
        scores = masks_mod.stability_scores(logits, 1.0)
        np.testing.assert_allclose(scores.numpy(), [1.0, 0.0, 1.0])  # empty at both: 1

    def test_nms_known_answer(self) -> None:
        shape = (10, 10)
        big = _rect(shape, 0, 10, 0, 5)  # 50 px
        near_big = _rect(shape, 0, 10, 0, 4)  # 40 px inside big: IoU 0.8
        part = _rect(shape, 0, 3, 0, 3)  # 9 px inside big: IoU 0.18, kept
        other = _rect(shape, 0, 10, 5, 10)  # disjoint
        masks = torch.as_tensor(np.stack([near_big, big, part, other]).reshape(4, -1))
        scores = torch.tensor([0.9, 0.95, 0.5, 0.7])
        keep = masks_mod.mask_nms(masks, scores, 0.7)
        assert keep.tolist() == [1, 3, 2]  # best first; near_big suppressed by big
        assert masks_mod.mask_nms(masks, scores, 0.85).tolist() == [1, 0, 3, 2]  # 0.8 <= 0.85: both kept
        assert masks_mod.mask_nms(masks[:0], scores[:0], 0.7).tolist() == []

    def test_paint_order_and_ids(self) -> None:
        shape = (6, 6)
        whole = _rect(shape, 0, 6, 0, 6)
        inner = _rect(shape, 1, 3, 1, 3)  # inside whole, lower score: still painted over it (smaller)
        hidden = _rect(shape, 4, 5, 4, 5)
        covered = np.zeros(shape, dtype=bool)
        masks = np.stack([inner, whole, hidden & False, covered])
        ids = masks_mod.paint_masks(masks, np.array([0.1, 0.99, 0.5, 0.5]))
        assert ids.dtype == np.uint16
        assert ids[0, 0] == 1
        assert ids[5, 5] == 1
        assert (ids[1:3, 1:3] == 2).all()  # inner on top, id 2
        assert set(np.unique(ids).tolist()) == {1, 2}  # empty masks dropped, ids consecutive

    def test_paint_same_area_higher_score_on_top(self) -> None:
        shape = (4, 4)
        a = _rect(shape, 0, 2, 0, 4)
        b = _rect(shape, 1, 3, 0, 4)  # same area, overlaps a on row 1
        ids = masks_mod.paint_masks(np.stack([a, b]), np.array([0.9, 0.3]))
        assert ids[1].tolist() == [2, 2, 2, 2]  # a (higher score) painted last, on top
        assert ids[0, 0] == 2
        assert ids[2, 0] == 1
        assert ids[3, 0] == 0

    def test_paint_nothing(self) -> None:
        ids = masks_mod.paint_masks(np.zeros((0, 3, 5), dtype=bool), np.zeros(0))
        assert ids.shape == (3, 5)
        assert not ids.any()


class TestPooledPainting:
    def test_boxes(self) -> None:
        ids = np.zeros((5, 6), dtype=np.uint16)
        ids[1:3, 2:5] = 1
        ids[4, 0] = 3
        boxes = features_mod.mask_boxes(ids, 3)
        np.testing.assert_array_equal(boxes, [[2, 1, 5, 3], [0, 0, 0, 0], [0, 4, 1, 5]])

    def test_square_crop(self) -> None:
        image = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3)
        fill = np.array([7, 8, 9], dtype=np.uint8)
        crop = features_mod.square_crop(image, np.array([1.0, 1.0, 3.0, 2.0]), 0.0, fill)
        assert crop.shape == (2, 2, 3)
        np.testing.assert_array_equal(crop[1], image[1, 1:3])  # centre (2, 1.5), side 2: rows 0-1, columns 1-2
        edge = features_mod.square_crop(image, np.array([0.0, 0.0, 2.0, 2.0]), 0.5, fill)
        assert edge.shape == (4, 4, 3)
        np.testing.assert_array_equal(edge[0, 0], fill)  # outside the image: the fill colour
        np.testing.assert_array_equal(edge[1:, 1:], image[:3, :3])

    def test_known_answer(self) -> None:
        ids = np.zeros((4, 8), dtype=np.int64)
        ids[:, :4] = 1
        ids[:2, 6:] = 2
        mask_feats = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        image_feat = np.array([0.0, 0.0, 1.0])
        out = features_mod.pooled_feature_map(ids, mask_feats, image_feat, (2, 4), 0.0)
        assert out.shape == (2, 4, 3)
        assert out.dtype == np.float16
        expected_ids = np.array([[1, 1, 0, 2], [1, 1, 0, 0]])  # cell centres at rows 1, 3 and columns 1, 3, 5, 7
        table = np.array([image_feat, *mask_feats])
        np.testing.assert_array_equal(out.astype(np.float32), table[expected_ids])

    def test_global_mix_normalised(self) -> None:
        ids = np.ones((2, 2), dtype=np.int64)
        out = features_mod.pooled_feature_map(ids, np.array([[1.0, 0.0]]), np.array([0.0, 1.0]), (1, 1), 0.5)
        np.testing.assert_allclose(out[0, 0].astype(np.float32), [np.sqrt(0.5), np.sqrt(0.5)], atol=1e-3)

    def test_ids_past_the_table_take_the_image(self) -> None:
        ids = np.full((2, 2), 9, dtype=np.int64)
        out = features_mod.pooled_feature_map(ids, np.array([[1.0, 0.0]]), np.array([0.0, 1.0]), (2, 2), 0.0)
        np.testing.assert_array_equal(out.astype(np.float32), np.broadcast_to([0.0, 1.0], (2, 2, 2)))
