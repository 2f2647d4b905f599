"""Stage 4: the continuous 3D language field (docs/method.md §3.2-3.3).

A latent pyramid tri-plane (per level three ``(C, R, R)`` planes, bilinearly sampled, summed over planes and
over levels into a ``C``-dim latent) followed by a bias-free MLP decoder is fitted to the fused multi-view
features of the primitives with a confidence-weighted cosine loss. The fitted field gives a language feature
for every primitive (smoothed across space, defined where no frame saw a primitive) and for any 3D point.

Inputs: primitive centres ``(N, 3)`` and :class:`panogs_core.stages.fusion.FusedFeatures` (targets ``(N, D)``,
confidence ``(N,)``). Output: :class:`LanguageField` (decoded unit features, tri-plane box, model weights).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from panogs_core.errors import InputError, ShapeError
from panogs_core.heap import return_freed_heap
from panogs_core.io.npz import save_npz
from panogs_core.progress import ProgressFn
from panogs_core.stages.language_field.config import LanguageFieldConfig
from panogs_core.threads import torch_threads

if TYPE_CHECKING:
    from panogs_core.stages.fusion import FusedFeatures

_STATE_PREFIX = "state."


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
        save_npz(path, **cast(dict[str, Any], arrays))

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

    DEPARTURE (docs/method.md §3.2): the box comes from the primitives, not from a hand-set ``scene.bound`` per
    scene, so any scene works without one.
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
    """Distil the fused 2D features into a pyramid tri-plane + MLP field (docs/method.md §3.2-3.3).

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
        >>> field = fit_language_field(points, fused, LanguageFieldConfig(epochs=1, min_steps=0, hidden_dims=(16,)))
        >>> field.features.shape, decode_points(field, points[:5]).shape
        ((200, 8), (5, 8))
    """
    return finish_language_field(set_up_language_field(points, fused, cfg), on_progress=on_progress)


@dataclass
class FieldSetUp:
    """A field ready to fit: its model at its start and its training set, made from the fused features.

    With the scene's feature basis (``basis_dims``, the default) the training set holds the targets' coefficients
    only, not the fused ``(N, D)`` features: a caller that drops its own reference to them after
    :func:`set_up_language_field` frees them before the decoding makes its ``(N, D)`` output (161 MB each at
    ScanNet size; the pipeline does, ``StageSpec.takes``).
    """

    points: np.ndarray  # (N, 3) float32, the primitives' centres, as checked
    bounds: np.ndarray  # (2, 3) float32, the tri-plane box
    model: Any  # triplane._TriplaneDecoder at its start
    data: Any  # triplane.TrainingSet, or None once the fit is done
    cfg: LanguageFieldConfig


def set_up_language_field(points: np.ndarray, fused: FusedFeatures, cfg: LanguageFieldConfig) -> FieldSetUp:
    """The first part of :func:`fit_language_field`: the inputs checked, the model made, the training set built.

    Raises:
        ShapeError, InputError: as :func:`fit_language_field`.
    """
    import torch

    from panogs_core.stages.language_field.triplane import TrainingSet, init_model

    points, features, weights = _check_inputs(points, fused)
    device = torch.device(cfg.device)
    bounds = field_bounds(points, cfg.bound_padding)  # (2, 3) float32
    resolutions = plane_resolutions(bounds, cfg)
    with torch_threads(cfg.cpu_threads if device.type == "cpu" else None):
        model = init_model(resolutions, features.shape[1], cfg)
        data = TrainingSet(
            points, features, weights, bounds, resolutions, device, basis_dims=cfg.basis_dims, seed=cfg.seed
        )
    return FieldSetUp(points=points, bounds=bounds, model=model, data=data, cfg=cfg)


def finish_language_field(setup: FieldSetUp, *, on_progress: ProgressFn | None = None) -> LanguageField:
    """The rest of :func:`fit_language_field`: the fit, then every primitive decoded.

    Raises:
        NumericalError: if the loss becomes NaN or infinite.
    """
    import torch

    from panogs_core.stages.language_field.triplane import decode_features, state_of, train_model

    cfg, model = setup.cfg, setup.model
    with torch_threads(cfg.cpu_threads if torch.device(cfg.device).type == "cpu" else None):
        train_model(model, setup.data, cfg, on_progress)
    setup.data = None  # its corners and targets (about 40 MB at ScanNet size) are not held while the decoding's are
    return_freed_heap()  # the training's freed temporaries would stay resident beside the decoding's output
    model.eval()
    # The decoding is a few large products, row by row (the same to the bit at any thread count): it takes the run's
    # threads. The set-up and the steps stay at ``cpu_threads``: the basis and the projection, products over 512 and
    # more terms, change in the last bits with the count (docs/benchmarks.md, "Language field speed").
    decoded = decode_features(model, setup.points, setup.bounds)  # (N, D)
    return LanguageField(features=decoded, bounds=setup.bounds, state=state_of(model))


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

    from panogs_core.stages.language_field.triplane import decode_features, model_from_state

    model = model_from_state(field.state, torch.device(device))
    return decode_features(model, points, np.asarray(field.bounds, dtype=np.float32))
