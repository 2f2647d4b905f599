"""Tests of stage 4: the tri-plane language field (known-answer regions, determinism, save/load)."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import pytest
from torch_threads import one_torch_thread  # noqa: F401  (autouse fixture: small tensors)

from panogs_core.errors import Cancelled, ConfigError, InputError, ShapeError
from panogs_core.stages.language_field import (
    LanguageField,
    LanguageFieldConfig,
    decode_points,
    field_bounds,
    fit_language_field,
    plane_resolutions,
)

DIM = 16


@dataclass(frozen=True)
class _Fused:
    """Stand-in with the fields of ``panogs_core.stages.fusion.FusedFeatures`` that the field reads."""

    features: np.ndarray  # (N, D) float32
    weights: np.ndarray  # (N,) float32
    seen_count: np.ndarray  # (N,) int32
    colors: np.ndarray | None = None


def _small_cfg(**overrides: object) -> LanguageFieldConfig:
    settings: dict[str, object] = {
        "cell_sizes": (0.5, 0.2),
        "hidden_dims": (32,),
        "epochs": 10,
        "batch_size": 256,
        "min_steps": 0,
        "lr": 1e-2,
        "plane_lr": 3e-2,
        "seed": 0,
    }
    settings.update(overrides)
    return LanguageFieldConfig(**settings)  # type: ignore[arg-type]


def _three_regions(n_per: int = 400, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Three 1 m boxes along x (gaps of 1 m), each with its own constant unit feature."""
    rng = np.random.default_rng(seed)
    region = np.repeat(np.arange(3), n_per)
    points = rng.uniform(0, 1, (3 * n_per, 3)) + np.c_[region * 2.0, np.zeros((3 * n_per, 2))]
    anchors = rng.normal(size=(3, DIM))
    anchors /= np.linalg.norm(anchors, axis=1, keepdims=True)
    return points.astype(np.float32), region, anchors.astype(np.float32)


def _fused(features: np.ndarray, weights: np.ndarray) -> _Fused:
    return _Fused(
        features=features.astype(np.float32),
        weights=weights.astype(np.float32),
        seen_count=(weights > 0).astype(np.int32),
    )


@pytest.fixture(scope="module")
def regions_field() -> tuple[LanguageField, np.ndarray, np.ndarray, np.ndarray]:
    points, region, anchors = _three_regions()
    field = fit_language_field(points, _fused(anchors[region], np.ones(len(points))), _small_cfg())
    return field, points, region, anchors


