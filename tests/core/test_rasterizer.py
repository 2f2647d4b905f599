"""The pure-torch Gaussian rasteriser: closed-form renders, depth order, culling, gradients."""

from __future__ import annotations

import math

import pytest
import torch
from torch_threads import one_torch_thread  # noqa: F401  (autouse fixture: small tensors)

from panogs_core.gaussians.rasterizer import DILATION, Gaussians3D, PinholeCamera, project, rasterize

IDENTITY_QUAT = (1.0, 0.0, 0.0, 0.0)


def _camera(width: int = 31, height: int = 31, f: float = 40.0, dtype: torch.dtype = torch.float64) -> PinholeCamera:
    # identity pose: the camera looks down world +z; principal point on a pixel centre
    return PinholeCamera(
        width=width,
        height=height,
        fx=f,
        fy=f,
        cx=(width - 1) / 2,
        cy=(height - 1) / 2,
        T_world_cam=torch.eye(4, dtype=dtype),
    )


def _gaussians(means: list[list[float]], scale: float, opacities: list[float]) -> Gaussians3D:
    n = len(means)
    return Gaussians3D(
        means=torch.tensor(means, dtype=torch.float64),
        quats=torch.tensor([IDENTITY_QUAT] * n, dtype=torch.float64),
        log_scales=torch.full((n, 3), math.log(scale), dtype=torch.float64),
        opacity_logits=torch.logit(torch.tensor(opacities, dtype=torch.float64)),
    )


