"""The torch half of the language field: the pyramid tri-plane + decoder model, its training and decoding.

Kept apart from :mod:`panogs_core.stages.language_field` so that importing the stage's config (the API process
validates job configs) does not import torch.
"""

from __future__ import annotations

import itertools
import math
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F

from panogs_core.errors import InputError, NumericalError
from panogs_core.progress import ProgressFn, report
from panogs_core.stages.language_field.basis import feature_basis, kept_energy, project_rows
from panogs_core.stages.language_field.corners import (
    BatchCorners,
    bilinear_corners,
    plane_table,
    planes_from_table,
)

if TYPE_CHECKING:
    from panogs_core.stages.language_field.config import LanguageFieldConfig

_DECODE_BATCH = 8192  # points per decoding batch: (8192, 512) float32 is 16 MiB (32768 held 128 MiB at peak)


class _TriplaneDecoder(torch.nn.Module):
    """Pyramid tri-plane encoder plus bias-free MLP decoder (docs/method.md §3.2-3.3)."""

    def __init__(self, planes: list[torch.Tensor], weights: list[torch.Tensor]) -> None:
        super().__init__()
        self.planes = torch.nn.ParameterList([torch.nn.Parameter(p) for p in planes])  # each (3, C, R, R)
        self.mlp = torch.nn.ParameterList([torch.nn.Parameter(w) for w in weights])  # each (out, in)

    def encode(self, coords: torch.Tensor) -> torch.Tensor:
        """Latent of points already mapped into the box as ``[-1, 1]^3``. ``(B, 3)`` -> ``(B, C)``."""
        # Plane 0 is (x, y), plane 1 (x, z), plane 2 (y, z); first coordinate indexes the plane width
        # (docs/method.md §3.2).
        grid = torch.stack([coords[:, [0, 1]], coords[:, [0, 2]], coords[:, [1, 2]]])  # (3, B, 2)
        grid = grid.unsqueeze(1)  # (3, 1, B, 2)
        latent = coords.new_zeros(coords.shape[0], self.planes[0].shape[1])  # (B, C)
        for plane in self.planes:
            # DEPARTURE (docs/method.md §3.2): border padding, not zero; it only matters for new points outside the box.
            sampled = F.grid_sample(plane, grid, mode="bilinear", padding_mode="border", align_corners=True)
            latent = latent + sampled.sum(dim=0).squeeze(1).t()  # sum over planes, then over levels
        return latent

    def hidden(self, latent: torch.Tensor) -> torch.Tensor:
        """Input of the last (linear) layer. ``(B, C)`` latent -> ``(B, H)``."""
        h = latent
        for weight in self.mlp[:-1]:
            h = torch.relu(h @ weight.t())
        return h

    def forward(self, coords: torch.Tensor) -> torch.Tensor:
        """Decoded (not normalised) feature. ``(B, 3)`` in ``[-1, 1]`` -> ``(B, D)``."""
        return self.hidden(self.encode(coords)) @ self.mlp[-1].t()


