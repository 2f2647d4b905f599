"""Stage 4: the continuous 3D language field (PanoGS reference sections 3.2 and 3.3).

A latent pyramid tri-plane (per level three ``(C, R, R)`` planes, bilinearly sampled, summed over planes and
over levels into a ``C``-dim latent) followed by a bias-free MLP decoder is fitted to the fused multi-view
features of the primitives with a confidence-weighted cosine loss. The fitted field gives a language feature
for every primitive (smoothed across space, defined where no frame saw a primitive) and for any 3D point.

Inputs: primitive centres ``(N, 3)`` and :class:`panogs_core.fusion.FusedFeatures` (targets ``(N, D)``,
confidence ``(N,)``). Output: :class:`LanguageField` (decoded unit features, tri-plane box, model weights).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from panogs_core.errors import ConfigError, InputError, ShapeError
from panogs_core.progress import ProgressFn

if TYPE_CHECKING:
    from panogs_core.fusion import FusedFeatures

_STATE_PREFIX = "state."


@dataclass(frozen=True, kw_only=True)
class LanguageFieldConfig:
    """Settings of the language field (reference 3.2-3.3; defaults: the reference's ScanNet settings).

    DEPARTURE (training schedule): the reference trains 11 epochs at batch 256 with lr 1e-3 for both groups
    (about 6.4k steps for 150k primitives). On a CPU the cost is per point, not per step, so we make fewer
    passes (4 epochs, batch 1024) with larger learning rates (decoder 5e-3, planes 1e-2). Measured on a
    synthetic 150k-point, 512-d room (ScanNet-20 CLIP embeddings on spatial blobs, 10 % class noise, 2 cores):
    13 s instead of 61 s, decoded argmax agreeing with the fused argmax on 0.901 of the points (reference
    schedule 0.905), mean cosine to the target 0.844 (0.846), accuracy against the true class 0.984 (0.981).
    Larger batches (4096-8192) at the same cost per epoch needed more epochs for the same quality.
    """

    # Metres per tri-plane cell, one per pyramid level (reference 3.2: ScanNet (0.2, 0.06), Replica (0.1, 0.04)).
    # The Replica levels: at 6 cm a picture 2 cm in front of its wall shares the wall's cells and decodes as
    # wall (picture IoU 0.00 -> 0.95, mIoU 0.871 -> 0.945 on the small default room, seed 0; the full table
    # is in docs/benchmarks.md). The cost is per point, not per cell, so the finer planes cost little.
    cell_sizes: tuple[float, ...] = (0.1, 0.04)
    channels: int = 10  # latent channels C per plane (reference num_components)
    init_scale: float = 0.1  # std of the N(0, s^2) plane initialisation
    hidden_dims: tuple[int, ...] = (128,)  # decoder hidden widths: C -> 128 -> D (ScanNet), no biases
    epochs: int = 4  # passes over the seen primitives (reference: 11)
    # Small scenes get more passes, so every scene trains at least this many steps: at 4 epochs a 7.7k-point
    # scene made only 32 steps and its decoded argmax matched the true class on 0.79 of the points (CLIP
    # space); 16 epochs (128 steps) gave 0.98. 150 steps still lost whole classes on 30k-point rooms (small
    # default preset: every chair decoded as desk on seed 1, mIoU 0.845; 600 steps: 0.951, PRQ(T) 0.77 ->
    # 0.93). Large scenes are unaffected (150k points: 4 epochs are 600 steps).
    min_steps: int = 600
    batch_size: int = 1024  # primitives per step (reference: 256)
    lr: float = 5e-3  # Adam learning rate of the decoder MLP (reference: 1e-3)
    plane_lr: float = 1e-2  # Adam learning rate of the planes (reference: 1e-3, same as the MLP)
    weight_decay: float = 1e-6  # L2 on the decoder weights only (reference)
    betas: tuple[float, float] = (0.9, 0.99)  # Adam betas (reference)
    bound_padding: float = 0.05  # metres added on every side of the primitives' box
    max_resolution: int = 1024  # cap on plane resolution R per level (memory: 3*C*R^2 floats per level)
    # Torch device for training and decoding. The CLI keeps the CPU; a service worker sets "cuda" where it sees a
    # GPU, unless the job names a device (worker/device.py).
    device: str = "cpu"
    seed: int = 0  # seeds plane/decoder initialisation and batch shuffling

    def __post_init__(self) -> None:
        _require(len(self.cell_sizes) >= 1, "cell_sizes", "at least one level", self.cell_sizes)
        for size in self.cell_sizes:
            _require(math.isfinite(size) and size > 0, "cell_sizes", "positive finite metres", self.cell_sizes)
        _require(self.channels >= 1, "channels", ">= 1", self.channels)
        _require(math.isfinite(self.init_scale) and self.init_scale > 0, "init_scale", "> 0", self.init_scale)
        _require(all(h >= 1 for h in self.hidden_dims), "hidden_dims", "widths >= 1", self.hidden_dims)
        _require(self.epochs >= 1, "epochs", ">= 1", self.epochs)
        _require(self.batch_size >= 1, "batch_size", ">= 1", self.batch_size)
        _require(self.min_steps >= 0, "min_steps", ">= 0", self.min_steps)
        _require(math.isfinite(self.lr) and self.lr > 0, "lr", "> 0", self.lr)
        _require(math.isfinite(self.plane_lr) and self.plane_lr > 0, "plane_lr", "> 0", self.plane_lr)
        _require(self.weight_decay >= 0, "weight_decay", ">= 0", self.weight_decay)
        _require(
            len(self.betas) == 2 and all(0 <= b < 1 for b in self.betas),
            "betas",
            "two values in [0, 1)",
            self.betas,
        )
        _require(
            math.isfinite(self.bound_padding) and self.bound_padding >= 0,
            "bound_padding",
            ">= 0",
            self.bound_padding,
        )
        _require(self.max_resolution >= 2, "max_resolution", ">= 2", self.max_resolution)
        # Checked by form, not with torch.device: importing the config must not import torch (API process).
        _require(
            re.fullmatch(r"cpu|cuda(:\d+)?|mps", self.device) is not None,
            "device",
            "cpu, cuda, cuda:N or mps",
            self.device,
        )


def _require(ok: bool, name: str, expected: str, value: object) -> None:
    if not ok:
        raise ConfigError(f"language_field.{name}: expected {expected}, found {value!r}")


@dataclass(frozen=True)
class LanguageField:
    """The fitted field: decoded features of the primitives, the tri-plane box and the model weights."""

    features: np.ndarray  # (N, D) float32, decoded feature per primitive, unit rows
    bounds: np.ndarray  # (2, 3) float32, lo / hi corner of the tri-plane box, world metres
    state: dict[str, np.ndarray]  # "planes.<level>" (3, C, R, R), "mlp.<layer>" (out, in), float32

    @property
    def dim(self) -> int:
        """Feature dimension D."""
        return int(self.features.shape[1])

    def save(self, path: str | Path) -> None:
        """Write one ``.npz`` at exactly ``path``: features, bounds, each state array as ``state.<name>``."""
        arrays: dict[str, Any] = {f"{_STATE_PREFIX}{k}": v for k, v in self.state.items()}
        arrays.update(features=self.features, bounds=self.bounds)
        with Path(path).open("wb") as fh:  # a handle: np.savez would append ".npz" to a bare path
            np.savez(fh, **cast(dict[str, Any], arrays))

    @classmethod
    def load(cls, path: str | Path) -> LanguageField:
        """Read a field written by :meth:`save` (no pickles)."""
        with np.load(Path(path), allow_pickle=False) as data:
            state = {k[len(_STATE_PREFIX) :]: data[k] for k in data.files if k.startswith(_STATE_PREFIX)}
            return cls(features=data["features"], bounds=data["bounds"], state=state)


def plane_resolutions(bounds: np.ndarray, cfg: LanguageFieldConfig) -> list[int]:
    """Plane resolution R per level: ``int(max_extent / cell)``, capped to ``[2, cfg.max_resolution]``.

    Args:
        bounds: Tri-plane box. ``(2, 3)`` float, lo / hi.
        cfg: Cell sizes and the resolution cap.

    Returns:
        One resolution per level of ``cfg.cell_sizes``.
    """
    extent = float(np.max(bounds[1].astype(np.float64) - bounds[0].astype(np.float64)))
    return [min(max(int(extent / cell), 2), cfg.max_resolution) for cell in cfg.cell_sizes]


def field_bounds(points: np.ndarray, padding: float) -> np.ndarray:
    """Axis-aligned box of the points, padded by ``padding`` metres on every side. ``(2, 3)`` float32.

    DEPARTURE: the reference uses a hand-set box per scene (``scene.bound``, reference 1.4); we compute it
    from the primitives so that any scene works without one.
    """
    lo = points.min(axis=0).astype(np.float64) - padding
    hi = points.max(axis=0).astype(np.float64) + padding
    hi = np.maximum(hi, lo + 1e-3)  # a flat axis (all points on one plane) still gets a non-empty box
    return np.stack([lo, hi]).astype(np.float32)


def _check_inputs(points: np.ndarray, fused: FusedFeatures) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate and convert once: points (N, 3) float32, features (N, D), weights (N,) float32."""
    points = np.asarray(points, dtype=np.float32)
    features = np.asarray(fused.features)
    weights = np.asarray(fused.weights, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise ShapeError(f"points: expected a non-empty (N, 3) array, found shape {points.shape}")
    if not np.isfinite(points).all():
        raise InputError("points: contains NaN or infinite coordinates")
    n = points.shape[0]
    if features.ndim != 2 or features.shape[0] != n or features.shape[1] == 0:
        raise ShapeError(f"fused.features: expected shape ({n}, D), found {features.shape}")
    if weights.shape != (n,):
        raise ShapeError(f"fused.weights: expected shape ({n},), found {weights.shape}")
    if not np.isfinite(weights).all() or (weights < 0).any():
        raise InputError("fused.weights: expected finite values >= 0")
    if not (weights > 0).any():
        raise InputError("fused.weights: every weight is 0 (no primitive is seen by a feature frame)")
    return points, features, weights


def fit_language_field(
    points: np.ndarray,  # (N, 3) float32, world metres
    fused: FusedFeatures,  # features (N, D), weights (N,)
    cfg: LanguageFieldConfig,
    *,
    on_progress: ProgressFn | None = None,
) -> LanguageField:
    """Distil the fused 2D features into a pyramid tri-plane + MLP field (reference 3.2-3.3).

    Loss per batch: ``mean_i w_i * (1 - cos(MLP(g(x_i)), F_i))`` over the primitives with ``w_i > 0``.

    Args:
        points: Primitive centres. ``(N, 3)`` float, world frame, metres.
        fused: Fused features ``(N, D)`` and confidence weights ``(N,)`` (0 where unseen).
        cfg: Tri-plane, decoder and training settings.
        on_progress: Called as ``on_progress(epoch, epochs)`` after every epoch; may raise ``Cancelled``.

    Returns:
        The field, with the decoded unit feature of every primitive. ``features`` is ``(N, D)`` float32.

    Raises:
        ShapeError: if ``points``, ``fused.features`` and ``fused.weights`` disagree on shape.
        InputError: for non-finite inputs, negative weights, or when every weight is 0.
        NumericalError: if the loss becomes NaN or infinite.

    Example:
        >>> from types import SimpleNamespace
        >>> points = np.random.default_rng(0).uniform(size=(200, 3)).astype(np.float32)
        >>> fused = SimpleNamespace(features=np.ones((200, 8), np.float32), weights=np.ones(200, np.float32))
        >>> field = fit_language_field(points, fused, LanguageFieldConfig(epochs=1, hidden_dims=(16,)))
        >>> field.features.shape, decode_points(field, points[:5]).shape
        ((200, 8), (5, 8))
    """
    import torch

    from panogs_core.triplane import _decode, _init_model, _state_of, _train, _training_set

    points, features, weights = _check_inputs(points, fused)
    device = torch.device(cfg.device)
    bounds = field_bounds(points, cfg.bound_padding)  # (2, 3) float32
    model = _init_model(plane_resolutions(bounds, cfg), features.shape[1], cfg)
    coords, targets, w = _training_set(points, features, weights, bounds, device)
    _train(model, coords, targets, w, cfg, on_progress)
    model.eval()
    decoded = _decode(model, points, bounds)  # (N, D)
    return LanguageField(features=decoded, bounds=bounds, state=_state_of(model))


def decode_points(
    field: LanguageField,
    points: np.ndarray,  # (P, 3) float, world metres
    *,
    device: str = "cpu",
) -> np.ndarray:  # (P, D) float32, unit rows
    """Decode the language feature of any 3D points with a fitted (or loaded) field.

    Points outside the tri-plane box take the value at the nearest box face.

    Args:
        field: A field from :func:`fit_language_field` or :meth:`LanguageField.load`.
        points: Query points. ``(P, 3)`` float, world frame, metres.
        device: Torch device to decode on.

    Returns:
        Unit feature rows. ``(P, D)`` float32.

    Raises:
        ShapeError: if ``points`` is not ``(P, 3)``.
    """
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError(f"points: expected shape (P, 3), found {points.shape}")
    import torch

    from panogs_core.triplane import _decode, _model_from_state

    model = _model_from_state(field.state, torch.device(device))
    return _decode(model, points, np.asarray(field.bounds, dtype=np.float32))