def test_one_gaussian_head_on_renders_the_closed_form_2d_gaussian() -> None:
    cam = _camera()
    z, s, o = 2.0, 0.05, 0.8
    g = _gaussians([[0.0, 0.0, z]], s, [o])
    out = rasterize(g, torch.ones(1, 1, dtype=torch.float64), cam, tile_size=8)
    var = (cam.fx * s / z) ** 2 + DILATION  # pixels^2: EWA covariance of an isotropic Gaussian plus the low-pass
    u = torch.arange(cam.width, dtype=torch.float64) - cam.cx
    v = torch.arange(cam.height, dtype=torch.float64) - cam.cy
    d2 = v[:, None] ** 2 + u[None, :] ** 2
    expected = o * torch.exp(-0.5 * d2 / var)
    expected = torch.where(expected >= 1 / 255, expected, torch.zeros_like(expected))
    inside = d2 <= (3 * math.sqrt(var)) ** 2  # the footprint: 3 standard deviations
    assert torch.allclose(out.alpha[inside], expected[inside], atol=1e-9)
    assert torch.allclose(out.features[..., 0], out.alpha)  # a channel of ones blends to the alpha
    assert out.alpha[~inside].abs().max() < 0.02  # beyond 3 sigma at most o exp(-4.5)
    assert float(out.depth[cam.height // 2, cam.width // 2]) == pytest.approx(z)
    assert float(out.alpha.max()) == pytest.approx(o)


def test_two_overlapping_gaussians_blend_front_to_back() -> None:
    cam = _camera()
    red_green = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
    centre = (cam.height // 2 - 1, cam.width // 2)  # a pixel near, not on, the common centre
    for z_red, z_green in ((1.0, 2.0), (2.0, 1.0)):
        g = _gaussians([[0.0, 0.0, z_red], [0.0, 0.0, z_green]], 0.1, [0.6, 0.7])
        out = rasterize(g, red_green, cam, tile_size=8)
        proj = project(g, cam)
        pix = torch.tensor([centre[1], centre[0]], dtype=torch.float64)
        alphas = []
        for i in range(2):
            d = pix - proj.means2d[i]
            a, b, c = proj.conics[i]
            power = -0.5 * (a * d[0] ** 2 + c * d[1] ** 2) - b * d[0] * d[1]
            alphas.append(float(proj.opacities[i] * torch.exp(power)))
        front, back = (0, 1) if z_red < z_green else (1, 0)
        w = [0.0, 0.0]
        w[front] = alphas[front]
        w[back] = (1 - alphas[front]) * alphas[back]
        got = out.features[centre]
        assert float(got[0]) == pytest.approx(w[0], abs=1e-9)
        assert float(got[1]) == pytest.approx(w[1], abs=1e-9)
        depth = (w[0] * z_red + w[1] * z_green) / (w[0] + w[1])
        assert float(out.depth[centre]) == pytest.approx(depth, abs=1e-9)


def test_top_index_is_the_front_gaussian_where_it_dominates() -> None:
    cam = _camera()
    g = _gaussians([[0.0, 0.0, 2.0], [0.0, 0.0, 1.0], [5.0, 5.0, 1.0]], 0.1, [0.9, 0.9, 0.9])
    out = rasterize(g, torch.zeros(3, 1, dtype=torch.float64), cam, with_top_index=True)
    assert out.top_index is not None
    assert int(out.top_index[cam.height // 2, cam.width // 2]) == 1
    assert int(out.top_index[0, 0]) == -1  # nothing covers the corner


def test_behind_camera_and_out_of_view_gaussians_are_culled() -> None:
    cam = _camera()
    g = _gaussians([[0.0, 0.0, -2.0], [0.0, 0.0, 0.001], [50.0, 0.0, 2.0], [0.0, 0.0, 2.0]], 0.05, [0.9] * 4)
    proj = project(g, cam)
    assert proj.radii.tolist()[:3] == [0, 0, 0]
    assert int(proj.radii[3]) > 0
    only_seen = rasterize(_gaussians([[0.0, 0.0, 2.0]], 0.05, [0.9]), torch.ones(1, 1, dtype=torch.float64), cam)
    out = rasterize(g, torch.ones(4, 1, dtype=torch.float64), cam)
    assert torch.allclose(out.alpha, only_seen.alpha)


def test_tile_size_and_chunking_do_not_change_the_image() -> None:
    gen = torch.Generator().manual_seed(0)
    n = 40
    g = Gaussians3D(
        means=torch.rand(n, 3, generator=gen, dtype=torch.float64) * torch.tensor([1.0, 1.0, 1.0])
        + torch.tensor([-0.5, -0.5, 1.5]),
        quats=torch.randn(n, 4, generator=gen, dtype=torch.float64),
        log_scales=torch.log(torch.rand(n, 3, generator=gen, dtype=torch.float64) * 0.08 + 0.01),
        opacity_logits=torch.randn(n, generator=gen, dtype=torch.float64),
    )
    feats = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    cam = _camera(30, 22)  # partial tiles at the right and bottom edges
    a = rasterize(g, feats, cam, tile_size=16, chunk=64)
    b = rasterize(g, feats, cam, tile_size=4, chunk=3, tiles_per_batch=5)
    assert torch.allclose(a.features, b.features, atol=1e-12)
    assert torch.allclose(a.depth, b.depth, atol=1e-12)
    assert float(a.alpha.max()) > 0.9  # the case overlaps enough to exercise compositing


def test_gradients_match_finite_differences() -> None:
    gen = torch.Generator().manual_seed(3)
    means = torch.tensor([[0.02, -0.01, 1.0], [-0.03, 0.02, 1.3], [0.0, 0.03, 1.6]], dtype=torch.float64)
    quats = torch.randn(3, 4, generator=gen, dtype=torch.float64)
    log_scales = torch.log(torch.tensor([[0.03, 0.02, 0.025], [0.04, 0.03, 0.02], [0.05, 0.05, 0.03]]))
    log_scales = log_scales.to(torch.float64)
    logits = torch.tensor([0.5, 1.0, 0.2], dtype=torch.float64)
    feats = torch.rand(3, 2, generator=gen, dtype=torch.float64)
    cam = _camera(8, 8, f=20.0)

    def render(m: torch.Tensor, q: torch.Tensor, s: torch.Tensor, o: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
        out = rasterize(Gaussians3D(m, q, s, o), f, cam, tile_size=4, chunk=2)
        return torch.cat([out.features.reshape(-1), out.depth.reshape(-1), out.alpha.reshape(-1)])

    inputs = tuple(x.clone().requires_grad_(True) for x in (means, quats, log_scales, logits, feats))
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def _crowd(n: int, seed: int, opacity_shift: float = 0.0) -> tuple[Gaussians3D, torch.Tensor]:
    """``n`` random, overlapping Gaussians in front of the camera with 3 feature channels (float64)."""
    gen = torch.Generator().manual_seed(seed)
    g = Gaussians3D(
        means=torch.rand(n, 3, generator=gen, dtype=torch.float64) * torch.tensor([0.6, 0.6, 1.0])
        + torch.tensor([-0.3, -0.3, 1.2]),
        quats=torch.randn(n, 4, generator=gen, dtype=torch.float64),
        log_scales=torch.log(torch.rand(n, 3, generator=gen, dtype=torch.float64) * 0.1 + 0.02),
        opacity_logits=torch.randn(n, generator=gen, dtype=torch.float64) + opacity_shift,
    )
    return g, torch.rand(n, 3, generator=gen, dtype=torch.float64)


@pytest.mark.parametrize(
    ("n", "seed", "opacity_shift", "chunk"),
    [
        (30, 0, 0.0, 4),  # many chunks per tile list, partial transmittance
        (80, 1, 4.0, 8),  # nearly opaque: early termination inside and across chunks, alphas clamped at 0.99
        (60, 2, -3.0, 128),  # faint: many alphas under 1/255, one chunk
    ],
)
def test_the_analytic_backward_equals_autograd(n: int, seed: int, opacity_shift: float, chunk: int) -> None:
    g, feats = _crowd(n, seed, opacity_shift)
    cam = _camera(20, 14)
    weights = torch.rand(14, 20, 5, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    grads = []
    for analytic in (False, True):
        leaves = [t.clone().requires_grad_(True) for t in (g.means, g.quats, g.log_scales, g.opacity_logits, feats)]
        out = rasterize(Gaussians3D(*leaves[:4]), leaves[4], cam, tile_size=4, chunk=chunk, analytic_backward=analytic)
        image = torch.cat([out.features, out.depth[..., None], out.alpha[..., None]], dim=-1)
        (image * weights).sum().backward()
        grads.append([leaf.grad for leaf in leaves])
    for name, plain, analytic in zip(("means", "quats", "log_scales", "opacity", "features"), *grads, strict=True):
        assert plain is not None
        assert analytic is not None
        assert float(plain.abs().max()) > 0, name
        assert torch.allclose(plain, analytic, rtol=1e-7, atol=1e-9), name


def test_analytic_gradients_match_finite_differences() -> None:
    g, feats = _crowd(6, 5, 1.0)
    cam = _camera(8, 8, f=20.0)

    def render(m: torch.Tensor, q: torch.Tensor, s: torch.Tensor, o: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
        out = rasterize(Gaussians3D(m, q, s, o), f, cam, tile_size=4, chunk=2, analytic_backward=True)
        return torch.cat([out.features.reshape(-1), out.depth.reshape(-1), out.alpha.reshape(-1)])

    inputs = tuple(x.clone().requires_grad_(True) for x in (g.means, g.quats, g.log_scales, g.opacity_logits, feats))
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)
