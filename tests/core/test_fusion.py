"""Stage 3, fusion: feature-cell lookup, unit normalisation, means, counts, confidence forms, colours."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from panogs_core.errors import ConfigError, InputError, ShapeError
from panogs_core.stages.fusion import FusedFeatures, FusionConfig, confidence_weights, feature_cells, fuse_features
from panogs_core.stages.visibility import Visibility
from panogs_core.types import Camera, Frame

CAM = Camera(width=8, height=6, fx=4.0, fy=4.0, cx=3.5, cy=2.5)
D = 4


@dataclass
class FakeScene:
    """The part of ``bundle.Scene`` that fusion reads."""

    camera: Camera
    frames: tuple[Frame, ...]
    feature_dim: int = D
    features: dict[str, np.ndarray] = field(default_factory=dict)
    colors: dict[str, np.ndarray] = field(default_factory=dict)

    def read_features(self, frame: Frame) -> np.ndarray:
        return self.features[frame.id]

    def read_color(self, frame: Frame) -> np.ndarray | None:
        return self.colors.get(frame.id)

    def read_masks(self, frame: Frame) -> np.ndarray:  # no 2D mask anywhere: mask pooling changes nothing
        return np.zeros((self.camera.height, self.camera.width), np.int32)


def _frame(fid: str, *, features: bool = True, color: bool = False) -> Frame:
    return Frame(
        id=fid,
        T_world_cam=np.eye(4),
        depth=f"depth/{fid}.png",
        features=f"features/{fid}.npy" if features else None,
        color=f"color/{fid}.png" if color else None,
        masks=f"masks/{fid}.png",
    )


def _two_region_map(left: np.ndarray, right: np.ndarray, hf: int = 3, wf: int = 4) -> np.ndarray:
    """(Hf, Wf, D) map: columns [0, Wf/2) hold `left`, the rest `right` (image columns 0-3 vs 4-7)."""
    fmap = np.empty((hf, wf, D), np.float32)
    fmap[:, : wf // 2] = left
    fmap[:, wf // 2 :] = right
    return fmap


def _visibility(per_frame: dict[str, list[tuple[int, int, int]]]) -> Visibility:
    """CSR from {frame id: [(point, row, col), ...]} (points ascending within a frame)."""
    ids, offsets, pts, rows, cols = [], [0], [], [], []
    for fid, obs in per_frame.items():
        ids.append(fid)
        for p, r, c in obs:
            pts.append(p)
            rows.append(r)
            cols.append(c)
        offsets.append(len(pts))
    return Visibility(
        frame_ids=tuple(ids),
        offsets=np.array(offsets, np.int64),
        point_index=np.array(pts, np.int32),
        pixel_row=np.array(rows, np.int32),
        pixel_col=np.array(cols, np.int32),
    )


E0, E1, E2 = np.eye(D, dtype=np.float32)[:3]


def _scene_two_frames() -> tuple[FakeScene, Visibility]:
    """Frame a: left = 3 e0 (non-unit on purpose), right = e1. Frame b: left = e0, right = e2.

    Point 0 is seen left in both; point 1 right in both; point 2 only in frame a, left; point 3 never.
    """
    scene = FakeScene(
        camera=CAM,
        frames=(_frame("a"), _frame("b")),
        features={"a": _two_region_map(3 * E0, E1), "b": _two_region_map(E0, E2)},
    )
    vis = _visibility({"a": [(0, 0, 1), (1, 5, 6), (2, 3, 3)], "b": [(0, 2, 0), (1, 1, 7)]})
    return scene, vis


class TestFuseFeatures:
    def test_smoke(self) -> None:
        scene, vis = _scene_two_frames()
        fused = fuse_features(scene, vis, 4, FusionConfig())
        assert fused.features.shape == (4, D)
        assert fused.features.dtype == np.float32

    def test_constant_regions_known_answer(self) -> None:
        scene, vis = _scene_two_frames()
        fused = fuse_features(scene, vis, 4, FusionConfig())
        np.testing.assert_allclose(fused.features[0], E0)  # 3 e0 normalised, twice
        np.testing.assert_allclose(fused.features[1], (E1 + E2) / 2)
        np.testing.assert_allclose(fused.features[2], E0)
        np.testing.assert_array_equal(fused.features[3], 0)
        assert fused.seen_count.tolist() == [2, 2, 1, 0]
        assert fused.seen_count.dtype == np.int32
        # Code form by hand: S = [2, 2, 1, 0] (range 2), V = 1 - |F|^2 = [0, 0.5, 0, 0] (range 0.5).
        s_prime, v_prime = np.array([1.0, 1.0, 0.5]), np.array([0.0, 1.0, 0.0])
        np.testing.assert_allclose(fused.weights[:3], 10 * s_prime / (v_prime + 1), rtol=1e-6)
        assert fused.weights[3] == 0.0

    def test_unseen_points_zero(self) -> None:
        scene, vis = _scene_two_frames()
        fused = fuse_features(scene, vis, 10, FusionConfig())
        assert np.all(fused.features[3:] == 0)
        assert np.all(fused.weights[3:] == 0)
        assert np.all(fused.seen_count[3:] == 0)

    def test_zero_feature_is_no_observation(self) -> None:
        scene, vis = _scene_two_frames()
        scene.features["b"] = _two_region_map(np.zeros(D, np.float32), E2)  # left half of b: no feature
        fused = fuse_features(scene, vis, 4, FusionConfig())
        assert fused.seen_count.tolist() == [1, 2, 1, 0]
        np.testing.assert_allclose(fused.features[0], E0)  # not diluted by the zero pixel

    def test_float16_memmap_features(self, tmp_path: Path) -> None:
        scene, vis = _scene_two_frames()
        for fid, fmap in list(scene.features.items()):
            np.save(tmp_path / f"{fid}.npy", fmap.astype(np.float16))
            scene.features[fid] = np.load(tmp_path / f"{fid}.npy", mmap_mode="r")
        fused = fuse_features(scene, vis, 4, FusionConfig())
        np.testing.assert_allclose(fused.features[1], (E1 + E2) / 2, atol=1e-3)

    def test_non_finite_feature_is_no_observation(self) -> None:
        scene, vis = _scene_two_frames()
        scene.features["a"] = _two_region_map(np.full(D, np.nan, np.float32), E1)
        fused = fuse_features(scene, vis, 4, FusionConfig())
        assert fused.seen_count.tolist() == [1, 2, 0, 0]
        assert np.all(np.isfinite(fused.features))
        assert np.all(np.isfinite(fused.weights))

    def test_big_endian_float64_features(self) -> None:
        scene, vis = _scene_two_frames()
        scene.features = {k: v.astype(">f8") for k, v in scene.features.items()}
        fused = fuse_features(scene, vis, 4, FusionConfig())
        np.testing.assert_allclose(fused.features[1], (E1 + E2) / 2, rtol=1e-6)

    def test_feature_map_resolution_mapping(self) -> None:
        # A map at the image size (cell = pixel) and one at 1 x 1 (every pixel reads the same cell).
        rng = np.random.default_rng(0)
        full = rng.standard_normal((CAM.height, CAM.width, D)).astype(np.float32)
        scene = FakeScene(camera=CAM, frames=(_frame("a"),), features={"a": full})
        vis = _visibility({"a": [(0, 5, 7), (1, 2, 3)]})
        fused = fuse_features(scene, vis, 2, FusionConfig())
        for p, (r, c) in enumerate([(5, 7), (2, 3)]):
            np.testing.assert_allclose(fused.features[p], full[r, c] / np.linalg.norm(full[r, c]), rtol=1e-6)
        scene.features["a"] = full[:1, :1] * 2
        fused = fuse_features(scene, vis, 2, FusionConfig())
        np.testing.assert_allclose(fused.features, np.repeat(full[:1, 0] / np.linalg.norm(full[0, 0]), 2, 0),
                                   rtol=1e-6)  # fmt: skip

    def test_mask_only_frames_give_colour_not_features(self) -> None:
        scene, vis = _scene_two_frames()
        scene.frames = (_frame("a", color=True), _frame("b", features=False, color=True))
        scene.colors = {
            "a": np.full((CAM.height, CAM.width, 3), 255, np.uint8),
            "b": np.zeros((CAM.height, CAM.width, 3), np.uint8),
        }
        fused = fuse_features(scene, vis, 4, FusionConfig())
        assert fused.seen_count.tolist() == [1, 1, 1, 0]
        np.testing.assert_allclose(fused.features[1], E1)
        assert fused.colors is not None
        np.testing.assert_allclose(fused.colors[:, 0], [0.5, 0.5, 1.0, 0.0])

    def test_no_colour_frames_gives_none(self) -> None:
        scene, vis = _scene_two_frames()
        assert fuse_features(scene, vis, 4, FusionConfig()).colors is None
        scene.frames = (_frame("a", color=True), _frame("b"))
        scene.colors = {"a": np.full((CAM.height, CAM.width, 3), 51, np.uint8)}
        assert fuse_features(scene, vis, 4, FusionConfig(fuse_colors=False)).colors is None
        colors = fuse_features(scene, vis, 4, FusionConfig()).colors
        assert colors is not None
        np.testing.assert_allclose(colors[:3], 0.2, rtol=1e-6)  # only frame a has colour

    def test_progress_per_frame(self) -> None:
        scene, vis = _scene_two_frames()
        calls: list[tuple[int, int]] = []
        fuse_features(scene, vis, 4, FusionConfig(), on_progress=lambda d, t: calls.append((d, t)))
        assert calls == [(1, 2), (2, 2)]

    def test_exception(self) -> None:
        scene, vis = _scene_two_frames()
        with pytest.raises(ShapeError, match="num_points"):
            fuse_features(scene, vis, 2, FusionConfig())
        scene.features["a"] = np.ones((3, 4, D + 1), np.float32)
        with pytest.raises(ShapeError, match="features of frame a"):
            fuse_features(scene, vis, 4, FusionConfig())
        scene.frames = (_frame("a"),)
        with pytest.raises(InputError, match=r"not in the scene: \['b'\]"):
            fuse_features(scene, vis, 4, FusionConfig())


class TestConfidence:
    def test_code_form_matches_reference_formula(self) -> None:
        rng = np.random.default_rng(0)
        count = rng.integers(0, 9, 50)
        f = rng.standard_normal((50, 6)).astype(np.float32)
        f *= (rng.uniform(0.2, 1.0, 50) / np.linalg.norm(f, axis=1))[:, None]
        f[count == 0] = 0
        w = confidence_weights(f, count, FusionConfig())
        s = count.astype(np.float64)
        v = np.where(count > 0, 1 - (f.astype(np.float64) ** 2).sum(1), 0)
        ref = 10 * (s / (s.max() - s.min())) / (v / (v.max() - v.min()) + 1)
        np.testing.assert_allclose(w, ref, rtol=1e-5)

    def test_variance_identity(self) -> None:
        # 1 - |mean|^2 equals the summed population variance of unit vectors.
        rng = np.random.default_rng(1)
        obs = rng.standard_normal((7, 5))
        obs /= np.linalg.norm(obs, axis=1, keepdims=True)
        mean = obs.mean(0)
        assert np.isclose(1 - mean @ mean, obs.var(axis=0).sum())

    def test_paper_and_none(self) -> None:
        f = np.array([[1.0, 0.0], [0.6, 0.0], [0.0, 0.0]], np.float32)
        count = np.array([1, 4, 0])
        paper = confidence_weights(f, count, FusionConfig(confidence="paper", paper_variance_eps=0.01))
        np.testing.assert_allclose(paper, [1 / 0.01, 4 / 0.65, 0.0], rtol=1e-5)
        none = confidence_weights(f, count, FusionConfig(confidence="none"))
        assert none.tolist() == [1.0, 1.0, 0.0]

    def test_degenerate_ranges_stay_finite(self) -> None:
        f = np.tile(np.array([[1.0, 0.0]], np.float32), (3, 1))
        w = confidence_weights(f, np.array([2, 2, 2]), FusionConfig())
        assert np.all(np.isfinite(w))
        np.testing.assert_allclose(w, 10.0)


class TestFeatureCells:
    @pytest.mark.parametrize(
        ("h", "w", "hf", "wf"),
        [(480, 640, 60, 80), (480, 640, 120, 160), (6, 8, 3, 4), (7, 5, 3, 2), (4, 4, 9, 9)],
    )
    def test_matches_float_formula(self, h: int, w: int, hf: int, wf: int) -> None:
        rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
        cells = feature_cells(rows.ravel(), cols.ravel(), (h, w), (hf, wf))
        r = np.floor((rows.ravel() + 0.5) * hf / h).astype(int)
        c = np.floor((cols.ravel() + 0.5) * wf / w).astype(int)
        assert np.array_equal(cells, r * wf + c)


class TestFusedFeaturesData:
    @pytest.mark.parametrize("with_colors", [True, False])
    def test_save_load_round_trip(self, tmp_path: Path, with_colors: bool) -> None:
        fused = FusedFeatures(
            features=np.ones((3, D), np.float32),
            weights=np.array([1, 0, 2], np.float32),
            seen_count=np.array([1, 0, 2], np.int32),
            colors=np.full((3, 3), 0.5, np.float32) if with_colors else None,
        )
        fused.save(tmp_path / "f.tmp")
        back = FusedFeatures.load(tmp_path / "f.tmp")
        assert np.array_equal(back.features, fused.features)
        assert np.array_equal(back.weights, fused.weights)
        assert np.array_equal(back.seen_count, fused.seen_count)
        assert (back.colors is None) == (not with_colors)

    def test_exception(self) -> None:
        with pytest.raises(ShapeError, match="weights"):
            FusedFeatures(features=np.ones((3, D), np.float32), weights=np.ones(2, np.float32),
                          seen_count=np.ones(3, np.int32), colors=None)  # fmt: skip


class TestFusionConfig:
    @pytest.mark.parametrize(
        ("name", "value"),
        [("confidence", "paperish"), ("weight_scale", 0.0), ("paper_variance_eps", -1.0),
         ("min_feature_norm", float("inf"))],
    )  # fmt: skip
    def test_exception(self, name: str, value: object) -> None:
        with pytest.raises(ConfigError, match=f"fusion.{name}"):
            FusionConfig(**{name: value})  # type: ignore[arg-type]

    def test_default_is_code_form(self) -> None:
        assert FusionConfig().confidence == "code"


class TestFusionOnABundle:
    def test_end_to_end_with_written_bundle(self, tmp_path: Path) -> None:
        # A wall at z = 2 m seen by one camera; features: left half e0, right half e1 (float16 on disk).
        from panogs_core.io.bundle import open_bundle
        from panogs_core.io.bundle.writer import BundleWriter
        from panogs_core.stages.visibility import VisibilityConfig, compute_visibility

        writer = BundleWriter(tmp_path / "b", name="wall", camera=CAM, feature_dim=D, feature_space="test")
        depth = np.full((CAM.height, CAM.width), 2.0)
        color = np.zeros((CAM.height, CAM.width, 3), np.uint8)
        color[:, :, 1] = 255
        fmap = _two_region_map(E0, E1).astype(np.float16)
        masks = np.ones((CAM.height, CAM.width), np.int32)
        writer.add_frame("0", np.eye(4), depth, color=color, features=fmap, masks=masks)
        scene = open_bundle(writer.close())
        points = np.array([[-0.5, 0.0, 2.0], [0.5, 0.0, 2.0], [0.0, 0.0, 5.0]], np.float32)  # u = 2.5, 4.0
        vis = compute_visibility(scene, points, VisibilityConfig())
        fused = fuse_features(scene, vis, 3, FusionConfig(mask_pooling=0.0))  # one mask over both halves
        np.testing.assert_allclose(fused.features, [E0, E1, np.zeros(D)], atol=1e-3)
        assert fused.seen_count.tolist() == [1, 1, 0]
        assert fused.colors is not None
        np.testing.assert_allclose(fused.colors[:2], [[0, 1, 0], [0, 1, 0]], atol=0.02)


@dataclass
class MaskedScene(FakeScene):
    """A FakeScene whose frames have 2D masks."""

    masks: dict[str, np.ndarray] = field(default_factory=dict)

    def read_masks(self, frame: Frame) -> np.ndarray:
        return self.masks[frame.id]


class TestMaskPooling:
    """docs/method.md §3.1: a feature cell on an object border bleeds; the object's mask pools its pure cells."""

    def _scene(self) -> tuple[MaskedScene, Visibility]:
        bleed = 0.4 * E0 + 0.6 * E1
        fmap = _two_region_map(E0, E1)  # cells of image columns 0-3 hold e0, 4-7 hold e1
        fmap[:, 1] = bleed / np.linalg.norm(bleed)  # ... but the cells of columns 2-3 lean to e1
        masks = np.where(np.arange(8)[None, :] < 4, 1, 2).repeat(6, axis=0).astype(np.int32)  # the objects
        scene = MaskedScene(camera=CAM, frames=(_frame("a"),), features={"a": fmap}, masks={"a": masks})
        return scene, _visibility({"a": [(0, 2, 3), (1, 2, 6)]})  # point 0 in the bleeding cell

    def test_pooling_pulls_a_border_primitive_to_its_object(self) -> None:
        scene, vis = self._scene()
        plain = fuse_features(scene, vis, 2, FusionConfig(mask_pooling=0.0))
        pooled = fuse_features(scene, vis, 2, FusionConfig(mask_pooling=0.8))
        assert np.argmax(plain.features[0]) == 1  # the bled feature
        assert np.argmax(pooled.features[0]) == 0  # its mask's feature
        assert np.linalg.norm(pooled.features[0]) == pytest.approx(1.0, abs=1e-5)  # blended rows stay unit
        assert np.argmax(pooled.features[1]) == 1  # inside the other object nothing changes
        np.testing.assert_array_equal(pooled.seen_count, plain.seen_count)

    def test_pooled_features_weight_pure_cells(self) -> None:
        from panogs_core.stages.fusion import mask_pooled_features

        fmap = np.stack([np.eye(2, dtype=np.float32)])  # (1, 2, 2): cell 0 = e0, cell 1 = e1
        masks = np.array([[1, 1, 1, 0]])  # mask 1 covers all of cell 0 and half of cell 1
        pooled, has = mask_pooled_features(fmap, masks)
        assert has.tolist() == [False, True]
        assert pooled[1, 0] > 3 * pooled[1, 1]  # the half-covered cell counts a quarter as much

    def test_config_range(self) -> None:
        with pytest.raises(ConfigError, match="mask_pooling"):
            FusionConfig(mask_pooling=1.5)