class TestFitLanguageField:
    def test_smoke(self, regions_field) -> None:
        field, points, _, _ = regions_field
        assert isinstance(field, LanguageField)
        assert field.features.shape == (points.shape[0], DIM)
        assert field.features.dtype == np.float32
        assert field.bounds.shape == (2, 3)
        assert field.bounds.dtype == np.float32
        np.testing.assert_allclose(np.linalg.norm(field.features, axis=1), 1.0, atol=1e-5)
        assert field.dim == DIM
        assert sorted(field.state) == ["mlp.0", "mlp.1", "planes.0", "planes.1"]
        assert field.state["mlp.0"].shape == (32, 10)
        assert field.state["mlp.1"].shape == (DIM, 32)

    def test_recovers_region_features(self, regions_field) -> None:
        field, _, region, anchors = regions_field
        cos = (field.features * anchors[region]).sum(axis=1)
        assert cos.min() > 0.95

    def test_zero_weight_points_are_ignored(self) -> None:
        points, region, anchors = _three_regions(n_per=150, seed=1)
        rng = np.random.default_rng(2)
        unseen = rng.random(len(points)) < 0.3
        weights = np.where(unseen, 0.0, 1.0)
        targets_a = np.where(unseen[:, None], rng.normal(size=(len(points), DIM)), anchors[region])
        targets_b = np.where(unseen[:, None], 0.0, anchors[region])
        cfg = _small_cfg(epochs=3)
        field_a = fit_language_field(points, _fused(targets_a, weights), cfg)
        field_b = fit_language_field(points, _fused(targets_b, weights), cfg)
        for key in field_a.state:
            np.testing.assert_array_equal(field_a.state[key], field_b.state[key])

    def test_cpu_threads_during_the_fit_then_restored(self) -> None:
        import torch

        points, region, anchors = _three_regions(n_per=50, seed=3)
        fused = _fused(anchors[region], np.ones(len(points)))
        seen: list[int] = []
        before = torch.get_num_threads()
        torch.set_num_threads(2)
        try:
            fit_language_field(
                points, fused, _small_cfg(epochs=1), on_progress=lambda *_: seen.append(torch.get_num_threads())
            )
            assert seen == [1]  # the default: one thread
            assert torch.get_num_threads() == 2
            seen.clear()
            fit_language_field(
                points,
                fused,
                _small_cfg(epochs=1, cpu_threads=None),
                on_progress=lambda *_: seen.append(torch.get_num_threads()),
            )
            assert seen == [2]
        finally:
            torch.set_num_threads(before)

    def test_the_decoding_takes_the_callers_threads_and_the_same_bits_at_any_count(self) -> None:
        """The fit's steps run at ``cpu_threads``; the decoding of every primitive (large products, row by row) runs
        at the caller's count, which must not move a bit of the features."""
        import torch

        points, region, anchors = _three_regions(n_per=50, seed=3)
        field = fit_language_field(points, _fused(anchors[region], np.ones(len(points))), _small_cfg(epochs=1))
        queries = np.random.default_rng(1).uniform(0, 5, (20_000, 3)).astype(np.float32)
        before = torch.get_num_threads()
        decoded = {}
        try:
            for threads in (1, 2):
                torch.set_num_threads(threads)
                decoded[threads] = decode_points(field, queries)
        finally:
            torch.set_num_threads(before)
        np.testing.assert_array_equal(decoded[1], decoded[2])
        assert decoded[1].flags.writeable
        assert decoded[1].dtype == np.float32

    def test_deterministic_for_a_seed(self) -> None:
        points, region, anchors = _three_regions(n_per=100, seed=3)
        fused = _fused(anchors[region], np.ones(len(points)))
        first = fit_language_field(points, fused, _small_cfg(epochs=2))
        second = fit_language_field(points, fused, _small_cfg(epochs=2))
        other = fit_language_field(points, fused, _small_cfg(epochs=2, seed=1))
        for key in first.state:
            np.testing.assert_array_equal(first.state[key], second.state[key])
        np.testing.assert_array_equal(first.features, second.features)
        assert not np.array_equal(first.state["planes.0"], other.state["planes.0"])

    def test_progress_per_epoch_and_cancel(self) -> None:
        points, region, anchors = _three_regions(n_per=50, seed=4)
        fused = _fused(anchors[region], np.ones(len(points)))
        calls: list[tuple[int, int]] = []
        cfg = _small_cfg(epochs=3, min_steps=0)
        fit_language_field(points, fused, cfg, on_progress=lambda d, t: calls.append((d, t)))
        assert calls == [(1, 3), (2, 3), (3, 3)]

    def test_min_steps_adds_epochs_on_small_scenes(self) -> None:
        points, region, anchors = _three_regions(n_per=50, seed=4)  # 150 points: one step per epoch
        fused = _fused(anchors[region], np.ones(len(points)))
        calls: list[tuple[int, int]] = []
        cfg = _small_cfg(epochs=2, min_steps=5, batch_size=1024)
        fit_language_field(points, fused, cfg, on_progress=lambda d, t: calls.append((d, t)))
        assert calls[-1] == (5, 5)

        def cancel(done: int, total: int) -> None:
            raise Cancelled("stop")

        with pytest.raises(Cancelled):
            fit_language_field(points, fused, _small_cfg(epochs=3), on_progress=cancel)

    def test_exception(self) -> None:
        points, region, anchors = _three_regions(n_per=20, seed=5)
        cfg = _small_cfg(epochs=1)
        good = _fused(anchors[region], np.ones(len(points)))
        with pytest.raises(ShapeError, match="points"):
            fit_language_field(points[:, :2], good, cfg)
        with pytest.raises(ShapeError, match=r"fused\.features"):
            fit_language_field(points[:10], good, cfg)
        with pytest.raises(ShapeError, match=r"fused\.weights"):
            fit_language_field(points, _fused(anchors[region], np.ones(5)), cfg)
        with pytest.raises(InputError, match="every weight is 0"):
            fit_language_field(points, _fused(anchors[region], np.zeros(len(points))), cfg)
        with pytest.raises(InputError, match=r"fused\.weights"):
            fit_language_field(points, _fused(anchors[region], -np.ones(len(points))), cfg)
        bad = points.copy()
        bad[0, 0] = np.nan
        with pytest.raises(InputError, match="NaN"):
            fit_language_field(bad, good, cfg)

    def test_accepts_fusion_output(self) -> None:
        from panogs_core.stages.fusion import FusedFeatures

        points, region, anchors = _three_regions(n_per=50, seed=6)
        fused = FusedFeatures(
            features=anchors[region],
            weights=np.ones(len(points), np.float32),
            seen_count=np.ones(len(points), np.int32),
            colors=None,
        )
        field = fit_language_field(points, fused, _small_cfg(epochs=1))
        assert field.features.shape == (len(points), DIM)


