"""``gaussians.ply``: the Gaussian scene in the layout the common 3D Gaussian splatting viewers read.

One binary little-endian vertex element with float properties, in this order (the 3DGS training code's
``save_ply``; docs/gaussians.md): ``x y z``, ``nx ny nz``, ``f_dc_0..2`` (SH DC per RGB channel), ``f_rest_*``
(the higher bands, channel-major: all of red's coefficients, then green's, then blue's), ``opacity`` (logit),
``scale_0..2`` (log), ``rot_0..3`` (quaternion w, x, y, z), then panogs' ``semantic`` and ``instance`` (int,
-1 void) that viewers ignore.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from panogs_core.errors import InputError, ShapeError
from panogs_core.gaussians.config import GaussianScene
from panogs_core.io.ply import read_ply_vertices, write_ply


def write_gaussian_ply(
    path: str | Path,
    gaussians: GaussianScene,
    normals: np.ndarray,  # (N, 3)
    semantic: np.ndarray,  # (N,) int
    instance: np.ndarray,  # (N,) int
) -> Path:
    """Write the scene and its labels (module docstring).

    Raises:
        ShapeError: if normals or labels do not have one row per Gaussian.
    """
    n = gaussians.means.shape[0]
    for name, arr, shape in (("normals", normals, (n, 3)), ("semantic", semantic, (n,)), ("instance", instance, (n,))):
        if arr.shape != shape:
            raise ShapeError(f"write_gaussian_ply: {name} expected shape {shape}, got {arr.shape}")
    fields: dict[str, np.ndarray] = {}
    for i, axis in enumerate("xyz"):
        fields[axis] = gaussians.means[:, i]
    for i, axis in enumerate(("nx", "ny", "nz")):
        fields[axis] = normals[:, i]
    for c in range(3):
        fields[f"f_dc_{c}"] = gaussians.sh[:, 0, c]
    rest = gaussians.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, -1)  # (N, 3 * (K - 1)), channel-major
    for j in range(rest.shape[1]):
        fields[f"f_rest_{j}"] = rest[:, j]
    fields["opacity"] = gaussians.opacity_logits
    for i in range(3):
        fields[f"scale_{i}"] = gaussians.log_scales[:, i]
    for i in range(4):
        fields[f"rot_{i}"] = gaussians.quats[:, i]
    out = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in fields.items()}
    out["semantic"] = np.asarray(semantic, dtype=np.int32)
    out["instance"] = np.asarray(instance, dtype=np.int32)
    return write_ply(path, out)


def read_gaussian_ply(path: str | Path) -> tuple[GaussianScene, np.ndarray, np.ndarray]:
    """(scene, semantic, instance) of a ``gaussians.ply`` (the layout above; labels -1 when absent).

    Raises:
        InputError: naming the file and the missing property, when the file lacks the layout.
    """
    v = read_ply_vertices(path)
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    required += [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    missing = [k for k in required if k not in v]
    if missing:
        raise InputError(f"{path}: not a Gaussian-splatting PLY, missing vertex properties {missing}")
    n = v["x"].shape[0]
    rest_names = sorted((k for k in v if k.startswith("f_rest_")), key=lambda k: int(k.rsplit("_", 1)[1]))
    if len(rest_names) % 3:
        raise InputError(f"{path}: {len(rest_names)} f_rest_* properties, expected a multiple of 3")
    k_rest = len(rest_names) // 3
    sh = np.zeros((n, 1 + k_rest, 3), np.float32)
    sh[:, 0] = np.stack([v[f"f_dc_{c}"] for c in range(3)], axis=1)
    if k_rest:
        rest = np.stack([v[name] for name in rest_names], axis=1).reshape(n, 3, k_rest)
        sh[:, 1:] = rest.transpose(0, 2, 1)
    scene = GaussianScene(
        means=np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32),
        sh=sh,
        opacity_logits=v["opacity"].astype(np.float32),
        log_scales=np.stack([v[f"scale_{i}"] for i in range(3)], axis=1).astype(np.float32),
        quats=np.stack([v[f"rot_{i}"] for i in range(4)], axis=1).astype(np.float32),
        fitted=True,
    )
    void = np.full(n, -1, np.int64)
    semantic = v["semantic"].astype(np.int64) if "semantic" in v else void
    instance = v["instance"].astype(np.int64) if "instance" in v else void.copy()
    return scene, semantic, instance