def _to_unit_cube(points: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """Map world points into ``[-1, 1]^3`` over the box. ``(B, 3)`` -> ``(B, 3)``.

    DEPARTURE (docs/method.md §3.2, pitfall 5): the whole plane, so the cells are the nominal ``cell_sizes``; the
    reference feeds ``[0, 1]`` to ``grid_sample`` and uses one quadrant.
    """
    return (points - bounds[0]) / (bounds[1] - bounds[0]) * 2.0 - 1.0


def init_model(resolutions: list[int], dim: int, cfg: LanguageFieldConfig) -> _TriplaneDecoder:
    """Planes ~ N(0, init_scale^2); decoder weights ~ U(+-1/sqrt(fan_in)) (PyTorch's default Linear init).

    A local generator makes the initialisation reproducible without touching torch's global RNG.
    """
    gen = torch.Generator().manual_seed(cfg.seed)
    planes = [torch.randn((3, cfg.channels, r, r), generator=gen) * cfg.init_scale for r in resolutions]
    widths = [cfg.channels, *cfg.hidden_dims, dim]
    weights = []
    for fan_in, fan_out in itertools.pairwise(widths):
        bound = 1.0 / math.sqrt(fan_in)
        weights.append((torch.rand((fan_out, fan_in), generator=gen) * 2.0 - 1.0) * bound)
    return _TriplaneDecoder(planes, weights).to(torch.device(cfg.device))


def model_from_state(state: dict[str, np.ndarray], device: torch.device) -> _TriplaneDecoder:
    """Rebuild the decoder from ``LanguageField.state`` (levels and layers in numeric order)."""

    def ordered(prefix: str) -> list[torch.Tensor]:
        keys = sorted((k for k in state if k.startswith(prefix)), key=lambda k: int(k[len(prefix) :]))
        return [torch.from_numpy(np.asarray(state[k], dtype=np.float32).copy()) for k in keys]

    planes, weights = ordered("planes."), ordered("mlp.")
    if not planes or not weights:
        raise InputError(f"language field state: expected 'planes.*' and 'mlp.*' arrays, found {sorted(state)}")
    return _TriplaneDecoder(planes, weights).to(device)


def state_of(model: _TriplaneDecoder) -> dict[str, np.ndarray]:
    state = {f"planes.{i}": p.detach().cpu().numpy().copy() for i, p in enumerate(model.planes)}
    state.update({f"mlp.{i}": w.detach().cpu().numpy().copy() for i, w in enumerate(model.mlp)})
    return state


@torch.no_grad()
def decode_features(model: _TriplaneDecoder, points: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """Decoded unit features of world points, in batches. ``(P, 3)`` -> ``(P, D)`` float32."""
    device = model.planes[0].device
    bounds_t = torch.from_numpy(bounds.astype(np.float32)).to(device)
    # (P, D), every row written. From torch's allocator, not numpy's: numpy advises transparent huge pages for large
    # arrays, and faulting those in right after the training made the decoding 0.50-0.54 s instead of 0.23 s
    # (docs/benchmarks.md, "Language field speed").
    out = torch.empty((points.shape[0], model.mlp[-1].shape[0])).numpy()
    rows = torch.from_numpy(out)
    for start in range(0, points.shape[0], _DECODE_BATCH):
        chunk = torch.from_numpy(points[start : start + _DECODE_BATCH].astype(np.float32)).to(device)
        hidden = model.hidden(model.encode(_to_unit_cube(chunk, bounds_t)))  # (B, H)
        if device.type == "cpu":  # straight into the output: no (B, D) temporaries (32 MiB a batch at D = 512)
            pred = torch.mm(hidden, model.mlp[-1].t(), out=rows[start : start + chunk.shape[0]])
        else:
            pred = hidden @ model.mlp[-1].t()
        # Rows the decoder maps exactly to 0 stay 0 rather than becoming NaN.
        pred.div_(pred.norm(dim=1, keepdim=True).clamp_min(1e-12))
        if device.type != "cpu":
            rows[start : start + chunk.shape[0]] = pred.cpu()
    return out


class TrainingSet:
    """The primitives with weight > 0: their bilinear plane corners, weights, and their targets read per batch.

    DEPARTURE (minor, docs/method.md §3.3): zero-weight (unseen) primitives, which add exactly 0 to the loss, are
    left out of the batches. The targets are the fused features' rows, read by each batch and scaled to unit length
    (:attr:`inverse_norms`): no (M, D) copy of the features is made (it was the stage's largest array).

    The training points never move, so where each one samples the planes is computed once
    (:func:`bilinear_corners`): a step gathers those cells instead of calling ``grid_sample`` per level.

    With ``basis_dims`` below ``D``, the targets are the coefficients of the unit rows in the scene's feature
    basis (:mod:`panogs_core.stages.language_field.basis`, :attr:`basis`), computed once; :attr:`inverse_norms`
    is then 1 (the coefficients are of unit rows already).
    """

    def __init__(
        self,
        points: np.ndarray,
        features: np.ndarray,
        weights: np.ndarray,
        bounds: np.ndarray,
        resolutions: list[int],
        device: torch.device,
        *,
        basis_dims: int | None = None,
        seed: int = 0,
    ) -> None:
        keep = np.flatnonzero(weights > 0)
        features = np.asarray(features, dtype=np.float32)  # (N, D), no copy when it is float32 already
        sq_norms = np.einsum("nd,nd->n", features, features)[keep]  # (M,), no (N, D) temporary
        if not np.isfinite(sq_norms).all():
            raise InputError("fused.features: contains NaN or infinite values where the weight is > 0")
        self.inverse_norms = torch.from_numpy(1.0 / np.sqrt(np.maximum(sq_norms, 1e-24))).to(device)  # (M,)
        coords = _to_unit_cube(torch.from_numpy(points[keep]), torch.from_numpy(bounds))  # (M, 3)
        cells, corner_weights = bilinear_corners(coords, resolutions)
        self.cells = cells.to(device)  # (M, K) row of each corner in the plane table
        self.corner_weights = corner_weights.to(device)  # (M, K) bilinear weight of each corner
        self.weights = torch.from_numpy(weights[keep]).to(device)  # (M,)
        self._rows = torch.from_numpy(keep).to(device)  # (M,) row of each kept primitive in `features`
        if not features.flags.writeable:  # torch.from_numpy warns on read-only memory
            features = features.copy()
        self._features = torch.from_numpy(features).to(device)  # (N, D) shares memory on the CPU
        self.basis: torch.Tensor | None = None  # (D, k) orthonormal, or None: the targets are the fused rows
        self.kept_energy = 1.0  # share of the unit targets' energy the basis keeps
        if basis_dims is not None and basis_dims < features.shape[1]:
            self.basis = feature_basis(self._features, self._rows, self.inverse_norms, self.weights, basis_dims, seed)
            self._features = project_rows(self._features, self._rows, self.inverse_norms, self.basis)  # (M, k)
            self._rows = torch.arange(len(keep), device=device)
            self.inverse_norms = torch.ones_like(self.inverse_norms)
            self.kept_energy = kept_energy(self._features, self.weights)

    def __len__(self) -> int:
        return int(self._rows.shape[0])

    def targets(self, idx: torch.Tensor) -> torch.Tensor:  # (B, D) or (B, k) rows of the kept primitives idx
        """The fused rows of a batch, not normalised (:attr:`inverse_norms` scales them to unit length), or their
        unit rows' coefficients in :attr:`basis`."""
        return self._features.index_select(0, self._rows.index_select(0, idx))


# Device types with torch's fused Adam kernel (torch 2.13: cpu, cuda, mps, xpu); elsewhere the per-tensor loop.
_FUSED_ADAM_DEVICES = ("cpu", "cuda", "mps", "xpu")


class _Adam:
    """Adam over a list of tensors whose gradients the caller computes: torch's update rule (no amsgrad), here
    because ``torch.optim.Adam`` imports ``torch._dynamo`` when it is built (about 1 s and 70 MB of a run at
    ScanNet size, docs/benchmarks.md, "Speed at ScanNet size, third pass").

    DEPARTURE (fused Adam, docs/method.md §3.3): torch's fused kernel (the op ``torch.optim.Adam(fused=True)``
    calls) where the device has one, instead of the per-tensor loop torch picks on the CPU; the same update rule,
    rounded differently. Elsewhere the per-tensor formula of ``torch.optim.Adam``.
    """

    def __init__(
        self, params: list[torch.Tensor], *, lr: float, betas: tuple[float, float], eps: float, weight_decay: float
    ) -> None:
        self.params = params
        self.lr, self.betas, self.eps, self.weight_decay = lr, betas, eps, weight_decay
        self.exp_avgs = [torch.zeros_like(p) for p in params]
        self.exp_avg_sqs = [torch.zeros_like(p) for p in params]
        self.steps = [torch.zeros((), dtype=torch.float32, device=p.device) for p in params]  # as torch keeps them
        self.fused = params[0].device.type in _FUSED_ADAM_DEVICES and hasattr(torch, "_fused_adam_")

    @torch.no_grad()
    def step(self, grads: list[torch.Tensor]) -> None:
        """One update of every tensor with its gradient (``grads`` in the order of ``params``)."""
        torch._foreach_add_(self.steps, 1)
        beta1, beta2 = self.betas
        if self.fused:
            torch._fused_adam_(
                self.params, grads, self.exp_avgs, self.exp_avg_sqs, [], self.steps,
                lr=self.lr, beta1=beta1, beta2=beta2, weight_decay=self.weight_decay, eps=self.eps,
                amsgrad=False, maximize=False,
            )  # fmt: skip
            return
        step = float(self.steps[0])
        bias_correction1, bias_correction2_sqrt = 1 - beta1**step, math.sqrt(1 - beta2**step)
        for param, grad, exp_avg, exp_avg_sq in zip(self.params, grads, self.exp_avgs, self.exp_avg_sqs, strict=True):
            if self.weight_decay:
                grad = grad.add(param, alpha=self.weight_decay)
            exp_avg.lerp_(grad, 1 - beta1)
            exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
            denom = (exp_avg_sq.sqrt() / bias_correction2_sqrt).add_(self.eps)
            param.addcdiv_(exp_avg, denom, value=-self.lr / bias_correction1)


def start_at_targets(last: torch.Tensor, data: TrainingSet, dim: int, seed: int) -> None:
    """Set the last layer's ``H`` columns to unit target rows drawn with ``seed`` (``decoder_init: targets``).

    ``last`` is ``(D, H)``, or ``(k, H)`` in the feature basis, where the rows are the unit targets' coefficients.
    Each column gets the expected length of PyTorch's uniform init, ``sqrt(D / (3 H))``: Adam's steps are the same
    size against it. With a ReLU hidden layer the decoded feature is a non-negative mix of the columns, so it
    starts inside the cone of the scene's own features rather than in a random direction, and fewer steps fit as
    closely (docs/method.md §3.3).
    """
    hidden = int(last.shape[1])
    gen = torch.Generator().manual_seed(seed + 2)  # not the shuffle's generator (seed + 1)
    count = len(data)
    if count >= hidden:
        pick = torch.randperm(count, generator=gen)[:hidden]
    else:  # fewer training rows than columns: some rows start several columns
        pick = torch.randint(count, (hidden,), generator=gen)
    pick = pick.to(data.weights.device)
    rows = data.targets(pick) * data.inverse_norms.index_select(0, pick).unsqueeze(1)  # (H, D) unit, or (H, k)
    last.copy_(rows.t() * math.sqrt(dim / (3.0 * hidden)))


def _cosine_loss_and_gradients(
    mlp: list[torch.Tensor],  # each (out, in), the last (D, H) linear
    latent: torch.Tensor,  # (B, C)
    targets: torch.Tensor,  # (B, D) as fused, not unit
    inverse_norms: torch.Tensor,  # (B,) 1 / |target|
    sample_weights: torch.Tensor,  # (B,)
) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:  # loss (), latent's gradient (B, C), each layer's
    """``mean_i w_i (1 - cos(W h_i, t_i))`` and its gradients, forward and backward by hand.

    No autograd graph is built (its bookkeeping was a third of a step at ScanNet size); the matrix products are most
    of the training time on a CPU. The last layer ``W`` (D, H) is linear and bias-free, and its part is taken in the
    cheaper of two exact forms (:func:`_last_layer_by_prediction`, :func:`_last_layer_by_gram`): the same cosine as
    torch.cosine_similarity (eps 1e-8) against unit targets, whose lengths scale the products instead.
    """
    inputs, pre_activations = [latent], []
    h = latent
    for weight in mlp[:-1]:
        pre = h @ weight.t()
        pre_activations.append(pre)
        h = torch.relu(pre)
        inputs.append(h)
    last = mlp[-1]  # (D, H)
    out_dim, width = last.shape
    # Per batch the prediction form takes three (B, D, H) products, the Gram form two and two (B, H, H) ones: with
    # the scene's 128-d basis and 128 hidden units (the defaults) 3 against 4, with D = 512 and no basis 6 against 5.
    last_layer = _last_layer_by_prediction if out_dim < 2 * width else _last_layer_by_gram
    loss, d_h, d_last = last_layer(h, last, targets, inverse_norms, sample_weights)
    grads = [d_last]
    for weight, pre, layer_input in zip(
        reversed(mlp[:-1]), reversed(pre_activations), reversed(inputs[:-1]), strict=True
    ):
        d_pre = d_h * (pre > 0)  # relu
        grads.append(d_pre.t() @ layer_input)  # (out, in)
        d_h = d_pre @ weight  # (B, in)
    grads.reverse()
    return loss, d_h, grads


def _last_layer_by_prediction(
    h: torch.Tensor,  # (B, H) the last hidden layer
    last: torch.Tensor,  # (D, H)
    targets: torch.Tensor,  # (B, D) as fused
    inverse_norms: torch.Tensor,  # (B,)
    sample_weights: torch.Tensor,  # (B,)
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # loss (), d loss / d h (B, H), d loss / d W (D, H)
    """The loss through the ``(B, D)`` prediction ``P = h W^T``: cheaper where ``D < 2 H`` (the scene's basis).

    ``cos = P . t / (|P| |t|)``; ``d cos / d P = t / (|t| |P|) - cos P / |P|^2``; then ``dW = dP^T h`` and
    ``dh = dP W``.
    """
    pred = h @ last.t()  # (B, D)
    dot = (pred * targets).sum(dim=1) * inverse_norms  # (B,) P . t / |t|
    norm = (pred * pred).sum(dim=1).sqrt()  # (B,) |P|
    live = norm > 1e-8  # where the 1e-8 floor holds, the cosine does not depend on the norm
    norm_floor = norm.clamp_min(1e-8)
    cos = dot / norm_floor
    loss = (sample_weights * (1.0 - cos)).mean()
    d_cos = sample_weights * (-1.0 / sample_weights.shape[0])  # (B,) d loss / d cos
    along_target = d_cos * inverse_norms / norm_floor  # (B,)
    along_pred = torch.where(live, -d_cos * cos / norm_floor**2, 0.0)  # (B,)
    d_pred = targets * along_target.unsqueeze(1) + pred * along_pred.unsqueeze(1)  # (B, D)
    return loss, d_pred @ last, d_pred.t() @ h


def _last_layer_by_gram(
    h: torch.Tensor,  # (B, H) the last hidden layer
    last: torch.Tensor,  # (D, H)
    targets: torch.Tensor,  # (B, D) as fused
    inverse_norms: torch.Tensor,  # (B,)
    sample_weights: torch.Tensor,  # (B,)
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # loss (), d loss / d h (B, H), d loss / d W (D, H)
    """The loss without the ``(B, D)`` prediction: cheaper where ``D >= 2 H`` (the fused 512-d rows, no basis).

    ``W h . t = h . (W^T t)`` and ``|W h|^2 = h^T (W^T W) h``; the backward reuses ``h (W^T W)`` for the gradient of
    the norm, where autograd computes a second ``(B, H) x (H, H)`` product.
    """
    projected = (targets @ last) * inverse_norms.unsqueeze(1)  # (B, H), as if the targets were unit rows
    gram = last.t() @ last  # (H, H)
    h_gram = h @ gram  # (B, H)
    dot = (h * projected).sum(dim=1)  # (B,)
    norm = (h_gram * h).sum(dim=1).clamp_min(0.0).sqrt()  # (B,) |W h|
    live = norm > 1e-8  # where the 1e-8 floor holds, the cosine does not depend on the norm
    norm_floor = norm.clamp_min(1e-8)
    cos = dot / norm_floor
    loss = (sample_weights * (1.0 - cos)).mean()
    # d loss / d cos = -w / B; cos = dot / n, n = sqrt(h^T G h), d n / d h = G h / n.
    d_cos = sample_weights * (-1.0 / sample_weights.shape[0])  # (B,)
    d_dot = d_cos / norm_floor  # (B,)
    d_sq = torch.where(live, -d_cos * dot / (2.0 * norm_floor**3), 0.0)  # (B,) d loss / d (h^T G h)
    d_h = projected * d_dot.unsqueeze(1) + h_gram * (2.0 * d_sq).unsqueeze(1)  # (B, H)
    # W's gradient: through W^T t (the targets' rows, scaled as above) and through G = W^T W.
    d_last = targets.t() @ (h * (d_dot * inverse_norms).unsqueeze(1))  # (D, H)
    d_gram = h.t() @ (h * d_sq.unsqueeze(1))  # (H, H), symmetric
    d_last.addmm_(last, d_gram, alpha=2.0)
    return loss, d_h, d_last


def train_model(
    model: _TriplaneDecoder,
    data: TrainingSet,
    cfg: LanguageFieldConfig,
    on_progress: ProgressFn | None,
) -> None:
    """Mini-batch Adam over shuffled primitives; the shuffle uses its own generator (seeded, reproducible).

    The planes train as one table (:func:`plane_table`), written back into ``model.planes`` at the end; the
    decoder's weights are updated in place. Adam keeps the reference's two groups: planes (eps 1e-15, no decay)
    and decoder (L2 weight decay); Adam is element-wise, so the update of every plane value is the one it would
    get in its ``(3, C, R, R)`` plane. Gradients are computed by hand (:func:`_cosine_loss_and_gradients`,
    :class:`BatchCorners`): no autograd graph is built. With a feature basis ``U`` (``data.basis``) the last layer
    trains as ``V = U^T W`` (``k``, H) and is written back as ``W = U V``.
    """
    resolutions = [int(p.shape[-1]) for p in model.planes]
    table = plane_table([p.detach() for p in model.planes])  # (cells, C), a copy
    weights_out = [w.detach() for w in model.mlp]  # the decoder's own storage
    basis = data.basis  # (D, k) or None
    # The layers that train: the decoder's own (updates land in the model), the last one in the basis if any.
    mlp = weights_out if basis is None else [*weights_out[:-1], basis.t() @ weights_out[-1]]
    if cfg.decoder_init == "targets":
        start_at_targets(mlp[-1], data, int(weights_out[-1].shape[0]), cfg.seed)
    planes_adam = _Adam([table], lr=cfg.plane_lr, betas=cfg.betas, eps=1e-15, weight_decay=0.0)
    mlp_adam = _Adam(mlp, lr=cfg.lr, betas=cfg.betas, eps=1e-8, weight_decay=cfg.weight_decay)  # torch's eps
    gen = torch.Generator().manual_seed(cfg.seed + 1)
    weights = data.weights  # (M,) > 0
    count = len(data)
    steps_per_epoch = max(1, math.ceil(count / cfg.batch_size))
    epochs = max(cfg.epochs, math.ceil(cfg.min_steps / steps_per_epoch))
    corners = BatchCorners(table)
    with torch.no_grad():
        for epoch in range(epochs):
            order = torch.randperm(count, generator=gen).to(weights.device)
            for start in range(0, count, cfg.batch_size):
                idx = order[start : start + cfg.batch_size]
                cells, corner_weights = data.cells.index_select(0, idx), data.corner_weights.index_select(0, idx)
                latent = corners.latent(cells, corner_weights)  # (B, C)
                inverse_norms, sample_weights = data.inverse_norms.index_select(0, idx), weights.index_select(0, idx)
                loss, latent_grad, mlp_grads = _cosine_loss_and_gradients(
                    mlp, latent, data.targets(idx), inverse_norms, sample_weights
                )
                planes_adam.step([corners.table_gradient(latent_grad)])
                mlp_adam.step(mlp_grads)
            if not math.isfinite(float(loss)):
                raise NumericalError(f"language field: the loss became {float(loss)} at epoch {epoch + 1}")
            report(on_progress, epoch + 1, epochs)
        for plane, trained in zip(model.planes, planes_from_table(table, resolutions), strict=True):
            plane.copy_(trained)
        if basis is not None:
            weights_out[-1].copy_(basis @ mlp[-1])  # (D, H), outputs in the basis's span
