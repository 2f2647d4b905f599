"""A differentiable 3D Gaussian rasteriser in pure torch: the CPU path and the reference of the CUDA path.

The image formation of 3D Gaussian splatting (Kerbl et al. 2023, see docs/gaussians.md):

1. **Projection.** Each Gaussian (centre, unit quaternion, log scale, opacity logit) goes to the camera with the
   world-to-camera transform ``inv(T_world_cam)`` (OpenCV axes, docs/conventions.md). Its 3D covariance
   ``R S S^T R^T`` becomes the 2D covariance ``J W Sigma W^T J^T`` (EWA splatting: ``J`` is the Jacobian of the
   perspective projection at the centre), plus ``DILATION`` pixels^2 on the diagonal, the usual low-pass filter
   that keeps a Gaussian at least about one pixel wide.
2. **Binning.** A Gaussian covers the pixels within 3 standard deviations of its centre; it is listed in every
   ``tile_size`` x ``tile_size`` tile that this square touches, and each tile's list is sorted by depth.
3. **Compositing.** Per pixel, front to back: ``alpha_i = min(0.99, o_i exp(-d^T Sigma^-1 d / 2))``, dropped below
   1/255, weight ``w_i = alpha_i prod_{j<i} (1 - alpha_j)``; a pixel stops when its transmittance would fall to
   1e-4 (early termination). Any number of channels are blended with the same weights; depth is the weighted
   camera z over the accumulated alpha.

Pixel centres are at integer coordinates (docs/conventions.md): pixel (u, v) is evaluated at (u, v). The CUDA path
(:mod:`panogs_core.gaussians.backends`) puts them at +0.5 and is given a shifted principal point to match.

Speed on the CPU comes from vectorising over a batch of tiles at once and over chunks of each tile's depth-sorted
list; a batch stops when every pixel of it has terminated. Gradients come from torch's autograd through these ops,
the reference; ``analytic_backward=True`` (the training path) differentiates the compositing by hand instead, the
way the CUDA rasterisers do: back to front over the chunks, recomputing each chunk's alphas, so a training step
keeps no per-pixel intermediates (its memory is bounded by one batch) and runs no autograd graph over them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from panogs_core.errors import ShapeError
from panogs_core.types import Camera

DILATION = 0.3  # pixels^2 added to the 2D covariance's diagonal (the 3DGS / gsplat low-pass value)
MIN_ALPHA = 1.0 / 255.0  # a Gaussian contributes nothing to a pixel below this alpha (3DGS)
MAX_ALPHA = 0.99  # alpha is clamped here so that transmittance never reaches 0 (3DGS)
MIN_TRANSMITTANCE = 1e-4  # a pixel stops once its transmittance would fall to this (3DGS)
NEAR_PLANE = 0.01  # m, Gaussians nearer to the camera plane are culled
SIGMA_EXTENT = 3.0  # a Gaussian's square footprint: this many standard deviations around its centre
# Where the projection Jacobian is evaluated, the centre's x/z and y/z are clamped to the image plus this fraction
# of half the field of view on each side: Gaussians far outside the view would otherwise get huge, wrong 2D
# footprints (3DGS and gsplat clamp the same way).
FOV_MARGIN = 0.3


@dataclass(frozen=True)
class PinholeCamera(Camera):
    """A pinhole view: a bundle's :class:`~panogs_core.types.Camera` intrinsics plus the camera-to-world pose.

    (``scaled`` is the intrinsics' own and returns a plain ``Camera``: rescale first, then add the pose.)
    """

    T_world_cam: torch.Tensor  # (4, 4), camera-to-world

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise ShapeError(f"camera: expected width, height >= 1, got {self.width} x {self.height}")
        if tuple(self.T_world_cam.shape) != (4, 4):
            raise ShapeError(f"camera.T_world_cam: expected shape (4, 4), got {tuple(self.T_world_cam.shape)}")

    @classmethod
    def from_camera(cls, camera: Camera, T_world_cam: torch.Tensor) -> PinholeCamera:
        """A bundle's camera model seen from the pose ``T_world_cam`` (4, 4), camera-to-world."""
        return cls(camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy, T_world_cam)


@dataclass(frozen=True)
class Gaussians3D:
    """3D Gaussians in the 3DGS parameterisation (tensors on one device, one dtype)."""

    means: torch.Tensor  # (N, 3) world, metres
    quats: torch.Tensor  # (N, 4) (w, x, y, z), need not be unit (normalised here)
    log_scales: torch.Tensor  # (N, 3)
    opacity_logits: torch.Tensor  # (N,)

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        expected = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,)}
        for name, shape in expected.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ShapeError(f"Gaussians3D.{name}: expected shape {shape}, got {got}")


