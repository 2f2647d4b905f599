"""The primitives' normals without open3d: the same vectors, signs included, as open3d's ``estimate_normals``."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from panogs_core.point_normals import pca_normals, smallest_eigenvectors
from panogs_core.stages.primitives import _open3d

RNG_SEED = 7


def _open3d_normals(points: np.ndarray, radius: float, max_nn: int) -> np.ndarray:  # (N, 3) float64
    o3d = _open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
    return np.asarray(cloud.normals)


def _open3d_smallest(covariances: np.ndarray) -> np.ndarray:  # (N, 3): open3d's vector of given matrices
    """A cloud that has covariances takes them as they are (open3d skips its neighbour search)."""
    o3d = _open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.zeros((len(covariances), 3))))
    cloud.covariances = o3d.utility.Matrix3dVector(covariances)
    cloud.estimate_normals()
    return np.asarray(cloud.normals)


def _noisy_plane(rng: np.random.Generator) -> np.ndarray:
    return np.c_[rng.random((4000, 2)), rng.normal(0.0, 0.003, 4000)]


def _sphere(rng: np.random.Generator) -> np.ndarray:
    points = rng.normal(size=(4000, 3))
    return points / np.linalg.norm(points, axis=1, keepdims=True)


def _box_corner(rng: np.random.Generator) -> np.ndarray:  # three faces meeting: normals turn across the edges
    faces = [
        np.c_[rng.random((1500, 2)) * 0.5, np.zeros(1500)][:, order] for order in ([0, 1, 2], [0, 2, 1], [2, 0, 1])
    ]
    return np.concatenate(faces)


def _jittered_grid(rng: np.random.Generator) -> np.ndarray:  # a mesh's vertices: a lattice, but no exact ties
    xs, ys = np.meshgrid(np.arange(60) * 0.02, np.arange(60) * 0.02)
    return np.c_[xs.ravel(), ys.ravel(), 0.3 * xs.ravel() ** 2] + rng.normal(0.0, 1e-4, (xs.size, 3))


def _scattered(rng: np.random.Generator) -> np.ndarray:  # sparse: many points with fewer than 3 neighbours
    return rng.random((3000, 3)) * 3.0


def _duplicates(rng: np.random.Generator) -> np.ndarray:  # every point four times (meshes repeat vertices)
    return np.repeat(rng.random((400, 3)) * 0.5, 4, axis=0)


def _line(rng: np.random.Generator) -> np.ndarray:  # rank-one covariances
    return np.c_[np.arange(300) * 0.01, np.zeros(300), np.zeros(300)]


CLOUDS: dict[str, Callable[[np.random.Generator], np.ndarray]] = {
    "noisy plane": _noisy_plane,
    "sphere": _sphere,
    "box corner": _box_corner,
    "jittered grid": _jittered_grid,
    "scattered": _scattered,
    "duplicates": _duplicates,
    "line": _line,
}


@pytest.mark.parametrize("name", sorted(CLOUDS))
def test_same_normals_as_open3d(name: str) -> None:
    """Direction and sign: the graph cut reads 1 - n_a . n_b with the signs as they come."""
    points = CLOUDS[name](np.random.default_rng(RNG_SEED))
    ours, theirs = pca_normals(points, 0.1, 30), _open3d_normals(points, 0.1, 30)
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-9)


@pytest.mark.parametrize("max_nn", [1, 2, 3, 30])
def test_few_neighbours_give_the_z_axis(max_nn: int) -> None:
    points = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0], [5.0, 5.0, 5.0]])
    ours = pca_normals(points, 0.1, max_nn)
    np.testing.assert_allclose(ours, _open3d_normals(points, 0.1, max_nn), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(ours[3], [0.0, 0.0, 1.0])  # alone within the radius


def test_every_branch_of_the_eigenvector_matches_open3d() -> None:
    """General, rank-one and rank-two matrices, multiples of the identity, diagonal ones with and without ties."""
    rng = np.random.default_rng(RNG_SEED)
    m = rng.normal(size=(2000, 3, 3))
    u, w = rng.normal(size=(300, 3)), rng.normal(size=(300, 3, 2))
    matrices = {
        "general": m @ m.transpose(0, 2, 1),
        "rank one": u[:, :, None] * u[:, None, :],
        "rank two": w @ w.transpose(0, 2, 1),
        "identity multiples": np.eye(3) * rng.random((20, 1, 1)),
        "diagonal": np.stack([np.diag(d) for d in rng.random((50, 3))]),
        "diagonal ties": np.stack([np.diag(d) for d in [(1, 1, 1), (1, 2, 2), (2, 1, 2), (2, 2, 1), (0, 0, 1)]]),
        "zero": np.zeros((2, 3, 3)),
    }
    for name, covariances in matrices.items():
        ours, theirs = smallest_eigenvectors(covariances), _open3d_smallest(covariances)
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-12, err_msg=name)


def test_empty_cloud() -> None:
    assert pca_normals(np.zeros((0, 3)), 0.1, 30).shape == (0, 3)


def test_geometry_path_does_not_import_open3d(tmp_path: Path) -> None:
    """What the module is for: a scene with a mesh never loads open3d (0.2-0.3 s of a run's start)."""
    code = """
import sys
import numpy as np
from panogs_core.stages.primitives import PrimitivesConfig, build_primitives
from panogs_core.types import Geometry

class Scene:  # the part of a bundle that the geometry path reads
    has_geometry = True

    def read_geometry(self):
        return Geometry(points=np.random.default_rng(0).random((500, 3)).astype(np.float32))

print(len(build_primitives(Scene(), PrimitivesConfig()).normals), "open3d" in sys.modules)
"""
    root = str(Path(__file__).resolve().parents[2])
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=root)
    assert out.stdout.split() == ["500", "False"]
