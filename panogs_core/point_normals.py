"""Unoriented PCA normals, as open3d 0.20's ``PointCloud.estimate_normals`` makes them, without importing open3d.

Stage 1 (:mod:`panogs_core.stages.primitives`) gives every primitive the normal the reference gets from open3d
(hybrid search, radius 0.1 m, 30 neighbours; docs/method.md §4.1). Importing open3d for that one call cost a
ScanNet-size run 0.21-0.33 s of its start (docs/benchmarks.md, "Fusion and primitives speed"); open3d is still
imported for the TSDF path, which needs its voxel block grid.

The graph cut reads ``1 - n_a . n_b`` with the normals' signs as they come (docs/method.md pitfall 10), so the sign
is part of the result: it is the one open3d's construction gives, reproduced step by step.

* **Neighbourhood**: the ``max_nn`` nearest points (the point itself among them) closer than ``radius``
  (``d^2 < r^2``: open3d keeps the k nearest, then cuts at the radius). Fewer than 3: the normal is ``(0, 0, 1)``.
* **Covariance** from the raw moments, ``E[x x^T] - E[x] E[x]^T`` (open3d's form; not the two-pass one).
* **Eigenvector of the smallest eigenvalue** by the closed form for symmetric 3 x 3 matrices of D. Eberly, "A
  Robust Eigensolver for 3 x 3 Symmetric Matrices" (Geometric Tools, 2014), on the matrix divided by its largest
  entry, with open3d's choices where it has a choice: the eigenvalues from the trigonometric solution; the first
  eigenvector of the extreme eigenvalue on the side of ``det / 2`` (the largest when ``det / 2 >= 0``, else the
  smallest) as the longest cross product of two rows of ``A - lambda I``; the second from the 2 x 2 problem in
  the plane orthogonal to it; the third as their cross product. A matrix with no off-diagonal entry gives the
  axis of its smallest diagonal entry.

On the ScanNet-size room (78,556 vertices) every normal equals open3d's as float32 (``tests/core/test_point_normals.py``
compares the two on clouds of several shapes).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

_DEFAULT_NORMAL = np.array([0.0, 0.0, 1.0])  # what open3d gives a point with fewer than 3 neighbours
_MIN_NEIGHBOURS = 3
_CHUNK = 16384  # points per block: its (chunk, max_nn) neighbour lists and gathers stay a few MB
_TWO_THIRDS_PI = 2.09439510239319549


def pca_normals(
    points: np.ndarray,  # (N, 3)
    radius: float,
    max_nn: int,
    tree: cKDTree | None = None,  # a tree of ``points`` as float64, when the caller has one
) -> np.ndarray:  # (N, 3) float64, unit, unoriented
    """Unit normals by PCA over each point's neighbourhood, signed as open3d signs them (module docstring).

    Example:
        >>> grid = np.stack(np.meshgrid(np.arange(5.0), np.arange(5.0), [0.0]), -1).reshape(-1, 3) * 0.02
        >>> np.abs(pca_normals(grid, 0.1, 30)[:, 2]).min()
        np.float64(1.0)
    """
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    normals = np.empty((n, 3))
    if n == 0:
        return normals
    tree = cKDTree(points) if tree is None else tree
    by_axis = np.ascontiguousarray(points.T)  # (3, N): each gather reads one contiguous coordinate
    # Block by block of points: the neighbour lists (N x 30 x 16 bytes, 1.2 GB for a 2.5M-vertex building mesh) and
    # the eigen-solver's temporaries are never held for all points at once.
    for lo in range(0, n, _CHUNK):
        queries = points[lo : lo + _CHUNK]
        normals[lo : lo + len(queries)] = smallest_eigenvectors(
            _neighbourhood_covariances(queries, by_axis, tree, radius, max_nn)
        )
    return normals


def _neighbourhood_covariances(
    queries: np.ndarray,  # (B, 3) float64, points of the tree
    by_axis: np.ndarray,  # (3, N) float64, the tree's points, a coordinate a row
    tree: cKDTree,
    radius: float,
    max_nn: int,
) -> np.ndarray:  # (B, 3, 3) float64; the identity where fewer than 3 neighbours
    """Covariance of each query's neighbourhood (its ``max_nn`` nearest points closer than ``radius``)."""
    n, b = by_axis.shape[1], len(queries)
    k = min(max_nn, n)
    # (B, k), nearest first, the point itself included; a little beyond the radius (inf, index N past it), then
    # open3d's own cut d^2 < r^2. The bound halves the query's time.
    dist, index = tree.query(queries, k=k, distance_upper_bound=radius * (1.0 + 1e-6), workers=-1)
    dist, index = dist.reshape(b, k), np.minimum(index.reshape(b, k), n - 1)
    inside = dist * dist < radius * radius  # (B, k)
    count = inside.sum(axis=1)  # (B,)
    # (k, B): neighbour by neighbour, so that numpy's sums over axis 0 add them one after the other, nearest first, as
    # open3d adds them (its sums are sequential; numpy's along a row are pairwise)
    covariances = _moments_covariance(by_axis, np.ascontiguousarray(index.T), np.ascontiguousarray(inside.T), count)
    covariances[count < _MIN_NEIGHBOURS] = np.eye(3)
    return covariances


