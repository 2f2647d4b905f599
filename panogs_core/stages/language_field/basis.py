"""The scene's own feature basis: the decoder predicts in it, and the loss is taken in it (docs/method.md §3.3).

The fused features of one room span far fewer directions than their ``D`` dimensions (a few dozen classes and
materials). With ``U`` (``D``, ``k``) orthonormal and the decoder's last layer ``W = U V``, the cosine of the
prediction to a unit target ``t`` is ``(V h) . (U^T t) / |V h|``: exactly the cosine in ``D`` dimensions of a
decoder whose outputs lie in ``U``'s span. Training reads the ``k``-dim coefficients ``U^T t`` instead of the
``D``-dim rows, so the per-point matrix products of a step shrink by ``D / k``. What the basis leaves out of a
target is what no decoder of that span can predict (:func:`kept_energy` measures it).
"""

from __future__ import annotations

import torch

# Rows of the second-moment estimate: 8192 unit rows of D = 512 make a 512 x 512 matrix in about 4 GFLOP,
# against 37 GFLOP for the 70k seen primitives of a ScanNet-size room. The basis from 8192 rows keeps 0.8771 of
# that room's target energy at 64 directions, the one from all 69,638 rows 0.8785 (32: 0.8409 and 0.8418;
# docs/benchmarks.md, "Language field speed").
BASIS_SAMPLE_ROWS = 8192
# Rows read at a time: no (M, D) copy of the features is made, and each temporary stays at 2 MiB (D = 512). With
# 8192 rows, the 16 MiB temporaries stayed resident after they were freed and the run's peak grew by 50-60 MB
# (docs/benchmarks.md, "Language field speed").
_PROJECT_BATCH = 1024


def feature_basis(
    features: torch.Tensor,  # (N, D) as fused, not unit
    rows: torch.Tensor,  # (M,) int64, the rows that train (weight > 0)
    inverse_norms: torch.Tensor,  # (M,) 1 / |features[rows]|
    weights: torch.Tensor,  # (M,) > 0, confidence of each row
    dims: int,
    seed: int,
) -> torch.Tensor:  # (D, k) float32, orthonormal columns, k = min(dims, D)
    """The ``k`` directions that keep most of the confidence-weighted energy of the unit target rows.

    Top eigenvectors of ``sum_i w_i t_i t_i^T`` (not centred: the mean direction of a room's features is part of
    every target) over at most :data:`BASIS_SAMPLE_ROWS` rows drawn with a seeded generator, read in batches.
    """
    dim = features.shape[1]
    count = rows.shape[0]
    gen = torch.Generator().manual_seed(seed)
    pick = torch.randperm(count, generator=gen)[:BASIS_SAMPLE_ROWS].to(rows.device)
    moment = features.new_zeros((dim, dim))  # (D, D)
    for start in range(0, pick.shape[0], _PROJECT_BATCH):
        part = pick[start : start + _PROJECT_BATCH]
        unit = features.index_select(0, rows.index_select(0, part)).mul_(inverse_norms.index_select(0, part)[:, None])
        moment.addmm_(unit.t(), unit * weights.index_select(0, part).unsqueeze(1))
    _, vectors = torch.linalg.eigh(moment.double().cpu())  # ascending eigenvalues
    top = vectors[:, dim - min(dims, dim) :].flip(1)  # (D, k), largest first
    return top.to(dtype=torch.float32, device=features.device).contiguous()


def project_rows(
    features: torch.Tensor,  # (N, D) as fused
    rows: torch.Tensor,  # (M,) int64
    inverse_norms: torch.Tensor,  # (M,)
    basis: torch.Tensor,  # (D, k)
) -> torch.Tensor:  # (M, k) coefficients of the unit rows
    """``U^T t`` for the unit target of every training row, in batches."""
    out = features.new_empty((rows.shape[0], basis.shape[1]))
    for start in range(0, rows.shape[0], _PROJECT_BATCH):
        part = rows[start : start + _PROJECT_BATCH]
        torch.mm(features.index_select(0, part), basis, out=out[start : start + part.shape[0]])
    out.mul_(inverse_norms.unsqueeze(1))
    return out


def kept_energy(coefficients: torch.Tensor, weights: torch.Tensor) -> float:
    """The confidence-weighted share of the unit targets' squared length the basis keeps, in ``[0, 1]``.

    ``1 - kept`` bounds from below the mean ``1 - cos^2`` that any decoder in the basis leaves.
    """
    kept = (coefficients * coefficients).sum(dim=1)  # (M,) |U^T t|^2, t unit
    return float((kept * weights).sum() / weights.sum())