class TestDecodePoints:
    def test_new_points_inside_regions(self, regions_field) -> None:
        field, _, _, anchors = regions_field
        points, region, _ = _three_regions(n_per=100, seed=9)  # new positions, same boxes
        decoded = decode_points(field, points)
        assert decoded.shape == (300, DIM)
        assert decoded.dtype == np.float32
        np.testing.assert_allclose(np.linalg.norm(decoded, axis=1), 1.0, atol=1e-5)
        assert (decoded * anchors[region]).sum(axis=1).min() > 0.95

    def test_training_points_match_fit_features(self, regions_field) -> None:
        field, points, _, _ = regions_field
        np.testing.assert_allclose(decode_points(field, points), field.features, atol=1e-6)

    def test_outside_box_is_finite_unit(self, regions_field) -> None:
        field, _, _, _ = regions_field
        far = np.array([[-100.0, 0, 0], [100.0, 100.0, 100.0]], np.float32)
        decoded = decode_points(field, far)
        assert np.isfinite(decoded).all()
        np.testing.assert_allclose(np.linalg.norm(decoded, axis=1), 1.0, atol=1e-5)

    def test_save_load_round_trip(self, regions_field, tmp_path) -> None:
        field, points, _, _ = regions_field
        path = tmp_path / "field.npz"
        field.save(path)
        with np.load(path, allow_pickle=False) as data:
            assert "state.planes.0" in data.files
            assert "features" in data.files
        loaded = LanguageField.load(path)
        assert sorted(loaded.state) == sorted(field.state)
        np.testing.assert_array_equal(loaded.features, field.features)
        np.testing.assert_array_equal(loaded.bounds, field.bounds)
        query = points[::7] + 0.01
        bare = tmp_path / "field_without_suffix"
        field.save(bare)
        np.testing.assert_array_equal(LanguageField.load(bare).features, field.features)
        np.testing.assert_array_equal(decode_points(loaded, query), decode_points(field, query))

    def test_exception(self, regions_field) -> None:
        field, _, _, _ = regions_field
        with pytest.raises(ShapeError, match="points"):
            decode_points(field, np.zeros((4, 2), np.float32))
        with pytest.raises(InputError, match="state"):
            decode_points(LanguageField(features=field.features, bounds=field.bounds, state={}), np.zeros((1, 3)))