def _moments_covariance(
    points: np.ndarray,  # (3, N) float64, a coordinate a row
    index: np.ndarray,  # (k, B) neighbour indices, nearest first
    inside: np.ndarray,  # (k, B) bool, the neighbours that count
    count: np.ndarray,  # (B,) how many count
) -> np.ndarray:  # (B, 3, 3)
    """``E[x x^T] - E[x] E[x]^T`` over each point's counted neighbours, by coordinate, divided as open3d divides."""
    size = np.maximum(count, 1).astype(np.float64)  # (B,)
    coords = [np.where(inside, column[index], 0.0) for column in points]  # 3 x (k, B)
    mean = [c.sum(axis=0) / size for c in coords]  # 3 x (B,)
    out = np.empty((index.shape[1], 3, 3))
    for i in range(3):
        for j in range(i, 3):
            out[:, i, j] = out[:, j, i] = (coords[i] * coords[j]).sum(axis=0) / size - mean[i] * mean[j]
    return out


def smallest_eigenvectors(covariances: np.ndarray) -> np.ndarray:  # (N, 3) float64 unit rows
    """The unit eigenvector of each symmetric 3 x 3 matrix's smallest eigenvalue, by open3d's construction.

    A zero matrix gives ``(0, 0, 1)`` (open3d's fallback for a normal of length 0).
    """
    n = len(covariances)
    out = np.tile(_DEFAULT_NORMAL, (n, 1))
    largest = covariances.reshape(n, 9).max(axis=1)  # (N,)
    nonzero = largest != 0
    a = covariances[nonzero] / largest[nonzero, None, None]  # (M, 3, 3) scaled as open3d scales
    off = a[:, 0, 1] ** 2 + a[:, 0, 2] ** 2 + a[:, 1, 2] ** 2  # (M,)
    diagonal = off <= 0
    vectors = np.empty((len(a), 3))
    vectors[diagonal] = _axis_of_smallest_diagonal(a[diagonal])
    vectors[~diagonal] = _trigonometric_smallest(a[~diagonal], off[~diagonal])
    out[nonzero] = vectors
    return out


def _axis_of_smallest_diagonal(a: np.ndarray) -> np.ndarray:  # (M, 3)
    """A diagonal matrix: x or y when strictly the smallest entry, else z (open3d's order of tests)."""
    d0, d1, d2 = a[:, 0, 0], a[:, 1, 1], a[:, 2, 2]
    axis = np.where((d0 < d1) & (d0 < d2), 0, np.where((d1 < d0) & (d1 < d2), 1, 2))
    return np.eye(3)[axis]


def _trigonometric_smallest(a: np.ndarray, off: np.ndarray) -> np.ndarray:  # (M, 3)
    """Eberly's closed form on matrices with an off-diagonal entry (``off`` the sum of their squares)."""
    q = np.trace(a, axis1=1, axis2=2) / 3.0
    b00, b11, b22 = a[:, 0, 0] - q, a[:, 1, 1] - q, a[:, 2, 2] - q
    a01, a02, a12 = a[:, 0, 1], a[:, 0, 2], a[:, 1, 2]
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + off * 2.0) / 6.0)
    c00 = b11 * b22 - a12 * a12
    c01 = a01 * b22 - a12 * a02
    c02 = a01 * a12 - b11 * a02
    half_det = np.clip((b00 * c00 - a01 * c01 + a02 * c02) / (p * p * p) * 0.5, -1.0, 1.0)
    angle = np.arccos(half_det) / 3.0
    beta2 = np.cos(angle) * 2.0
    beta0 = np.cos(angle + _TWO_THIRDS_PI) * 2.0
    beta1 = -(beta0 + beta2)
    values = np.stack([q + p * beta0, q + p * beta1, q + p * beta2], axis=1)  # (M, 3) ascending but for rounding
    out = np.empty((len(a), 3))
    for from_largest in (True, False):
        rows = np.flatnonzero((half_det >= 0) == from_largest)
        if rows.size:
            out[rows] = _from_extreme(a[rows], values[rows], from_largest)
    return out


def _from_extreme(a: np.ndarray, values: np.ndarray, from_largest: bool) -> np.ndarray:  # (M, 3)
    """The smallest eigenvalue's vector, built as open3d builds it from the largest eigenvalue's vector (or the
    smallest's, by the sign of ``det / 2``): that vector where its eigenvalue is strictly the smallest, else the middle
    one where that is, else the third as their cross product (middle x first from the largest, first x middle from
    the smallest)."""
    start = 2 if from_largest else 0
    first = _vector_by_row_crosses(a, values[:, start])
    out = first.copy()
    rest = np.flatnonzero(~_strictly_smallest(values, start))
    if rest.size == 0:
        return out
    middle = _vector_in_orthogonal_plane(a[rest], first[rest], values[rest, 1])
    third = np.cross(middle, first[rest]) if from_largest else np.cross(first[rest], middle)
    out[rest] = np.where(_strictly_smallest(values[rest], 1)[:, None], middle, third)
    return out