@dataclass(frozen=True)
class Projected:
    """Gaussians seen by a camera: pixel centres, conics, depths, footprints (culled ones have radius 0)."""

    means2d: torch.Tensor  # (N, 2) pixels (u, v)
    conics: torch.Tensor  # (N, 3) inverse 2D covariance (a, b, c) of [[a, b], [b, c]]
    depths: torch.Tensor  # (N,) camera z, metres
    radii: torch.Tensor  # (N,) int64 pixels, 0 = culled
    opacities: torch.Tensor  # (N,) in (0, 1)


@dataclass(frozen=True)
class Render:
    """What :func:`rasterize` returns."""

    features: torch.Tensor  # (H, W, C) blended channels
    alpha: torch.Tensor  # (H, W) accumulated opacity
    depth: torch.Tensor  # (H, W) expected camera z (0 where alpha is 0)
    top_index: torch.Tensor | None  # (H, W) int64, Gaussian of largest weight per pixel, -1 = none


def quaternion_to_rotation(quats: torch.Tensor) -> torch.Tensor:  # (N, 4) -> (N, 3, 3)
    """Rotation matrices of (w, x, y, z) quaternions, normalised first."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(-1, 3, 3)


def covariances_3d(quats: torch.Tensor, log_scales: torch.Tensor) -> torch.Tensor:  # (N, 3, 3)
    """``R S S^T R^T`` with ``S = diag(exp(log_scales))``."""
    m = quaternion_to_rotation(quats) * torch.exp(log_scales)[:, None, :]  # R S: column j scaled by s_j
    return m @ m.transpose(1, 2)


def world_to_camera(camera: PinholeCamera, dtype: torch.dtype, device: torch.device) -> torch.Tensor:  # (4, 4)
    """``inv(T_world_cam)`` computed in float64, then cast."""
    return torch.linalg.inv(camera.T_world_cam.to(torch.float64)).to(dtype=dtype, device=device)


def project(gaussians: Gaussians3D, camera: PinholeCamera) -> Projected:
    """Step 1 of the module docstring: 2D centres, conics, depths and square footprints; culls what is not seen.

    Culled (radius 0): centre nearer than ``NEAR_PLANE`` (behind the camera), a degenerate 2D covariance, or a
    footprint wholly outside the image.
    """
    means = gaussians.means
    view = world_to_camera(camera, means.dtype, means.device)
    rot, trans = view[:3, :3], view[:3, 3]
    p_cam = means @ rot.T + trans  # (N, 3)
    z = p_cam[:, 2]
    in_front = z > NEAR_PLANE
    z_safe = torch.where(in_front, z, torch.ones_like(z))
    # Jacobian of (fx x/z + cx, fy y/z + cy) at the (clamped) centre
    margin_x = FOV_MARGIN * 0.5 * camera.width / camera.fx
    margin_y = FOV_MARGIN * 0.5 * camera.height / camera.fy
    lo_x, hi_x = -(camera.cx + 0.5) / camera.fx - margin_x, (camera.width - 0.5 - camera.cx) / camera.fx + margin_x
    lo_y, hi_y = -(camera.cy + 0.5) / camera.fy - margin_y, (camera.height - 0.5 - camera.cy) / camera.fy + margin_y
    tx = (p_cam[:, 0] / z_safe).clamp(lo_x, hi_x) * z_safe
    ty = (p_cam[:, 1] / z_safe).clamp(lo_y, hi_y) * z_safe
    zeros = torch.zeros_like(z)
    jac = torch.stack(
        [
            torch.stack([camera.fx / z_safe, zeros, -camera.fx * tx / z_safe**2], -1),
            torch.stack([zeros, camera.fy / z_safe, -camera.fy * ty / z_safe**2], -1),
        ],
        dim=1,
    )  # (N, 2, 3)
    cov_cam = rot @ covariances_3d(gaussians.quats, gaussians.log_scales) @ rot.T  # (N, 3, 3)
    cov2d = jac @ cov_cam @ jac.transpose(1, 2)  # (N, 2, 2)
    a = cov2d[:, 0, 0] + DILATION
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + DILATION
    det = a * c - b * b
    valid = in_front & (det > 0)
    det_safe = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)
    u = camera.fx * p_cam[:, 0] / z_safe + camera.cx
    v = camera.fy * p_cam[:, 1] / z_safe + camera.cy
    means2d = torch.stack([u, v], dim=-1)
    with torch.no_grad():
        # largest eigenvalue of the 2D covariance -> the footprint's half side
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt((mid * mid - det).clamp_min(0.1))
        radii = torch.ceil(SIGMA_EXTENT * torch.sqrt(lam)).to(torch.int64)
        on_image = (
            (u + radii > -0.5)
            & (u - radii < camera.width - 0.5)
            & (v + radii > -0.5)
            & (v - radii < camera.height - 0.5)
        )
        radii = torch.where(valid & on_image & torch.isfinite(u) & torch.isfinite(v), radii, torch.zeros_like(radii))
    return Projected(
        means2d=means2d,
        conics=conics,
        depths=z,
        radii=radii,
        opacities=torch.sigmoid(gaussians.opacity_logits),
    )


@dataclass(frozen=True)
class _Bins:
    """Gaussian ids per tile, depth-sorted, as one flat list with per-tile offsets."""

    ids: torch.Tensor  # (M,) int64 Gaussian index, grouped by tile, front to back within a tile
    starts: torch.Tensor  # (tiles,) int64
    counts: torch.Tensor  # (tiles,) int64
    tiles_x: int
    tiles_y: int


def bin_tiles(projected: Projected, width: int, height: int, tile_size: int) -> _Bins:
    """Step 2: list each seen Gaussian in every tile its footprint touches; sort each list by depth."""
    tiles_x = math.ceil(width / tile_size)
    tiles_y = math.ceil(height / tile_size)
    with torch.no_grad():
        seen = torch.nonzero(projected.radii > 0).squeeze(1)
        centre = projected.means2d[seen].detach()
        r = projected.radii[seen].to(centre.dtype)
        # pixel u lies in tile u // tile_size; floor((x + 0.5) / T) never misses a tile of the pixels in [x0, x1]
        x0 = torch.floor((centre[:, 0] - r + 0.5) / tile_size).clamp(0, tiles_x - 1).to(torch.int64)
        x1 = torch.floor((centre[:, 0] + r + 0.5) / tile_size).clamp(0, tiles_x - 1).to(torch.int64)
        y0 = torch.floor((centre[:, 1] - r + 0.5) / tile_size).clamp(0, tiles_y - 1).to(torch.int64)
        y1 = torch.floor((centre[:, 1] + r + 0.5) / tile_size).clamp(0, tiles_y - 1).to(torch.int64)
        nx, ny = x1 - x0 + 1, y1 - y0 + 1
        per = nx * ny  # tiles touched by each seen Gaussian
        owner = torch.repeat_interleave(torch.arange(seen.numel(), device=per.device), per)  # (M,) index into ``seen``
        first = torch.cumsum(per, 0) - per
        local = torch.arange(owner.numel(), device=per.device) - first[owner]  # 0..per-1 within each Gaussian
        tx = x0[owner] + local % nx[owner]
        ty = y0[owner] + local // nx[owner]
        tile = ty * tiles_x + tx
        # sort by depth, then stably by tile: each tile's list ends up front to back
        by_depth = torch.argsort(projected.depths[seen].detach()[owner], stable=True)
        by_tile = torch.argsort(tile[by_depth], stable=True)
        order = by_depth[by_tile]
        ids = seen[owner[order]]
        counts = torch.bincount(tile, minlength=tiles_x * tiles_y)
        starts = torch.cumsum(counts, 0) - counts
    return _Bins(ids=ids, starts=starts, counts=counts, tiles_x=tiles_x, tiles_y=tiles_y)


def rasterize(
    gaussians: Gaussians3D,
    features: torch.Tensor,  # (N, C)
    camera: PinholeCamera,
    *,
    background: torch.Tensor | None = None,  # (C,)
    tile_size: int = 8,
    tiles_per_batch: int = 64,
    chunk: int = 128,
    with_top_index: bool = False,
    analytic_backward: bool = False,
) -> Render:
    """Render ``features`` (any channels) of the Gaussians seen by ``camera``, with alpha and depth.

    Args:
        gaussians: The scene.
        features: Per-Gaussian channels to blend (colour, one-hot labels, language features...).
        camera: The view.
        background: Added where the pixel's transmittance is left (``features + (1 - alpha) background``).
        tile_size: Tile edge in pixels. 8 on the CPU: fewer pixel-Gaussian pairs than 16 (the small demo room at
            160 x 120: 1.9 M padded pairs against 8.3 M; bench/gaussians.py).
        tiles_per_batch: Tiles composited together (memory: batch x tile_size^2 x chunk x a few floats).
        chunk: Depth-sorted Gaussians composited per step of a batch.
        with_top_index: Also return, per pixel, the Gaussian of largest blending weight (for label ids).
        analytic_backward: Differentiate the compositing with its hand-written backward (:class:`_CompositeAnalytic`,
            the training path: faster, and it keeps no per-pixel intermediates) instead of autograd through the
            ops (the reference it is tested against).

    Returns:
        The render; differentiable in ``gaussians`` and ``features`` (not in ``top_index``).
    """
    n = gaussians.means.shape[0]
    if features.ndim != 2 or features.shape[0] != n:
        raise ShapeError(f"rasterize: features expected shape ({n}, C), got {tuple(features.shape)}")
    projected = project(gaussians, camera)
    bins = bin_tiles(projected, camera.width, camera.height, tile_size)
    # the channels composited together: the features, then depth (weighted camera z)
    values = torch.cat([features, projected.depths[:, None]], dim=1)  # (N, C + 1)
    packed = torch.cat([projected.means2d, projected.conics, projected.opacities[:, None], values], dim=1)
    channels = values.shape[1]
    dev = values.device
    tiles_out = torch.zeros(
        bins.tiles_y * bins.tiles_x, tile_size * tile_size, channels + 1, dtype=values.dtype, device=dev
    )
    top_out = torch.full((bins.tiles_y * bins.tiles_x, tile_size * tile_size), -1, dtype=torch.int64, device=dev)
    busy = torch.nonzero(bins.counts > 0).squeeze(1)
    # tiles of similar list length are batched together so that padding wastes little
    busy = busy[torch.argsort(bins.counts[busy], descending=True, stable=True)]
    monomials = _pixel_monomials(tile_size, values.dtype, dev)  # (P, 6), the same for every tile
    pieces = []
    for start in range(0, busy.numel(), tiles_per_batch):
        tiles = busy[start : start + tiles_per_batch]
        slots, valid = _tile_slots(bins, tiles)
        gathered = packed[slots]  # (B, K, 6 + C + 1)
        origin = _tile_centres(tiles, bins.tiles_x, tile_size, values.dtype)  # (B, 2)
        if analytic_backward and packed.requires_grad:
            out = _CompositeAnalytic.apply(gathered, valid, origin, monomials, chunk)
        else:
            out = _composite(gathered, valid, origin, monomials, chunk)
        pieces.append((tiles, out))
        if with_top_index:
            with torch.no_grad():
                ids = torch.where(valid, slots, -1)
                top_out[tiles] = _top_gaussian(gathered.detach(), ids, origin, monomials, chunk)
    if pieces:
        order = torch.cat([t for t, _ in pieces])
        tiles_out = tiles_out.index_put((order,), torch.cat([o for _, o in pieces]))
    image = _untile(tiles_out, bins, tile_size, camera)  # (H, W, C + 2)
    feats, depth_sum, alpha = image[..., :-2], image[..., -2], image[..., -1]
    depth = depth_sum / alpha.clamp_min(1e-10) * (alpha > 0)
    if background is not None:
        feats = feats + (1 - alpha)[..., None] * background
    top = _untile(top_out[..., None], bins, tile_size, camera)[..., 0] if with_top_index else None
    return Render(features=feats, alpha=alpha, depth=depth, top_index=top)


def _tile_slots(bins: _Bins, tiles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, K) Gaussian ids of each tile's list padded to the longest, and the (B, K) mask of real entries."""
    counts = bins.counts[tiles]
    k = int(counts.max())
    offsets = torch.arange(k, device=tiles.device)
    valid = offsets[None, :] < counts[:, None]
    flat = (bins.starts[tiles][:, None] + offsets[None, :]).clamp_max(max(bins.ids.numel() - 1, 0))
    slots = torch.where(valid, bins.ids[flat], torch.zeros_like(flat))
    return slots, valid


