"""PLY writer and vertex reader: round trips, the three encodings, skipped elements, malformed files."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from panogs_core.errors import InputError
from panogs_core.io.ply import PlyBudget, read_ply_vertices, scan_ply_positions, vertex_count, write_ply


def _fields(n: int = 5) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {
        "x": rng.normal(size=n).astype(np.float32),
        "y": rng.normal(size=n).astype(np.float32),
        "z": rng.normal(size=n).astype(np.float64),
        "red": rng.integers(0, 256, n).astype(np.uint8),
        "label": rng.integers(-5, 5, n).astype(np.int32),
        "code": rng.integers(0, 60000, n).astype(np.uint16),
        "small": rng.integers(-300, 300, n).astype(np.int16),
    }


class TestWritePly:
    def test_round_trip_keeps_dtypes_and_values(self, tmp_path: Path) -> None:
        fields = _fields()
        write_ply(tmp_path / "a.ply", fields)
        out = read_ply_vertices(tmp_path / "a.ply")
        assert list(out) == list(fields)
        for name, arr in fields.items():
            assert out[name].dtype == arr.dtype, name
            np.testing.assert_array_equal(out[name], arr)

    def test_int64_written_as_int(self, tmp_path: Path) -> None:
        write_ply(tmp_path / "a.ply", {"x": np.array([1, -2, 3], dtype=np.int64)})
        out = read_ply_vertices(tmp_path / "a.ply")
        assert out["x"].dtype == np.int32
        np.testing.assert_array_equal(out["x"], [1, -2, 3])
        assert b"property int x" in (tmp_path / "a.ply").read_bytes()

    def test_faces_are_skipped_and_counted(self, tmp_path: Path) -> None:
        faces = np.array([[0, 1, 2], [2, 3, 4]])
        write_ply(tmp_path / "m.ply", _fields(), faces=faces)
        data = (tmp_path / "m.ply").read_bytes()
        assert b"element face 2\nproperty list uchar int vertex_indices" in data
        assert vertex_count(tmp_path / "m.ply") == 5
        np.testing.assert_array_equal(read_ply_vertices(tmp_path / "m.ply")["red"], _fields()["red"])

    @pytest.mark.parametrize(
        ("fields", "faces", "match"),
        [
            ({"x": np.zeros((2, 2), np.float32)}, None, "1-D"),
            ({"x": np.zeros(2, np.float32), "y": np.zeros(3, np.float32)}, None, "3 values"),
            ({"x": np.array([2**40], np.int64)}, None, "int32 range"),
            ({"x": np.zeros(2, np.complex64)}, None, "unsupported dtype"),
            ({"x": np.zeros(3, np.float32)}, np.array([[0, 1, 3]]), r"\[0, 3\)"),
        ],
    )
    def test_exception(
        self, tmp_path: Path, fields: dict[str, np.ndarray], faces: np.ndarray | None, match: str
    ) -> None:
        with pytest.raises(InputError, match=match):
            write_ply(tmp_path / "bad.ply", fields, faces=faces)


def _header(fmt: str, n: int, extra_before: str = "", extra_after: str = "") -> bytes:
    return (
        f"ply\nformat {fmt} 1.0\ncomment made by a test\n{extra_before}element vertex {n}\n"
        "property float x\nproperty float y\nproperty float z\nproperty uchar red\n"
        f"{extra_after}end_header\n"
    ).encode()


class TestReadPly:
    def test_ascii_with_faces_after_vertices(self, tmp_path: Path) -> None:
        body = "0 0 0 255\n1.5 2 -3 7\n0 1 0 0\n3 0 1 2\n"
        path = tmp_path / "a.ply"
        path.write_bytes(
            _header("ascii", 3, extra_after="element face 1\nproperty list uchar int vertex_indices\n") + body.encode()
        )
        out = read_ply_vertices(path)
        np.testing.assert_allclose(out["y"], [0, 2, 1])
        assert out["red"].dtype == np.uint8
        np.testing.assert_array_equal(out["red"], [255, 7, 0])

    def test_big_endian(self, tmp_path: Path) -> None:
        rec = np.zeros(2, dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("red", "u1")])
        rec["x"], rec["y"], rec["z"], rec["red"] = [1.0, -2.5], [3.0, 4.0], [5.0, 6.0], [9, 200]
        path = tmp_path / "be.ply"
        path.write_bytes(_header("binary_big_endian", 2) + rec.tobytes())
        out = read_ply_vertices(path)
        np.testing.assert_array_equal(out["x"], [1.0, -2.5])
        assert out["x"].dtype == np.float32
        assert out["x"].dtype.byteorder in ("=", "<", "|")  # native order, usable without surprises
        np.testing.assert_array_equal(out["red"], [9, 200])

    def test_element_with_lists_before_vertices_is_skipped(self, tmp_path: Path) -> None:
        # A leading element with variable-length lists forces the reader to walk it row by row.
        pre = "element meta 2\nproperty list uchar short vals\nproperty uchar flag\n"
        meta = np.array([2], "u1").tobytes() + np.array([1, 2], "<i2").tobytes() + b"\x01"
        meta += np.array([0], "u1").tobytes() + b"\x00"
        rec = np.zeros(1, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1")])
        rec["x"], rec["red"] = 7.0, 3
        path = tmp_path / "pre.ply"
        path.write_bytes(_header("binary_little_endian", 1, extra_before=pre) + meta + rec.tobytes())
        out = read_ply_vertices(path)
        assert out["x"].tolist() == [7.0]
        assert out["red"].tolist() == [3]

    def test_ascii_element_before_vertices_is_skipped(self, tmp_path: Path) -> None:
        pre = "element face 1\nproperty list uchar int vertex_indices\n"
        path = tmp_path / "pre.ply"
        path.write_bytes(_header("ascii", 1, extra_before=pre) + b"4 0 1 2 3\n9 8 7 6\n")
        assert read_ply_vertices(path)["z"].tolist() == [7.0]

    @pytest.mark.parametrize(
        ("content", "match"),
        [
            (b"not a ply\n", "not a PLY"),
            (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", "no end_header"),
            (b"ply\nformat weird 1.0\nend_header\n", "unsupported PLY format"),
            (b"ply\nformat ascii 1.0\nproperty float x\nend_header\n", "before any element"),
            (
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n",
                "malformed PLY property",
            ),
            (b"ply\nformat ascii 1.0\nelement face 0\nend_header\n", "no vertex element"),
            (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1\n", "truncated"),
            (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\nabc\n", "not numeric"),
            (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty uchar x\nend_header\n1.5\n", "integers"),
            (
                b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nend_header\n\0\0",
                "truncated",
            ),
            (
                b"ply\nformat binary_big_endian 1.0\nelement vertex 999999999999\nproperty double x\nend_header\n",
                "truncated",
            ),
            (
                b"ply\nformat binary_little_endian 1.0\nelement face 99999999999\nproperty uchar f\n"
                b"element vertex 1\nproperty float x\nend_header\n",
                "'face' truncated",
            ),
        ],
    )
    def test_malformed_names_the_file(self, tmp_path: Path, content: bytes, match: str) -> None:
        path = tmp_path / "broken.ply"
        path.write_bytes(content)
        with pytest.raises(InputError, match=match) as info:
            read_ply_vertices(path)
        assert "broken.ply" in str(info.value)

    @pytest.mark.parametrize(
        ("content", "match"),
        [
            (  # int() refused it with a ValueError (Python's 4,300-digit limit), which became a 500
                b"ply\nformat ascii 1.0\nelement vertex " + b"7" * 5000 + b"\nproperty float x\nend_header\n",
                "broken.ply: line 3: PLY element 'vertex' count of 5,000 digits, expected at most 19",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 0" + b"0" * 30 + b"1\nproperty float x\nend_header\n1\n",
                "broken.ply: line 3: PLY element 'vertex' count of 32 digits",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nend_header\n1 2 3\n",
                "broken.ply: PLY element 'vertex' truncated or its count false: 3 rows need at least 12 bytes of data, "
                "the file holds 6 after its header",
            ),
            (  # an element of rows without properties takes no bytes: any count would fit the file
                b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n"
                b"element junk 9223372036854775807\nend_header\n\0\0\0\0",
                "broken.ply: PLY element 'junk' has 9,223,372,036,854,775,807 rows but no properties",
            ),
            (  # rows with lists take at least their length prefix each: a count is bounded by the file too
                b"ply\nformat binary_little_endian 1.0\nelement face 1000\nproperty list uchar int v\n"
                b"element vertex 1\nproperty float x\nend_header\n" + bytes(500),
                "broken.ply: PLY element 'face' truncated or its count false: 1,000 rows need at least 1,000 bytes",
            ),
            (  # a list length of 4 billion: refused before a 16 GB read is attempted
                b"ply\nformat binary_little_endian 1.0\nelement face 1\nproperty list uint int v\n"
                b"element vertex 1\nproperty float x\nend_header\n\xff\xff\xff\xff" + bytes(4),
                "broken.ply: PLY element 'face' truncated",
            ),
            (b"ply\ncomment " + b"c" * (1024**2 + 10) + b"\n", "broken.ply: line 2: PLY header longer than 1,048,576"),
            (b"ply\n" + b"comment\n" * 10_000, "broken.ply: PLY header has no end_header within 10,000 lines"),
            (b"ply\nformat ascii 2.0\nend_header\n", "broken.ply: line 2: unsupported PLY format line 'format ascii 2"),
            (
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty list float int v\nend_header\n",
                "broken.ply: line 4: PLY list length type 'float', expected an integer type",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty uchar x\nend_header\n1 1\n",
                "broken.ply: line 5: PLY property 'x' repeated in element 'vertex'",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nelement vertex 1\nend_header\n",
                "broken.ply: line 5: PLY element 'vertex' repeated",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nbogus" + b"b" * 500 + b"\n",
                "broken.ply: line 5: unknown PLY header keyword 'bogusbbb",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 2\nproperty uchar red\nend_header\n300 1\n",
                r"broken.ply: PLY property 'red' has values in \[1, 300\], outside its type's range \[0, 255\]",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 2\nproperty uchar red\nend_header\n" + b"9" * 5000 + b" 1\n",
                "broken.ply: PLY property 'red' must hold integers",  # the value parses as inf
            ),
        ],
        ids=[
            "count of 5000 digits", "count of leading zeros", "ascii count", "no properties", "list rows",
            "list length", "long line", "many lines", "format version", "list length type", "property twice",
            "element twice", "long keyword", "uchar range", "huge ascii value",
        ],
    )  # fmt: skip
    def test_header_numbers_are_bounded(self, tmp_path: Path, content: bytes, match: str) -> None:
        path = tmp_path / "broken.ply"
        path.write_bytes(content)
        with pytest.raises(InputError, match=match) as info:
            read_ply_vertices(path)
        assert len(str(info.value)) < 400  # a value is quoted, never a whole line of the file

    def test_largest_count_that_fits_is_read(self, tmp_path: Path) -> None:
        path = tmp_path / "big.ply"
        write_ply(path, {"x": np.arange(1000, dtype=np.float32)})
        assert vertex_count(path) == 1000
        assert len(read_ply_vertices(path)["x"]) == 1000

    def test_missing_file(self, tmp_path: Path) -> None:
        with pytest.raises(InputError, match=r"nope\.ply"):
            read_ply_vertices(tmp_path / "nope.ply")

    def test_open3d_reads_what_we_write(self, tmp_path: Path) -> None:
        o3d = pytest.importorskip("open3d")
        pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
        write_ply(
            tmp_path / "t.ply",
            {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]},
            faces=np.array([[0, 1, 2]]),
        )
        mesh = o3d.io.read_triangle_mesh(str(tmp_path / "t.ply"))
        np.testing.assert_allclose(np.asarray(mesh.vertices), pts)
        np.testing.assert_array_equal(np.asarray(mesh.triangles), [[0, 1, 2]])


class TestBudget:
    """What a file may cost is refused by name before the work; data is read in chunks, never whole."""

    def test_vertices_over_the_budget(self, tmp_path: Path) -> None:
        path = write_ply(tmp_path / "v.ply", _fields(5))
        with pytest.raises(InputError, match=r"v\.ply: 5 vertices, over the limit of 4 \(subsample the mesh\)"):
            read_ply_vertices(path, PlyBudget(max_vertices=4))
        assert scan_ply_positions(path, PlyBudget(max_vertices=5))[0] == 5

    @staticmethod
    def _faces_first(path: Path, faces: int) -> Path:
        pre = f"element face {faces}\nproperty list uchar int vertex_indices\n"
        face = np.array([3], "u1").tobytes() + np.array([0, 0, 0], "<i4").tobytes()
        rec = np.zeros(1, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1")])
        path.write_bytes(_header("binary_little_endian", 1, extra_before=pre) + face * faces + rec.tobytes())
        return path

    def test_list_rows_before_the_vertices(self, tmp_path: Path) -> None:
        path = self._faces_first(tmp_path / "faces-first.ply", 300_000)
        with pytest.raises(InputError, match=r"element 'face' has list properties and 300,000 rows before"):
            scan_ply_positions(path)  # the default budget, 200,000 such rows, is checked from the header
        small = self._faces_first(tmp_path / "small.ply", 1_000)
        assert read_ply_vertices(small, PlyBudget(max_list_rows=1_000))["x"].tolist() == [0.0]
        with pytest.raises(InputError, match="at most 999 such rows"):
            read_ply_vertices(small, PlyBudget(max_list_rows=999))

    def test_ascii_values_over_the_budget(self, tmp_path: Path) -> None:
        path = tmp_path / "zeros.ply"
        path.write_bytes(_header("ascii", 1000) + b"0 " * 4000)
        with pytest.raises(InputError, match=r"ASCII body of 4,000 values up to the vertices, over the limit of 3,999"):
            scan_ply_positions(path, PlyBudget(max_ascii_values=3999))

    def test_ascii_reads_only_what_the_header_declares(self, tmp_path: Path) -> None:
        path = tmp_path / "trailing.ply"
        path.write_bytes(_header("ascii", 1) + b"1 2 3 4\n" + b"0 " * 3_000_000)
        assert scan_ply_positions(path) == (1, True)

    @pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian"])
    def test_chunks_join_to_the_whole(self, tmp_path: Path, encoding: str) -> None:
        n = 65_537 if encoding == "ascii" else 262_145  # one row past a chunk
        rng = np.random.default_rng(0)
        xyz = rng.integers(-1000, 1000, (n, 3)).astype(np.float32) / 8  # exact in ASCII
        red = rng.integers(0, 256, n).astype(np.uint8)
        path = tmp_path / f"{encoding}.ply"
        if encoding == "ascii":
            rows = "\n".join(f"{a} {b} {c} {r}" for (a, b, c), r in zip(xyz.tolist(), red.tolist(), strict=True))
            path.write_bytes(_header("ascii", n) + rows.encode() + b"\n")
        else:
            write_ply(path, {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "red": red})
        out = read_ply_vertices(path)
        np.testing.assert_array_equal(np.stack([out["x"], out["y"], out["z"]], axis=1), xyz)
        np.testing.assert_array_equal(out["red"], red)
        assert scan_ply_positions(path) == (n, True)

    def test_scan_finds_a_non_finite_position_in_a_later_chunk(self, tmp_path: Path) -> None:
        xyz = np.zeros((300_000, 3), np.float32)
        xyz[-1, 1] = np.inf
        path = write_ply(tmp_path / "inf.ply", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]})
        assert scan_ply_positions(path) == (300_000, False)

    def test_scan_holds_one_chunk_of_an_ascii_mesh(self, tmp_path: Path) -> None:
        n = 1_000_000  # 8 MB of "0 0 0 0\n": read whole, its tokens alone took over 300 MB
        path = tmp_path / "big.ply"
        path.write_bytes(_header("ascii", n) + b"0 0 0 0\n" * n)
        tracemalloc.start()
        try:
            assert scan_ply_positions(path) == (n, True)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 64 * 1024**2, f"peak {peak / 1024**2:.0f} MiB"