class TestGeometry:
    def test_bounds_and_resolutions(self) -> None:
        points = np.array([[0, 0, 0], [4.0, 2.0, 1.0]], np.float32)
        bounds = field_bounds(points, 0.5)
        np.testing.assert_array_equal(bounds, [[-0.5, -0.5, -0.5], [4.5, 2.5, 1.5]])
        cfg = LanguageFieldConfig(cell_sizes=(0.25, 0.0625), max_resolution=50)
        assert plane_resolutions(bounds, cfg) == [20, 50]  # max extent 5 m: 5 / 0.25 = 20; 80 capped to 50

    def test_flat_axis_gets_a_box(self) -> None:
        points = np.array([[0, 0, 1.0], [1.0, 1.0, 1.0]], np.float32)
        bounds = field_bounds(points, 0.0)
        assert (bounds[1] > bounds[0]).all()

    def test_gathered_corners_sample_as_grid_sample(self) -> None:
        # Training gathers each point's bilinear corners from one table; decoding uses grid_sample on the planes.
        # Both must give the same latent, on the box's faces and corners too, and the table must map back.
        import torch

        from panogs_core.stages.language_field.corners import (
            BatchCorners,
            add_table_gradient,
            bilinear_corners,
            gathered_latent,
            plane_table,
            planes_from_table,
        )
        from panogs_core.stages.language_field.triplane import init_model

        resolutions = [3, 7]
        model = init_model(resolutions, 4, LanguageFieldConfig(channels=5, hidden_dims=(8,)))
        rng = np.random.default_rng(0)
        coords = rng.uniform(-1, 1, size=(300, 3)).astype(np.float32)
        coords[:8] = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T  # the box's corners
        coords[8:20, 1] = 1.0  # a face
        coords_t = torch.from_numpy(coords)
        table = plane_table(list(model.planes))
        assert table.shape == (3 * (9 + 49), 5)
        cells, weights = bilinear_corners(coords_t, resolutions)
        assert cells.shape == weights.shape == (300, 24)
        assert int(cells.min()) >= 0
        assert int(cells.max()) < table.shape[0]
        np.testing.assert_allclose(weights.sum(dim=1).numpy(), 6.0, atol=1e-5)  # 4 corners x 3 planes x 2 levels
        with torch.no_grad():
            expected = model.encode(coords_t).numpy()
            gathered = gathered_latent(table, cells, weights).numpy()
        np.testing.assert_allclose(gathered, expected, atol=1e-5)
        for plane, back in zip(model.planes, planes_from_table(table, resolutions), strict=True):
            assert torch.equal(plane.detach(), back)

        # The table's gradient written by hand is autograd's gradient of the gathered latent.
        upstream = torch.from_numpy(rng.normal(size=(300, 5)).astype(np.float32))
        leaf = table.detach().clone().requires_grad_(True)
        (gathered_latent(leaf, cells, weights) * upstream).sum().backward()
        by_hand = torch.full_like(table, 7.0)  # stale values: the buffer is overwritten, not added to
        add_table_gradient(by_hand, cells, weights, upstream)
        assert leaf.grad is not None
        np.testing.assert_allclose(by_hand.numpy(), leaf.grad.numpy(), atol=1e-5)

        # The CPU training path (sparse products of the corner weights) gives the same latent and gradient.
        batch = BatchCorners(table)
        assert batch.on_cpu
        np.testing.assert_allclose(batch.latent(cells, weights).numpy(), expected, atol=1e-5)
        np.testing.assert_allclose(batch.table_gradient(upstream).numpy(), leaf.grad.numpy(), atol=1e-5)