def _tile_centres(tiles: torch.Tensor, tiles_x: int, tile_size: int, dtype: torch.dtype) -> torch.Tensor:
    """(B, 2) pixel coordinates (u, v) of each tile's centre: the origin of its local pixel coordinates."""
    half = (tile_size - 1) / 2
    u = (tiles % tiles_x).to(dtype) * tile_size + half
    v = (tiles // tiles_x).to(dtype) * tile_size + half
    return torch.stack([u, v], dim=-1)


def _pixel_monomials(tile_size: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:  # (P, 6)
    """``[1, u, v, u^2, u v, v^2]`` of a tile's pixels (row-major) in coordinates centred on the tile.

    The exponent of a Gaussian at a pixel is a quadratic in the pixel's coordinates, so the exponents of a whole
    batch are one matrix product of these monomials with six coefficients per Gaussian (:func:`_power_coefficients`)
    instead of a dozen passes over (pixel, Gaussian) arrays. Centring keeps the terms small, so float32 loses little.
    """
    local = torch.arange(tile_size, dtype=dtype, device=device) - (tile_size - 1) / 2
    v, u = torch.meshgrid(local, local, indexing="ij")
    u, v = u.reshape(-1), v.reshape(-1)
    return torch.stack([torch.ones_like(u), u, v, u * u, u * v, v * v], dim=-1)


def _power_coefficients(gathered: torch.Tensor, origin: torch.Tensor) -> torch.Tensor:  # (B, 6, k)
    """Coefficients of ``-d^T conic d / 2`` (d = pixel - mean, conic [[a, b], [b, c]]) on :func:`_pixel_monomials`."""
    mu = gathered[..., 0] - origin[:, None, 0]  # (B, k) the mean relative to the tile's centre
    mv = gathered[..., 1] - origin[:, None, 1]
    a, b, c = gathered[..., 2], gathered[..., 3], gathered[..., 4]
    constant = -0.5 * a * mu * mu - b * mu * mv - 0.5 * c * mv * mv
    return torch.stack([constant, a * mu + b * mv, c * mv + b * mu, -0.5 * a, -b, -0.5 * c], dim=1)


def _alpha_terms(
    gathered: torch.Tensor, valid: torch.Tensor, origin: torch.Tensor, monomials: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(alpha, keep, exp(power), o exp(power)), each (B, P, k): ``alpha = min(0.99, o exp(power))`` where kept (inside
    the footprint, at least 1/255, not padding), else 0."""
    power = monomials @ _power_coefficients(gathered, origin)  # (P, 6) @ (B, 6, k) -> (B, P, k)
    gauss = torch.exp(power.clamp_max(0))
    raw = gathered[:, None, :, 5] * gauss
    alpha = raw.clamp_max(MAX_ALPHA)
    keep = valid[:, None, :] & (power <= 0) & (alpha >= MIN_ALPHA)
    return torch.where(keep, alpha, torch.zeros_like(alpha)), keep, gauss, raw


def _alphas(
    gathered: torch.Tensor, valid: torch.Tensor, origin: torch.Tensor, monomials: torch.Tensor
) -> torch.Tensor:  # (B, P, k)
    """Per pixel and listed Gaussian: ``min(0.99, o exp(-d^T conic d / 2))``, 0 below 1/255 and on padding."""
    return _alpha_terms(gathered, valid, origin, monomials)[0]


def _composite(
    gathered: torch.Tensor,
    valid: torch.Tensor,
    origin: torch.Tensor,
    monomials: torch.Tensor,
    chunk: int,
    chunk_starts: list[torch.Tensor] | None = None,
) -> torch.Tensor:
    """Step 3 for a batch of tiles: (B, P, C + 1 + 1) blended values (features, depth) and alpha.

    ``chunk_starts``, when given, receives the (B, P) transmittance at the start of each chunk composited.
    """
    b, p = origin.shape[0], monomials.shape[0]
    values = gathered[..., 6:]
    acc = values.new_zeros(b, p, values.shape[-1])
    acc_alpha = values.new_zeros(b, p)
    carry = values.new_ones(b, p)  # transmittance before the chunk
    for k0 in range(0, gathered.shape[1], chunk):
        sl = slice(k0, k0 + chunk)
        if chunk_starts is not None:
            chunk_starts.append(carry.clone())  # a view would keep the whole previous chunk alive
        alpha = _alphas(gathered[:, sl], valid[:, sl], origin, monomials)  # (B, P, k)
        after = carry[..., None] * torch.cumprod(1 - alpha, dim=-1)  # transmittance after each Gaussian
        before = torch.cat([carry[..., None], after[..., :-1]], dim=-1)
        # early termination: a Gaussian that would take the transmittance to 1e-4 and all behind it are skipped
        weights = alpha * before * (after.detach() > MIN_TRANSMITTANCE)
        acc = acc + weights @ values[:, sl]
        acc_alpha = acc_alpha + weights.sum(-1)
        carry = after[..., -1]
        if bool((carry.detach() <= MIN_TRANSMITTANCE).all()):
            break
    return torch.cat([acc, acc_alpha[..., None]], dim=-1)


class _CompositeAnalytic(torch.autograd.Function):
    """:func:`_composite` with its gradient written out (3DGS's backward pass, vectorised like the forward).

    Per pixel, with transmittance ``T_i = prod_{j<i} (1 - alpha_j)``, the live mask ``m_i`` (early termination, a
    prefix of the list, not differentiated) and weights ``w_i = m_i alpha_i T_i``, the outputs are ``sum_i w_i v_i``
    (every value channel) and ``sum_i w_i``. With ``q_i = v_i . dL/dvalues + dL/dalpha_sum``:

    * ``dL/dv_i = w_i dL/dvalues``;
    * ``dL/dalpha_i = m_i T_i q_i - (sum_{k>i} w_k q_k) / (1 - alpha_i)`` (each later weight holds the factor
      ``1 - alpha_i``; ``alpha_i <= 0.99`` keeps the division safe);
    * through ``alpha = min(0.99, o exp(power))``: ``dL/do`` and ``dL/dpower``, then the 2D mean and the conic.

    The forward keeps the transmittance at the start of each chunk it composited; the backward walks the chunks
    back to front, recomputes their alphas and carries the running ``sum_{k>i} w_k q_k``.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: torch.autograd.function.FunctionCtx,
        gathered: torch.Tensor,
        valid: torch.Tensor,
        origin: torch.Tensor,
        monomials: torch.Tensor,
        chunk: int,
    ) -> torch.Tensor:
        starts: list[torch.Tensor] = []
        with torch.no_grad():
            out = _composite(gathered, valid, origin, monomials, chunk, chunk_starts=starts)
        none = origin.new_ones(0, origin.shape[0], monomials.shape[0])
        ctx.save_for_backward(gathered, valid, origin, monomials, torch.stack(starts) if starts else none)
        ctx.chunk = chunk  # type: ignore[attr-defined]
        return out

    @staticmethod
    def backward(  # type: ignore[override]
        ctx: torch.autograd.function.FunctionCtx, grad_out: torch.Tensor
    ) -> tuple[torch.Tensor, None, None, None, None]:
        gathered, valid, origin, monomials, starts = ctx.saved_tensors  # type: ignore[attr-defined]
        chunk: int = ctx.chunk  # type: ignore[attr-defined]
        grad_values, grad_alpha_sum = grad_out[..., :-1], grad_out[..., -1]
        grad = torch.zeros_like(gathered)
        behind = torch.zeros_like(grad_alpha_sum)  # (B, P) sum of w_k q_k over the Gaussians behind this chunk
        for index in range(starts.shape[0] - 1, -1, -1):
            sl = slice(index * chunk, (index + 1) * chunk)
            g = gathered[:, sl]
            alpha, keep, gauss, raw = _alpha_terms(g, valid[:, sl], origin, monomials)
            after = starts[index][..., None] * torch.cumprod(1 - alpha, dim=-1)
            before = torch.cat([starts[index][..., None], after[..., :-1]], dim=-1)
            live_before = before * (after > MIN_TRANSMITTANCE)  # m_i T_i
            weights = alpha * live_before
            q = grad_values @ g[..., 6:].transpose(1, 2) + grad_alpha_sum[..., None]  # (B, P, k)
            wq = weights * q
            later = torch.flip(torch.cumsum(torch.flip(wq, [-1]), -1), [-1]) - wq + behind[..., None]
            grad_alpha = live_before * q - later / (1 - alpha)
            behind = behind + wq.sum(-1)
            grad[:, sl, 6:] = weights.transpose(1, 2) @ grad_values
            grad_raw = torch.where(keep & (raw <= MAX_ALPHA), grad_alpha, torch.zeros_like(grad_alpha))
            grad[:, sl, 5] = (grad_raw * gauss).sum(1)
            # the exponent's gradient on its six coefficients, then on the mean and the conic
            coef = monomials.T @ (grad_raw * raw)  # (6, P) @ (B, P, k) -> (B, 6, k)
            mu = g[..., 0] - origin[:, None, 0]
            mv = g[..., 1] - origin[:, None, 1]
            a, b, c = g[..., 2], g[..., 3], g[..., 4]
            grad[:, sl, 0] = -(a * mu + b * mv) * coef[:, 0] + a * coef[:, 1] + b * coef[:, 2]
            grad[:, sl, 1] = -(b * mu + c * mv) * coef[:, 0] + b * coef[:, 1] + c * coef[:, 2]
            grad[:, sl, 2] = -0.5 * mu * mu * coef[:, 0] + mu * coef[:, 1] - 0.5 * coef[:, 3]
            grad[:, sl, 3] = -mu * mv * coef[:, 0] + mv * coef[:, 1] + mu * coef[:, 2] - coef[:, 4]
            grad[:, sl, 4] = -0.5 * mv * mv * coef[:, 0] + mv * coef[:, 2] - 0.5 * coef[:, 5]
        return grad, None, None, None, None


def _top_gaussian(
    gathered: torch.Tensor, ids: torch.Tensor, origin: torch.Tensor, monomials: torch.Tensor, chunk: int
) -> torch.Tensor:  # (B, P) int64 Gaussian of the largest weight, -1 none
    """Like :func:`_composite`, but keeps the argmax of the weights (labels are ids, not blendable values).

    ``ids`` is the (B, K) Gaussian id of each slot, -1 on padding.
    """
    b, p = origin.shape[0], monomials.shape[0]
    best_w = gathered.new_zeros(b, p)
    best = torch.full((b, p), -1, dtype=torch.int64, device=gathered.device)
    carry = gathered.new_ones(b, p)
    for k0 in range(0, gathered.shape[1], chunk):
        sl = slice(k0, k0 + chunk)
        alpha = _alphas(gathered[:, sl], ids[:, sl] >= 0, origin, monomials)
        after = carry[..., None] * torch.cumprod(1 - alpha, dim=-1)
        before = torch.cat([carry[..., None], after[..., :-1]], dim=-1)
        weights = alpha * before * (after > MIN_TRANSMITTANCE)
        w, arg = weights.max(dim=-1)  # (B, P)
        better = w > best_w
        best = torch.where(better, torch.gather(ids[:, sl], 1, arg), best)
        best_w = torch.where(better, w, best_w)
        carry = after[..., -1]
        if bool((carry <= MIN_TRANSMITTANCE).all()):
            break
    return best


def _untile(tiles: torch.Tensor, bins: _Bins, tile_size: int, camera: PinholeCamera) -> torch.Tensor:
    """(tiles, P, C) -> (H, W, C), cropping the partial tiles at the right and bottom edges."""
    c = tiles.shape[-1]
    grid = tiles.reshape(bins.tiles_y, bins.tiles_x, tile_size, tile_size, c).permute(0, 2, 1, 3, 4)
    full = grid.reshape(bins.tiles_y * tile_size, bins.tiles_x * tile_size, c)
    return full[: camera.height, : camera.width]