def _strictly_smallest(values: np.ndarray, i: int) -> np.ndarray:  # (M,) bool
    others = [j for j in range(3) if j != i]
    return (values[:, i] < values[:, others[0]]) & (values[:, i] < values[:, others[1]])


def _vector_by_row_crosses(a: np.ndarray, value: np.ndarray) -> np.ndarray:  # (M, 3) unit
    """Eigenvector of a simple eigenvalue: the longest cross product of two rows of ``A - value I`` (first wins
    ties, in the order r0 x r1, r0 x r2, r1 x r2)."""
    shifted = a - value[:, None, None] * np.eye(3)
    r0, r1, r2 = shifted[:, 0], shifted[:, 1], shifted[:, 2]
    crosses = np.stack([np.cross(r0, r1), np.cross(r0, r2), np.cross(r1, r2)], axis=1)  # (M, 3, 3)
    lengths = crosses[:, :, 0] ** 2 + crosses[:, :, 1] ** 2 + crosses[:, :, 2] ** 2  # (M, 3) squared, as open3d sums
    best = np.where(lengths[:, 1] > lengths[:, 0], 1, 0)
    best = np.where(lengths[:, 2] > lengths[np.arange(len(a)), best], 2, best)
    rows = np.arange(len(a))
    with np.errstate(divide="ignore", invalid="ignore"):  # a zero matrix A - value I: NaN, as open3d's
        return crosses[rows, best] / np.sqrt(lengths[rows, best])[:, None]


def _vector_in_orthogonal_plane(a: np.ndarray, first: np.ndarray, value: np.ndarray) -> np.ndarray:  # (M, 3)
    """Eigenvector of ``value`` orthogonal to the unit ``first``: the 2 x 2 problem on a basis (U, V) of the plane."""
    x, y, z = first[:, 0], first[:, 1], first[:, 2]
    zero = np.zeros(len(a))
    by_x = np.abs(x) > np.abs(y)
    with np.errstate(divide="ignore", invalid="ignore"):  # only the chosen side's length is ever used
        inv_x = (1.0 / np.sqrt(x * x + z * z))[:, None]
        inv_y = (1.0 / np.sqrt(y * y + z * z))[:, None]
        u = np.where(by_x[:, None], np.stack([-z, zero, x], axis=1) * inv_x, np.stack([zero, z, -y], axis=1) * inv_y)
    v = np.cross(first, u)
    au, av = _times(a, u), _times(a, v)
    m00 = _dot(u, au) - value
    m01 = _dot(u, av)
    m11 = _dot(v, av) - value
    # Solve [m00 m01; m01 m11] (s, t) = 0 by the row of larger entries, normalised without overflow.
    use_top = np.abs(m00) >= np.abs(m11)
    diag = np.where(use_top, m00, m11)
    coef_u, coef_v = _null_direction(diag, m01, use_top)
    out = coef_u[:, None] * u - coef_v[:, None] * v
    degenerate = np.maximum(np.abs(diag), np.abs(m01)) <= 0
    out[degenerate] = u[degenerate]
    return out


def _times(a: np.ndarray, u: np.ndarray) -> np.ndarray:  # (M, 3): A u, summed left to right as open3d sums
    return a[:, :, 0] * u[:, 0:1] + a[:, :, 1] * u[:, 1:2] + a[:, :, 2] * u[:, 2:3]


def _dot(u: np.ndarray, w: np.ndarray) -> np.ndarray:  # (M,): u . w, summed left to right
    return u[:, 0] * w[:, 0] + u[:, 1] * w[:, 1] + u[:, 2] * w[:, 2]


def _null_direction(
    diag: np.ndarray, m01: np.ndarray, use_top: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:  # coefficients of U and of V, each (M,)
    """open3d's normalisation of the chosen row ``(diag, m01)`` (top row: (m00, m01); bottom: (m01, m11)).

    Top row, ``|m00| >= |m01|``: t = m01 / m00, m00' = 1 / sqrt(1 + t^2), m01' = t m00'; result m01' U - m00' V.
    Top row otherwise: t = m00 / m01, m01' = 1 / sqrt(1 + t^2), m00' = t m01'; the same result.
    Bottom row: the same with m11 for m00 and the result m11' U - m01' V.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        by_diag = np.abs(diag) >= np.abs(m01)
        t_diag = m01 / diag  # the row divided by its diagonal entry
        s_diag = 1.0 / np.sqrt(1.0 + t_diag * t_diag)
        t_off = diag / m01  # ... by its off-diagonal entry
        s_off = 1.0 / np.sqrt(1.0 + t_off * t_off)
        diag_n = np.where(by_diag, s_diag, t_off * s_off)  # the normalised diagonal entry
        off_n = np.where(by_diag, t_diag * s_diag, s_off)  # the normalised off-diagonal entry
    # top: m01' U - m00' V; bottom: m11' U - m01' V
    return np.where(use_top, off_n, diag_n), np.where(use_top, diag_n, off_n)
