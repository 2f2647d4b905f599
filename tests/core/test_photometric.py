"""Spherical harmonics colours, SSIM and the photometric loss."""

from __future__ import annotations

import math

import pytest
import torch
from torch_threads import one_torch_thread  # noqa: F401  (autouse fixture: small tensors)

from panogs_core.errors import ConfigError
from panogs_core.gaussians.photometric import photometric_loss, psnr, ssim
from panogs_core.gaussians.spherical_harmonics import num_coefficients, rgb_to_dc, sh_basis, sh_to_color


def test_dc_only_colour_is_view_independent_and_round_trips() -> None:
    rgb = torch.tensor([[0.2, 0.5, 0.9]], dtype=torch.float64)
    coeffs = torch.zeros(1, 16, 3, dtype=torch.float64)
    coeffs[:, 0] = rgb_to_dc(rgb)
    for centre in ([0.0, 0.0, 0.0], [3.0, -1.0, 2.0]):
        got = sh_to_color(coeffs, torch.tensor([[1.0, 1.0, 1.0]], dtype=torch.float64), torch.tensor(centre), 3)
        assert torch.allclose(got, rgb)


def test_basis_is_orthonormal_on_the_sphere() -> None:
    # Monte-Carlo integral of Y_i Y_j over the sphere (4 pi times the mean) -> identity
    gen = torch.Generator().manual_seed(0)
    d = torch.randn(400_000, 3, generator=gen, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True)
    y = sh_basis(d, 3)
    gram = 4 * math.pi * (y.T @ y) / d.shape[0]
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=0.02)


def test_degree_one_colour_depends_on_the_view_direction() -> None:
    coeffs = torch.zeros(1, 4, 3, dtype=torch.float64)
    coeffs[0, 2, :] = 0.5  # the band-1 z term
    mean = torch.zeros(1, 3, dtype=torch.float64)
    from_below = sh_to_color(coeffs, mean, torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64), 1)
    from_above = sh_to_color(coeffs, mean, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), 1)
    assert float(from_below[0, 0]) > 0.5 > float(from_above[0, 0])


def test_bad_degree_is_refused() -> None:
    with pytest.raises(ConfigError, match="degree"):
        num_coefficients(4)


def test_ssim_is_one_on_equal_images_and_drops_with_noise() -> None:
    gen = torch.Generator().manual_seed(1)
    img = torch.rand(24, 32, 3, generator=gen)
    assert float(ssim(img, img)) == pytest.approx(1.0, abs=1e-6)
    noisy = (img + 0.2 * torch.randn(img.shape, generator=gen)).clamp(0, 1)
    assert float(ssim(img, noisy)) < 0.9
    assert float(photometric_loss(img, img)) == pytest.approx(0.0, abs=1e-6)
    assert float(photometric_loss(noisy, img)) > 0.05


def test_the_l2_norm_takes_the_squared_error_in_place_of_l1() -> None:
    target = torch.zeros(8, 8, 3)
    render = target + 0.1
    assert float(photometric_loss(render, target, 0.0)) == pytest.approx(0.1, abs=1e-6)
    assert float(photometric_loss(render, target, 0.0, "l2")) == pytest.approx(0.01, abs=1e-6)
    # with D-SSIM the two differ by the photometric term alone
    with_ssim = float(photometric_loss(render, target, 0.2, "l1")) - float(photometric_loss(render, target, 0.2, "l2"))
    assert with_ssim == pytest.approx(0.8 * (0.1 - 0.01), abs=1e-6)


def test_psnr_of_a_known_error() -> None:
    a = torch.zeros(4, 4, 3)
    assert psnr(a + 0.1, a) == pytest.approx(20.0, abs=1e-4)
