"""The CUDA path (gsplat) against the pure-torch rasteriser: same images, same gradients, within tolerances.

Runs wherever a CUDA device and the ``gpu`` extra are present; skipped otherwise. Tolerances (float32): the two
paths bin Gaussians into tiles with different footprints (gsplat: 3.33 sigma per axis; here 3 sigma of the
largest axis), so pixels at a footprint's edge may see a contribution of at most about ``o exp(-4.5)`` in one
path and not the other: image max |diff| <= 0.02, mean |diff| <= 1e-3; gradients: cosine similarity >= 0.99 and
relative L2 error <= 0.05 per parameter.
"""

from __future__ import annotations

import pytest
import torch

from panogs_core.gaussians.backends import gsplat_installed, rasterize_gsplat, resolve_backend
from panogs_core.gaussians.rasterizer import Gaussians3D, PinholeCamera, rasterize

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
    pytest.mark.skipif(not gsplat_installed(), reason="needs the gpu extra (gsplat)"),
]


def _scene(device: torch.device) -> tuple[Gaussians3D, torch.Tensor, PinholeCamera]:
    gen = torch.Generator().manual_seed(0)
    n = 2000
    means = torch.rand(n, 3, generator=gen) * torch.tensor([2.0, 1.5, 2.0]) + torch.tensor([-1.0, -0.75, 1.5])
    g = Gaussians3D(
        means=means.to(device),
        quats=torch.randn(n, 4, generator=gen).to(device),
        log_scales=torch.log(torch.rand(n, 3, generator=gen) * 0.04 + 0.005).to(device),
        opacity_logits=torch.randn(n, generator=gen).to(device),
    )
    colors = torch.rand(n, 3, generator=gen).to(device)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, 3] = torch.tensor([0.1, -0.05, 0.0], dtype=torch.float64)
    cam = PinholeCamera(width=96, height=64, fx=80.0, fy=80.0, cx=47.5, cy=31.5, T_world_cam=pose)
    return g, colors, cam


def _grads(render: object, g: Gaussians3D, colors: torch.Tensor, cam: PinholeCamera) -> tuple[torch.Tensor, list]:
    params = [t.clone().requires_grad_(True) for t in (g.means, g.quats, g.log_scales, g.opacity_logits, colors)]
    out = render(Gaussians3D(*params[:4]), params[4], cam)  # type: ignore[operator]
    target = torch.linspace(0, 1, out.features.numel(), device=colors.device).reshape(out.features.shape)
    loss = ((out.features - target) ** 2).sum() + out.depth.sum() * 0.1
    loss.backward()
    return out.features.detach(), [p.grad for p in params]


def test_auto_picks_gsplat_on_cuda() -> None:
    assert resolve_backend("auto", torch.device("cuda")) == "gsplat"
    assert resolve_backend("auto", torch.device("cpu")) == "torch"


def test_images_and_gradients_match_the_torch_rasteriser() -> None:
    device = torch.device("cuda")
    g, colors, cam = _scene(device)
    ref_img, ref_grads = _grads(lambda *a: rasterize(*a), g, colors, cam)
    cuda_img, cuda_grads = _grads(lambda *a: rasterize_gsplat(*a), g, colors, cam)
    diff = (ref_img - cuda_img).abs()
    print(f"image |diff| max {float(diff.max()):.2e} mean {float(diff.mean()):.2e}")
    assert float(diff.max()) <= 0.02
    assert float(diff.mean()) <= 1e-3
    for name, a, b in zip(("means", "quats", "log_scales", "opacity", "colors"), ref_grads, cuda_grads, strict=True):
        assert a is not None
        assert b is not None
        cos = torch.nn.functional.cosine_similarity(a.reshape(1, -1), b.reshape(1, -1)).item()
        rel = float((a - b).norm() / a.norm().clamp_min(1e-12))
        print(f"grad {name}: cosine {cos:.4f} relative L2 {rel:.3e}")
        assert cos >= 0.99, name
        assert rel <= 0.05, name