class TestTraining:
    """The training step's hand-written parts against torch's own: autograd's gradients, torch.optim.Adam."""

    # Outputs of 4 take the last layer through the prediction (D < 2 H), of 20 through the Gram matrix.
    @pytest.mark.parametrize("out_dim", [4, 20])
    @pytest.mark.parametrize("hidden", [(8,), (8, 6)])
    def test_gradients_are_autograds(self, hidden: tuple[int, ...], out_dim: int) -> None:
        import torch

        from panogs_core.stages.language_field.triplane import _cosine_loss_and_gradients

        gen = torch.Generator().manual_seed(0)
        widths = [5, *hidden, out_dim]
        mlp = [torch.randn((o, i), generator=gen, dtype=torch.float64) for i, o in itertools.pairwise(widths)]
        latent = torch.randn((40, 5), generator=gen, dtype=torch.float64)
        targets = torch.randn((40, out_dim), generator=gen, dtype=torch.float64) * 3.0  # not unit: scaled inside
        weights = torch.rand(40, generator=gen, dtype=torch.float64)
        loss, latent_grad, grads = _cosine_loss_and_gradients(mlp, latent, targets, 1 / targets.norm(dim=1), weights)

        leaves = [w.clone().requires_grad_(True) for w in mlp]
        x = latent.clone().requires_grad_(True)
        h = x
        for w in leaves[:-1]:
            h = torch.relu(h @ w.t())
        expected = (weights * (1 - torch.cosine_similarity(h @ leaves[-1].t(), targets, dim=1))).mean()
        expected.backward()
        assert float(loss) == pytest.approx(float(expected.detach()), rel=1e-12)
        assert x.grad is not None
        np.testing.assert_allclose(latent_grad.numpy(), x.grad.numpy(), rtol=1e-9, atol=1e-14)
        for by_hand, leaf in zip(grads, leaves, strict=True):
            assert leaf.grad is not None
            np.testing.assert_allclose(by_hand.numpy(), leaf.grad.numpy(), rtol=1e-9, atol=1e-14)

    def test_both_forms_of_the_last_layer_agree(self) -> None:
        import torch

        from panogs_core.stages.language_field.triplane import _last_layer_by_gram, _last_layer_by_prediction

        gen = torch.Generator().manual_seed(2)
        h = torch.relu(torch.randn((50, 8), generator=gen, dtype=torch.float64))
        h[3] = 0.0  # a zero prediction: the 1e-8 floor, no gradient through the norm
        last = torch.randn((6, 8), generator=gen, dtype=torch.float64)
        targets = torch.randn((50, 6), generator=gen, dtype=torch.float64) * 2.0
        weights = torch.rand(50, generator=gen, dtype=torch.float64)
        by_prediction = _last_layer_by_prediction(h, last, targets, 1 / targets.norm(dim=1), weights)
        by_gram = _last_layer_by_gram(h, last, targets, 1 / targets.norm(dim=1), weights)
        assert float(by_prediction[0]) == pytest.approx(float(by_gram[0]), rel=1e-12)
        for a, b in zip(by_prediction[1:], by_gram[1:], strict=True):
            np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=1e-9, atol=1e-14)

    @pytest.mark.parametrize("fused", [True, False])
    def test_adam_is_torchs(self, fused: bool) -> None:
        import torch

        from panogs_core.stages.language_field.triplane import _Adam

        gen = torch.Generator().manual_seed(1)
        start = [torch.randn((7, 3), generator=gen), torch.randn(5, generator=gen)]
        ours = [p.clone() for p in start]
        adam = _Adam(ours, lr=1e-2, betas=(0.9, 0.99), eps=1e-8, weight_decay=1e-3)
        adam.fused = fused  # the kernel, or the per-tensor formula of devices without it
        theirs = [torch.nn.Parameter(p.clone()) for p in start]
        reference = torch.optim.Adam(theirs, lr=1e-2, betas=(0.9, 0.99), eps=1e-8, weight_decay=1e-3, foreach=False)
        for _ in range(20):
            grads = [torch.randn(p.shape, generator=gen) for p in start]
            adam.step(grads)
            for param, grad in zip(theirs, grads, strict=True):
                param.grad = grad.clone()
            reference.step()
        for mine, param in zip(ours, theirs, strict=True):
            np.testing.assert_allclose(mine.numpy(), param.detach().numpy(), rtol=1e-5, atol=1e-6)
        assert not torch.equal(ours[0], start[0])

    def test_a_fit_imports_no_dynamo(self) -> None:
        # torch.optim.Adam imports torch._dynamo when it is built (about 1 s and 70 MB); the field's own Adam does not.
        import subprocess
        import sys

        script = (
            "import sys, numpy as np\n"
            "from types import SimpleNamespace\n"
            "from panogs_core.stages.language_field import LanguageFieldConfig, fit_language_field\n"
            "points = np.random.default_rng(0).uniform(size=(100, 3)).astype(np.float32)\n"
            "fused = SimpleNamespace(features=np.ones((100, 4), np.float32), weights=np.ones(100, np.float32))\n"
            "fit_language_field(points, fused, LanguageFieldConfig(epochs=1, min_steps=2, hidden_dims=(8,)))\n"
            "print('torch' in sys.modules, 'torch._dynamo' in sys.modules)\n"
        )
        out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout
        assert out.split() == ["True", "False"]


