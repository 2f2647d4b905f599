"""gaussians.ply in the 3DGS layout, read back with a reader written here from the PLY format, not panogs'."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from panogs_core.errors import InputError
from panogs_core.gaussians.config import GaussianScene
from panogs_core.gaussians.ply import read_gaussian_ply, write_gaussian_ply
from panogs_core.io.ply import write_ply

_PLY_TYPES = {"float": "<f4", "double": "<f8", "int": "<i4", "uint": "<u4", "uchar": "u1", "char": "i1"}


def _independent_read(path: Path) -> tuple[list[str], np.ndarray]:
    """A minimal binary-little-endian PLY reader (header lines, then one structured record per vertex)."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    assert lines[0] == "ply"
    assert lines[1] == "format binary_little_endian 1.0"
    count = next(int(line.split()[2]) for line in lines if line.startswith("element vertex"))
    props = [line.split() for line in lines if line.startswith("property")]
    dtype = np.dtype([(name, _PLY_TYPES[kind]) for _, kind, name in props])
    return [p[2] for p in props], np.frombuffer(data, dtype=dtype, count=count, offset=end)


def _scene(n: int = 5, degree: int = 2) -> GaussianScene:
    rng = np.random.default_rng(0)
    quats = rng.normal(size=(n, 4)).astype(np.float32)
    return GaussianScene(
        means=rng.normal(size=(n, 3)).astype(np.float32),
        sh=rng.normal(size=(n, (degree + 1) ** 2, 3)).astype(np.float32),
        opacity_logits=rng.normal(size=n).astype(np.float32),
        log_scales=rng.normal(size=(n, 3)).astype(np.float32),
        quats=quats / np.linalg.norm(quats, axis=1, keepdims=True),
        fitted=True,
    )


def test_layout_and_values_read_back_independently(tmp_path: Path) -> None:
    g = _scene()
    normals = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (5, 1))
    semantic = np.array([0, 1, -1, 2, 2])
    instance = np.array([3, -1, -1, 0, 1])
    write_gaussian_ply(tmp_path / "g.ply", g, normals, semantic, instance)
    names, rec = _independent_read(tmp_path / "g.ply")
    rest = [f"f_rest_{i}" for i in range(24)]  # 8 higher coefficients x 3 channels at degree 2
    assert names == [
        *"xyz",
        "nx", "ny", "nz",
        "f_dc_0", "f_dc_1", "f_dc_2",
        *rest,
        "opacity",
        "scale_0", "scale_1", "scale_2",
        "rot_0", "rot_1", "rot_2", "rot_3",
        "semantic", "instance",
    ]  # fmt: skip
    assert np.array_equal(rec["x"], g.means[:, 0])
    assert np.array_equal(rec["f_dc_1"], g.sh[:, 0, 1])
    assert np.array_equal(rec["f_rest_0"], g.sh[:, 1, 0])  # red's first higher coefficient
    assert np.array_equal(rec["f_rest_7"], g.sh[:, 8, 0])  # red's last
    assert np.array_equal(rec["f_rest_8"], g.sh[:, 1, 1])  # then green's
    assert np.array_equal(rec["f_rest_23"], g.sh[:, 8, 2])
    assert np.array_equal(rec["opacity"], g.opacity_logits)  # logit, as viewers expect
    assert np.array_equal(rec["scale_2"], g.log_scales[:, 2])  # log scale
    assert np.array_equal(rec["rot_0"], g.quats[:, 0])  # w first
    assert rec["semantic"].tolist() == semantic.tolist()
    assert rec["instance"].tolist() == instance.tolist()
    assert rec.dtype["semantic"] == np.dtype("<i4")


def test_panogs_reads_back_what_it_wrote(tmp_path: Path) -> None:
    g = _scene(degree=3)
    write_gaussian_ply(tmp_path / "g.ply", g, np.zeros((5, 3), np.float32), np.arange(5), np.arange(5) - 1)
    back, semantic, instance = read_gaussian_ply(tmp_path / "g.ply")
    assert np.array_equal(back.sh, g.sh)
    assert np.array_equal(back.quats, g.quats)
    assert semantic.tolist() == [0, 1, 2, 3, 4]
    assert instance.tolist() == [-1, 0, 1, 2, 3]


def test_a_plain_point_cloud_is_refused_naming_what_is_missing(tmp_path: Path) -> None:
    write_ply(tmp_path / "p.ply", {k: np.zeros(3, np.float32) for k in "xyz"})
    with pytest.raises(InputError, match=r"missing vertex properties.*f_dc_0"):
        read_gaussian_ply(tmp_path / "p.ply")
