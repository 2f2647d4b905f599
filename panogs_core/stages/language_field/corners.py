"""Where the training points sample the tri-plane, and the gather and scatter of a batch's corners.

The training points never move, so each one's bilinear corners in every plane (24 cells for two levels) and their
weights are computed once (:func:`bilinear_corners`); the planes train as one ``(cells, C)`` table
(:func:`plane_table`). A step's latent is ``sum_k weight_k * table[cell_k]`` and the table's gradient its
transpose: both are products with the batch's sparse ``(B, cells)`` matrix of corner weights
(:class:`BatchCorners`).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy import sparse

# The (width, height) coordinates of each plane: plane 0 is (x, y), plane 1 (x, z), plane 2 (y, z).
_PLANE_AXES = ((0, 1), (0, 2), (1, 2))


def bilinear_corners(
    coords: torch.Tensor,  # (M, 3) in [-1, 1]
    resolutions: list[int],
) -> tuple[torch.Tensor, torch.Tensor]:  # (M, K) int64, (M, K) float32, K = 12 per level
    """The plane cells a point samples and their bilinear weights, in the layout of :func:`plane_table`.

    The same sampling as the decoder's ``encode`` (``grid_sample``, bilinear, ``align_corners=True``, border
    padding): ``latent = sum_k weight_k * table[cell_k]``. Written column by column into the two results, so no
    list of K columns is held beside them. The cells stay int64: torch's CPU ``index_select`` and ``index_add_``
    took 2.5x as long with int32 indices (1,024 points of 24 corners, one thread).
    """
    count, corners = coords.shape[0], 12 * len(resolutions)
    cells = torch.empty((count, corners), dtype=torch.int64, device=coords.device)
    weights = torch.empty((count, corners), dtype=torch.float32, device=coords.device)
    offset, column = 0, 0
    for res in resolutions:
        for a, b in _PLANE_AXES:
            x = ((coords[:, a] + 1.0) * 0.5 * (res - 1)).clamp(0.0, res - 1.0)  # width position
            y = ((coords[:, b] + 1.0) * 0.5 * (res - 1)).clamp(0.0, res - 1.0)  # height position
            x0 = x.floor().clamp(max=res - 2)
            y0 = y.floor().clamp(max=res - 2)
            fx, fy = x - x0, y - y0
            base = offset + y0.long() * res + x0.long()
            for cell, weight in (
                (base, (1 - fx) * (1 - fy)),
                (base + 1, fx * (1 - fy)),
                (base + res, (1 - fx) * fy),
                (base + res + 1, fx * fy),
            ):
                cells[:, column] = cell
                weights[:, column] = weight
                column += 1
            offset += res * res
    return cells, weights


def plane_table(planes: list[torch.Tensor]) -> torch.Tensor:  # (cells, C)
    """Every level's ``(3, C, R, R)`` planes as one ``(sum 3 R^2, C)`` table, rows in (level, plane, y, x) order."""
    return torch.cat([p.permute(0, 2, 3, 1).reshape(-1, p.shape[1]) for p in planes])


def planes_from_table(table: torch.Tensor, resolutions: list[int]) -> list[torch.Tensor]:
    """The inverse of :func:`plane_table`: ``(cells, C)`` -> per level ``(3, C, R, R)``."""
    planes, offset = [], 0
    for res in resolutions:
        block = table[offset : offset + 3 * res * res]
        planes.append(block.reshape(3, res, res, -1).permute(0, 3, 1, 2).contiguous())
        offset += 3 * res * res
    return planes


def gathered_latent(
    table: torch.Tensor,  # (cells, C)
    cells: torch.Tensor,  # (B, K) rows of the table
    corner_weights: torch.Tensor,  # (B, K)
) -> torch.Tensor:  # (B, C)
    """``sum_k weight_k * table[cell_k]`` with torch's index ops: the tri-plane latent of points whose corners are
    known."""
    rows = table.index_select(0, cells.reshape(-1)).reshape(*cells.shape, table.shape[1])  # (B, K, C)
    return (rows * corner_weights.unsqueeze(2)).sum(dim=1)


def add_table_gradient(
    grad: torch.Tensor,  # (cells, C), overwritten
    cells: torch.Tensor,  # (B, K)
    corner_weights: torch.Tensor,  # (B, K)
    latent_grad: torch.Tensor,  # (B, C)
) -> torch.Tensor:  # grad
    """The table's gradient of a batch with torch's index ops, written into a buffer kept across steps.

    The backward of :func:`gathered_latent` by hand: autograd would allocate a fresh ``(cells, C)`` zero
    gradient every step, whose page faults cost twice the zeroing and the scatter together.
    """
    grad.zero_()
    rows = (corner_weights.unsqueeze(2) * latent_grad.unsqueeze(1)).reshape(-1, grad.shape[1])  # (B K, C)
    grad.index_add_(0, cells.reshape(-1), rows)
    return grad


class BatchCorners:
    """A batch's corners and weights: its latent from the table, and the table's gradient from the latent's.

    On the CPU both are products with the batch's ``(B, cells)`` CSR matrix ``S`` of corner weights (24 entries a
    row): ``latent = S table`` and ``grad = S^T latent_grad``, scipy's sparse kernels, one C loop each. torch's
    CPU ``index_select`` and ``index_add_`` on rows of C = 10 floats pay a per-row dispatch: on the AVX2 AMD EPYC
    they took 1.9 and 4.8 CPU ms a step (1,024 points), scipy's products 1.0 and 1.0 (docs/benchmarks.md,
    "Language field speed"). Elsewhere (a GPU) the torch ops of :func:`gathered_latent` and
    :func:`add_table_gradient`, into a gradient buffer kept across steps.
    """

    def __init__(self, table: torch.Tensor) -> None:
        self.table = table  # (cells, C), trained in place
        self.on_cpu = table.device.type == "cpu"
        self._grad = None if self.on_cpu else torch.zeros_like(table)  # (cells, C), reused by every step
        self._table_rows = table.detach().numpy() if self.on_cpu else None  # the table's memory, not a copy
        self._matrix: sparse.csr_matrix | None = None
        self._cells: torch.Tensor | None = None
        self._weights: torch.Tensor | None = None

    def latent(self, cells: torch.Tensor, corner_weights: torch.Tensor) -> torch.Tensor:  # (B, C)
        """The latent of a batch of points from their corners ``(B, K)`` and weights ``(B, K)``."""
        if not self.on_cpu:
            self._cells, self._weights = cells, corner_weights
            return gathered_latent(self.table, cells, corner_weights)
        count, corners = cells.shape
        indptr = np.arange(0, count * corners + 1, corners, dtype=np.int64)
        self._matrix = sparse.csr_matrix(
            (corner_weights.numpy().reshape(-1), cells.numpy().reshape(-1), indptr),
            shape=(count, self.table.shape[0]),
        )
        return torch.from_numpy(self._matrix @ self._table_rows)

    def table_gradient(self, latent_grad: torch.Tensor) -> torch.Tensor:  # (cells, C)
        """The table's gradient of the last :meth:`latent`'s batch, given the latent's gradient ``(B, C)``."""
        if not self.on_cpu:
            assert self._grad is not None
            assert self._cells is not None
            assert self._weights is not None
            return add_table_gradient(self._grad, self._cells, self._weights, latent_grad)
        assert self._matrix is not None
        return torch.from_numpy(self._matrix.T @ latent_grad.numpy())