class TestConfig:
    @pytest.mark.parametrize(
        ("field", "value"),
        [
            ("cell_sizes", ()),
            ("cell_sizes", (0.2, -1.0)),
            ("channels", 0),
            ("init_scale", 0.0),
            ("hidden_dims", (0,)),
            ("epochs", 0),
            ("batch_size", 0),
            ("lr", -1.0),
            ("plane_lr", 0.0),
            ("weight_decay", -1.0),
            ("betas", (0.9, 1.0)),
            ("bound_padding", -0.1),
            ("max_resolution", 1),
            ("device", "not-a-device"),
            ("cpu_threads", 0),
            ("basis_dims", 0),
            ("decoder_init", "zeros"),
        ],
    )
    def test_exception_names_field(self, field: str, value: object) -> None:
        with pytest.raises(ConfigError, match=f"language_field.{field}"):
            LanguageFieldConfig(**{field: value})  # type: ignore[arg-type]

    def test_defaults_follow_scannet(self) -> None:
        cfg = LanguageFieldConfig()
        assert cfg.cell_sizes == (0.1, 0.04)  # the reference's Replica levels
        assert cfg.channels == 10
        assert cfg.hidden_dims == (128,)
        assert cfg.betas == (0.9, 0.9)  # DEPARTURE (docs/method.md §3.3): the reference's second moment is 0.99
        assert cfg.weight_decay == 1e-6
        assert cfg.init_scale == 0.1


class TestFeatureBasis:
    """The scene's feature basis: the loss taken in it, the basis itself, and a fit that predicts in it."""

    def test_loss_in_the_basis_is_the_full_cosine(self) -> None:
        import torch

        from panogs_core.stages.language_field.basis import project_rows
        from panogs_core.stages.language_field.triplane import _cosine_loss_and_gradients

        gen = torch.Generator().manual_seed(1)
        basis, _ = torch.linalg.qr(torch.randn((12, 4), generator=gen, dtype=torch.float64))  # (D, k) orthonormal
        reduced = [torch.randn((o, i), generator=gen, dtype=torch.float64) for i, o in ((5, 8), (8, 4))]
        full = [reduced[0], basis @ reduced[1]]  # the decoder whose outputs lie in the basis's span
        latent = torch.randn((30, 5), generator=gen, dtype=torch.float64)
        targets = torch.randn((30, 12), generator=gen, dtype=torch.float64) * 2.0  # partly outside the span
        weights = torch.rand(30, generator=gen, dtype=torch.float64)
        inverse = 1 / targets.norm(dim=1)
        rows = torch.arange(30)
        coefficients = project_rows(targets, rows, inverse, basis)
        loss_k, latent_grad_k, grads_k = _cosine_loss_and_gradients(
            reduced, latent, coefficients, torch.ones(30, dtype=torch.float64), weights
        )
        loss_d, latent_grad_d, grads_d = _cosine_loss_and_gradients(full, latent, targets, inverse, weights)
        assert float(loss_k) == pytest.approx(float(loss_d), rel=1e-12)
        np.testing.assert_allclose(latent_grad_k.numpy(), latent_grad_d.numpy(), rtol=1e-9, atol=1e-14)
        np.testing.assert_allclose(grads_k[0].numpy(), grads_d[0].numpy(), rtol=1e-9, atol=1e-14)
        # The reduced layer's gradient is the full one's seen through the basis (W = U V: dV = U^T dW).
        np.testing.assert_allclose(grads_k[1].numpy(), (basis.t() @ grads_d[1]).numpy(), rtol=1e-9, atol=1e-14)

    def test_basis_spans_features_of_few_directions(self) -> None:
        import torch

        from panogs_core.stages.language_field.basis import feature_basis, kept_energy, project_rows

        rng = np.random.default_rng(0)
        directions = rng.normal(size=(5, 40))
        features = torch.from_numpy((rng.normal(size=(300, 5)) @ directions).astype(np.float32))  # rank 5 in 40-d
        rows = torch.arange(300)
        inverse = 1 / features.norm(dim=1)
        weights = torch.ones(300)
        wide = feature_basis(features, rows, inverse, weights, 5, seed=0)
        assert wide.shape == (40, 5)
        np.testing.assert_allclose((wide.t() @ wide).numpy(), np.eye(5), atol=1e-5)
        assert kept_energy(project_rows(features, rows, inverse, wide), weights) == pytest.approx(1.0, abs=1e-4)
        narrow = feature_basis(features, rows, inverse, weights, 2, seed=0)
        assert kept_energy(project_rows(features, rows, inverse, narrow), weights) < 0.99

    def test_fit_predicts_in_the_basis(self) -> None:
        points, region, anchors = _three_regions(n_per=200, seed=4)
        wide = np.zeros((3, 48), np.float32)
        wide[:, :DIM] = anchors  # 48-d features that span 3 directions
        fused = _fused(wide[region], np.ones(len(points)))
        field = fit_language_field(points, fused, _small_cfg(basis_dims=8))
        assert field.state["mlp.1"].shape == (48, 32)
        cos = (field.features * wide[region]).sum(axis=1)
        assert cos.min() > 0.95
        full = fit_language_field(points, fused, _small_cfg(basis_dims=None))
        assert not np.array_equal(full.state["mlp.1"], field.state["mlp.1"])


