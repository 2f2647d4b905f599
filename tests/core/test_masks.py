"""The mask look-ups: which mask id each key frame sees under each primitive it sees, and their checkpoint."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from panogs_core.errors import ConfigError, InputError, ShapeError
from panogs_core.stages.affinity import AffinityConfig
from panogs_core.stages.masks import MaskLookupConfig, MaskObservations, observe_masks
from panogs_core.stages.visibility import Visibility
from panogs_core.types import Camera, Frame


@dataclass(frozen=True)
class _FakeScene:
    """The three things observe_masks reads from a Scene."""

    camera: Camera
    frames: tuple[Frame, ...]
    masks: dict[str, np.ndarray]

    def read_masks(self, frame: Frame) -> np.ndarray:
        return self.masks[frame.id]


def _frame(fid: str, masks: bool = True) -> Frame:
    return Frame(id=fid, T_world_cam=np.eye(4), depth=f"{fid}.png", masks=f"{fid}_m.png" if masks else None)


class TestObserveMasks:
    def _scene(self) -> tuple[_FakeScene, Visibility]:
        camera = Camera(width=8, height=6, fx=1.0, fy=1.0, cx=4.0, cy=3.0)
        full = np.arange(48, dtype=np.int32).reshape(6, 8) % 5  # ids 0..4, same size as the camera
        half = np.array([[1, 2, 0, 3], [4, 5, 6, 0], [7, 8, 9, 10]], dtype=np.int32)  # (3, 4): 2x2 blocks
        scene = _FakeScene(
            camera=camera,
            frames=(_frame("a"), _frame("b", masks=False), _frame("c")),
            masks={"a": full, "c": half},
        )
        vis = Visibility(
            frame_ids=("a", "b", "c"),
            offsets=np.array([0, 3, 4, 8], dtype=np.int64),
            point_index=np.array([0, 1, 2, 5, 3, 4, 6, 7], dtype=np.int32),
            pixel_row=np.array([0, 0, 5, 2, 0, 1, 3, 5], dtype=np.int32),
            pixel_col=np.array([0, 1, 7, 2, 2, 3, 6, 5], dtype=np.int32),
        )
        return scene, vis

    def test_smoke(self) -> None:
        scene, vis = self._scene()
        calls: list[tuple[int, int]] = []
        obs = observe_masks(scene, vis, on_progress=lambda d, t: calls.append((d, t)))
        assert obs.num_frames == 2  # frame b has no mask
        assert calls == [(1, 2), (2, 2)]

    def test_feature(self) -> None:
        scene, vis = self._scene()
        obs = observe_masks(scene, vis)
        # frame a: pixels (0,0) -> 0 (dropped), (0,1) -> 1, (5,7) -> 47 % 5 = 2.
        np.testing.assert_array_equal(obs.point_index[: obs.offsets[1]], [1, 2])
        np.testing.assert_array_equal(obs.label[: obs.offsets[1]], [1, 2])
        # frame c, mask (3, 4) under a (6, 8) camera: pixel (v, u) reads cell (v // 2, u // 2).
        # (0,2) -> [0,1] = 2; (1,3) -> [0,1] = 2; (3,6) -> [1,3] = 0 dropped; (5,5) -> [2,2] = 9.
        lo = obs.offsets[1]
        np.testing.assert_array_equal(obs.point_index[lo:], [3, 4, 7])
        np.testing.assert_array_equal(obs.label[lo:], [2, 2, 9])
        assert obs.point_index.dtype == np.int32
        assert obs.label.dtype == np.int32

    def test_depth_residual_filter(self) -> None:
        # Frame c (4 observations): the residuals spread +-0.1 % except point 7 at +5 %, a surface hidden
        # behind the one the sensor saw: with the filter on it must not read the mask in front of it. Off
        # (the default, mad 0), it does.
        scene, vis = self._scene()
        residual = np.array([0.0, 0.001, -0.001, 0.0, 0.001, -0.001, 0.0, 0.05], dtype=np.float16)
        vis = Visibility(vis.frame_ids, vis.offsets, vis.point_index, vis.pixel_row, vis.pixel_col, residual)
        on = MaskLookupConfig(depth_mad=3.0)
        obs = observe_masks(scene, vis, on)
        np.testing.assert_array_equal(obs.point_index[obs.offsets[1] :], [3, 4])
        off = observe_masks(scene, vis)
        np.testing.assert_array_equal(off.point_index[off.offsets[1] :], [3, 4, 7])
        # The floor keeps a tolerance when every residual is the same (MAD 0): 0.5 % passes a 1 % floor.
        flat = np.zeros(8, dtype=np.float16)
        flat[7] = 0.005
        vis = Visibility(vis.frame_ids, vis.offsets, vis.point_index, vis.pixel_row, vis.pixel_col, flat)
        np.testing.assert_array_equal(observe_masks(scene, vis, on).point_index[obs.offsets[1] :], [3, 4, 7])

    def test_cell_rounding(self) -> None:
        # A 4-row mask under a 6-row camera: pixel row v reads mask row floor((v + 0.5) * 4 / 6).
        camera = Camera(width=1, height=6, fx=1.0, fy=1.0, cx=0.0, cy=0.0)
        mask = np.array([[1], [2], [3], [4]], dtype=np.int32)
        scene = _FakeScene(camera=camera, frames=(_frame("a"),), masks={"a": mask})
        rows = np.arange(6, dtype=np.int32)
        vis = Visibility(
            frame_ids=("a",),
            offsets=np.array([0, 6], dtype=np.int64),
            point_index=rows.copy(),
            pixel_row=rows,
            pixel_col=np.zeros(6, dtype=np.int32),
        )
        obs = observe_masks(scene, vis)
        expected = [math.floor((v + 0.5) * 4 / 6) + 1 for v in range(6)]
        np.testing.assert_array_equal(obs.label, expected)

    def test_exception(self) -> None:
        scene, vis = self._scene()
        other = Visibility(
            frame_ids=("zz",),
            offsets=np.array([0, 0], dtype=np.int64),
            point_index=np.zeros(0, np.int32),
            pixel_row=np.zeros(0, np.int32),
            pixel_col=np.zeros(0, np.int32),
        )
        with pytest.raises(InputError, match=r"observe_masks: visibility names frame\(s\) \['zz'\]"):
            observe_masks(scene, other)
        bad = _FakeScene(camera=scene.camera, frames=scene.frames, masks={"a": np.zeros(5, np.int32)})
        with pytest.raises(ShapeError, match=r"frame 'a': expected a \(Hm, Wm\) mask, found \(5,\)"):
            observe_masks(bad, vis)

    def test_save_load(self, tmp_path: Path) -> None:
        scene, vis = self._scene()
        obs = observe_masks(scene, vis)
        obs.save(tmp_path / "obs")
        back = MaskObservations.load(tmp_path / "obs")
        for name in ("offsets", "point_index", "label"):
            np.testing.assert_array_equal(getattr(back, name), getattr(obs, name))

    def test_contract(self) -> None:
        with pytest.raises(ShapeError, match="offsets must rise from 0 to T = 2"):
            MaskObservations(offsets=np.array([0, 1]), point_index=np.zeros(2, np.int32), label=np.ones(2, np.int32))


class TestMaskLookupConfig:
    def test_the_affinity_section_holds_the_lookup_settings(self) -> None:
        lookup = AffinityConfig(mask_depth_mad=2.5, mask_depth_floor=0.02).mask_lookup()
        assert lookup == MaskLookupConfig(depth_mad=2.5, depth_floor=0.02)
        assert AffinityConfig().mask_lookup() == MaskLookupConfig()  # off by default

    @pytest.mark.parametrize(
        ("kwargs", "match"),
        [
            ({"depth_mad": -1.0}, r"affinity\.mask_depth_mad: expected a number >= 0, found -1\.0"),
            ({"depth_floor": 0.0}, r"affinity\.mask_depth_floor: expected a number > 0, found 0\.0"),
        ],
    )
    def test_exception(self, kwargs: dict, match: str) -> None:
        with pytest.raises(ConfigError, match=match):
            MaskLookupConfig(**kwargs)