class TestBlockwiseRows:
    """The rows read block by block (``_frame_rows``) equal those read from the whole float32 map, to the bit."""

    @staticmethod
    def _whole_map(
        fmap: np.ndarray, src: np.ndarray, masks: np.ndarray | None, pixel: np.ndarray, weight: float
    ) -> tuple[np.ndarray, np.ndarray]:
        from panogs_core.stages import fusion

        cells, inv_norm = fusion._cells_and_inverse_norms(fmap, 1e-6)
        if masks is None:
            cell, index = np.unique(src, return_inverse=True)
            return cells[cell] * inv_norm[cell, None], index
        dense, values = fusion._dense_mask_ids(masks)
        pair, index = np.unique(src * len(values) + dense[pixel], return_inverse=True)
        cell, mask = pair // len(values), pair % len(values)
        cell_of_pixel = fusion.mask_pixel_cells(masks.shape, fmap.shape[:2])
        pooled = fusion._pool_cells(cells, inv_norm, dense, len(values), cell_of_pixel)
        table = cells[cell] * ((1.0 - weight) * inv_norm[cell])[:, None]
        return table + (weight * pooled)[mask], index

    @pytest.mark.parametrize("dtype", [np.float16, np.float32])
    @pytest.mark.parametrize("pooling", [0.0, 0.5])
    def test_identical_to_whole_map(self, monkeypatch: pytest.MonkeyPatch, dtype: type, pooling: float) -> None:
        from panogs_core.stages import fusion

        monkeypatch.setattr(fusion, "_BLOCK", 64)  # 9 blocks, the last one partial
        rng = np.random.default_rng(3)
        hf, wf, hm, wm = 23, 25, 46, 50
        fmap = rng.standard_normal((hf, wf, 8)).astype(dtype)
        fmap[0, 3] = 0.0  # no feature
        fmap[5, 7, 2] = np.nan  # not finite
        masks = rng.choice([0, 7, 9, 60000], size=(hm, wm)).astype(np.int32)
        masks[10:30, 5:40] = 9  # a big mask over many blocks
        pixel = rng.integers(0, hm * wm, 300)
        src = fusion.feature_cells(pixel // wm, pixel % wm, (hm, wm), (hf, wf))
        args = None if pooling == 0.0 else (masks, pixel, pooling)
        table, index = fusion._frame_rows(fmap, src, 1e-6, fusion._CellBuffers(), args)
        expected, expected_index = self._whole_map(fmap, src, None if pooling == 0.0 else masks, pixel, pooling)
        np.testing.assert_array_equal(index, expected_index)
        assert table.tobytes() == expected.astype(np.float32).tobytes()

    def test_a_frame_takes_one_row_buffer(self, monkeypatch: pytest.MonkeyPatch) -> None:
        """The masks' pooled features are added through the block buffer: a frame holds one (U, D) buffer of rows
        (three frames are in flight on two threads; where a frame's rows are about its map's cells, a second
        buffer was 40 MB a frame at 160 x 120 x 512)."""
        import tracemalloc

        from panogs_core.stages import fusion

        monkeypatch.setattr(fusion, "_BLOCK", 64)
        rng = np.random.default_rng(4)
        hf, wf, hm, wm = 40, 50, 80, 100
        fmap = rng.standard_normal((hf, wf, 512)).astype(np.float16)
        masks = rng.choice([0, 3, 4], size=(hm, wm)).astype(np.int32)
        pixel = np.arange(hm * wm)  # every pixel: about three rows a cell
        src = fusion.feature_cells(pixel // wm, pixel % wm, (hm, wm), (hf, wf))
        tracemalloc.start()
        try:
            table, _ = fusion._frame_rows(fmap, src, 1e-6, fusion._CellBuffers(), (masks, pixel, 0.5))
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert table.shape[0] > 2 * hf * wf  # rows per (cell, mask) pair
        assert peak < 1.5 * table.nbytes, (peak, table.nbytes)


@pytest.mark.parametrize("workers", [2, 3])
def test_frames_on_threads_give_the_sequential_result(monkeypatch: pytest.MonkeyPatch, workers: int) -> None:
    """The frames' rows made on threads, summed in frame order: the same bits as one frame after the other."""
    from panogs_core.stages import fusion

    rng = np.random.default_rng(5)
    frames = tuple(_frame(f"f{i}", color=True) for i in range(7))
    scene = MaskedScene(
        camera=CAM,
        frames=frames,
        features={f.id: rng.standard_normal((3, 4, D)).astype(np.float16) for f in frames},
        colors={f.id: rng.integers(0, 256, (6, 8, 3), dtype=np.uint8) for f in frames},
        masks={f.id: rng.integers(0, 3, (6, 8)).astype(np.int32) for f in frames},
    )
    seen = {f.id: sorted({(int(p), int(p) % 6, int(p) % 8) for p in rng.choice(20, 12, replace=False)}) for f in frames}
    vis = _visibility(seen)
    monkeypatch.setattr(fusion, "decode_threads", lambda: 1)
    one = fuse_features(scene, vis, 20, FusionConfig())
    monkeypatch.setattr(fusion, "decode_threads", lambda: workers)
    many = fuse_features(scene, vis, 20, FusionConfig())
    assert one.colors is not None
    assert many.colors is not None
    for a, b in ((one.features, many.features), (one.weights, many.weights), (one.colors, many.colors)):
        assert a.tobytes() == b.tobytes()
    np.testing.assert_array_equal(one.seen_count, many.seen_count)


@pytest.mark.parametrize("order", ["ascending", "shuffled"])
def test_frame_rows_add_as_an_indexed_add_would(order: str) -> None:
    """Each seen primitive gets its row added once a frame, in frame order, whatever order the frame lists them in:
    the same bits as ``sum[targets] += table[rows]`` frame after frame."""
    from panogs_core.stages.fusion import _CellBuffers, _FeatureSum, _FrameRows

    rng = np.random.default_rng(3)
    num_points, dim = 50, 6
    sums, expected = _FeatureSum(num_points, dim), np.zeros((num_points, dim), np.float32)
    seen = []
    for _ in range(4):
        table = rng.normal(size=(7, dim)).astype(np.float32)
        targets = np.sort(rng.choice(num_points, 20, replace=False)).astype(np.int64)
        if order == "shuffled":
            targets = rng.permutation(targets)
        rows = rng.integers(0, 7, 20).astype(np.int64)
        sums.add(_FrameRows(table=table, targets=targets, rows=rows, buffers=_CellBuffers()))
        expected[targets] += table[rows]
        seen.append(targets)
    np.testing.assert_array_equal(sums.total, expected)
    np.testing.assert_array_equal(np.bincount(np.concatenate(seen), minlength=num_points), sums.count)