class TestDecoderInit:
    """``decoder_init: targets``: the last layer starts at the scene's own unit target rows."""

    @staticmethod
    def _training_set(features: np.ndarray, basis_dims: int | None = None):  # type: ignore[no-untyped-def]
        import torch

        from panogs_core.stages.language_field.triplane import TrainingSet

        points = np.random.default_rng(0).uniform(size=(len(features), 3)).astype(np.float32)
        weights = np.ones(len(features), np.float32)
        weights[0] = 0.0  # an unseen row is never drawn
        bounds = field_bounds(points, 0.05)
        return TrainingSet(points, features, weights, bounds, [4], torch.device("cpu"), basis_dims=basis_dims, seed=0)

    def test_columns_are_unit_targets_at_the_uniform_length(self) -> None:
        import torch

        from panogs_core.stages.language_field.triplane import start_at_targets

        features = np.random.default_rng(1).normal(size=(50, DIM)).astype(np.float32) * 3.0
        data = self._training_set(features)
        last = torch.zeros((DIM, 8))
        start_at_targets(last, data, DIM, seed=0)
        length = np.sqrt(DIM / (3 * 8))  # the expected column length of PyTorch's U(+-1/sqrt(H)) init
        columns = last.numpy().T  # (H, D)
        np.testing.assert_allclose(np.linalg.norm(columns, axis=1), length, rtol=1e-5)
        unit = features / np.linalg.norm(features, axis=1, keepdims=True)
        best = (columns / length) @ unit.T  # (H, N) cosines
        assert np.allclose(best.max(axis=1), 1.0, atol=1e-5)  # each column is one target's direction
        assert not np.isclose(best[:, 0], 1.0, atol=1e-3).any()  # never the zero-weight row
        assert len(set(best.argmax(axis=1).tolist())) == 8  # eight different rows

    def test_in_a_basis_the_columns_are_coefficients(self) -> None:
        import torch

        from panogs_core.stages.language_field.triplane import start_at_targets

        features = np.random.default_rng(2).normal(size=(60, DIM)).astype(np.float32)
        data = self._training_set(features, basis_dims=6)
        assert data.basis is not None
        last = torch.zeros((6, 8))  # V = U^T W
        start_at_targets(last, data, DIM, seed=0)
        unit = features / np.linalg.norm(features, axis=1, keepdims=True)
        coefficients = unit @ data.basis.numpy()  # (N, k)
        scaled = last.numpy().T / np.sqrt(DIM / (3 * 8))
        distance = np.linalg.norm(scaled[:, None, :] - coefficients[None], axis=2).min(axis=1)
        np.testing.assert_allclose(distance, 0.0, atol=1e-5)

    def test_fewer_rows_than_columns(self) -> None:
        import torch

        from panogs_core.stages.language_field.triplane import start_at_targets

        features = np.random.default_rng(3).normal(size=(5, DIM)).astype(np.float32)
        data = self._training_set(features)  # 4 training rows, 8 columns
        last = torch.zeros((DIM, 8))
        start_at_targets(last, data, DIM, seed=0)
        assert np.isfinite(last.numpy()).all()
        assert (np.linalg.norm(last.numpy(), axis=0) > 0).all()

    def test_fits_closer_in_few_steps(self) -> None:
        points, region, anchors = _three_regions(n_per=200, seed=5)
        fused = _fused(anchors[region], np.ones(len(points)))
        # 6 steps: the start decides
        uniform = fit_language_field(points, fused, _small_cfg(epochs=2, batch_size=256, decoder_init="uniform"))
        started = fit_language_field(points, fused, _small_cfg(epochs=2, batch_size=256, decoder_init="targets"))
        cos_uniform = (uniform.features * anchors[region]).sum(axis=1).mean()
        cos_started = (started.features * anchors[region]).sum(axis=1).mean()
        assert cos_started > cos_uniform + 0.05
