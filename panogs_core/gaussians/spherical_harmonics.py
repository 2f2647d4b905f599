"""View-dependent colour from real spherical harmonics, in the layout of 3D Gaussian splatting.

Each Gaussian holds ``(degree + 1)^2`` coefficients per colour channel. The colour seen along the unit direction
``d`` (from the camera centre to the Gaussian) is ``sum_k c_k Y_k(d) + 0.5``, clamped at 0: the +0.5 offset makes
zero coefficients mid grey, so the DC coefficient of a colour ``rgb`` is ``(rgb - 0.5) / Y_0``. The basis is the
real, orthonormal one, in the band order and signs that 3DGS and gsplat use (so a ``gaussians.ply`` written here
looks the same in their viewers): see docs/gaussians.md.
"""

from __future__ import annotations

import torch

from panogs_core.errors import ConfigError, ShapeError
from panogs_core.gaussians.config import SH_C0

MAX_DEGREE = 3
SH_C1 = 0.4886025119029199  # sqrt(3) / (2 sqrt(pi))
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_coefficients(degree: int) -> int:
    """Coefficients per channel up to ``degree``: ``(degree + 1)^2``."""
    if not (isinstance(degree, int) and 0 <= degree <= MAX_DEGREE):
        raise ConfigError(f"spherical harmonics degree: expected an integer in [0, {MAX_DEGREE}], got {degree!r}")
    return (degree + 1) ** 2


def sh_basis(directions: torch.Tensor, degree: int) -> torch.Tensor:  # (N, 3) unit -> (N, (degree + 1)^2)
    """The real SH basis functions at unit ``directions``, bands 0..``degree`` in 3DGS order."""
    num_coefficients(degree)
    x, y, z = directions.unbind(-1)
    cols = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        cols += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        cols += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        cols += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(cols, dim=-1)


def sh_to_color(coeffs: torch.Tensor, means: torch.Tensor, camera_centre: torch.Tensor, degree: int) -> torch.Tensor:
    """RGB (N, 3) seen from ``camera_centre`` (3,): the first ``(degree + 1)^2`` of ``coeffs`` (N, K, 3) are used.

    Raises:
        ShapeError: if ``coeffs`` has fewer coefficients than the degree needs.
    """
    k = num_coefficients(degree)
    if coeffs.ndim != 3 or coeffs.shape[1] < k or coeffs.shape[2] != 3:
        raise ShapeError(f"sh_to_color: coeffs expected shape (N, >= {k}, 3), got {tuple(coeffs.shape)}")
    dirs = means - camera_centre
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(dirs, degree)  # (N, k)
    rgb = (basis[:, :, None] * coeffs[:, :k, :]).sum(dim=1) + 0.5
    return rgb.clamp_min(0.0)


def rgb_to_dc(rgb: torch.Tensor) -> torch.Tensor:
    """DC coefficient of a constant colour in [0, 1]."""
    return (rgb - 0.5) / SH_C0
