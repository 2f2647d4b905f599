"""Hostile JSON and images at the API: each is a 422 naming the file or field, the
limit and its setting, never a 500, and a refused bundle leaves nothing on disk."""

from __future__ import annotations

import io
import struct
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from svc_helpers import RecordingSender, edit_manifest, make_scene, new_key, pack, upload_bytes, write_tiny_bundle

from service.api_app import create_app
from service.settings import Settings


def _refused(client: TestClient, auth: dict[str, str], data: bytes, settings: Settings) -> dict[str, Any]:
    """Upload ``data``, try to make a scene; assert 422 and that nothing stayed behind."""
    upload = upload_bytes(client, auth, data, filename="bad.zip")
    response = client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=auth)
    assert response.status_code == 422, response.text
    body = dict(response.json())
    assert body["type"] == "invalid_bundle"
    assert "nothing was kept" in body["message"]
    for sub in ("scenes", "uploads"):
        folder = settings.storage / sub
        assert not folder.exists() or not any(folder.iterdir()), f"{sub} not empty"
    for host_path in (str(settings.storage), str(settings.data_dir.resolve()), str(settings.data_dir)):
        assert host_path not in response.text
    return body


def _bundle(tmp_path: Path, mutate: Callable[[Path], object]) -> bytes:
    root = write_tiny_bundle(tmp_path / "bundle")
    mutate(root)
    return pack(root)


def _nested(levels: int) -> Any:
    value: Any = 1
    for _ in range(levels):
        value = {"a": value}
    return value


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _zeros_png(width: int, height: int) -> bytes:
    """A complete, valid 16-bit grey PNG of zeros, compressed row by row (never held whole in memory)."""
    compressor = zlib.compressobj(9)
    row = b"\x00" * (1 + 2 * width)  # filter byte, then the row
    data = b"".join(compressor.compress(row) for _ in range(height)) + compressor.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", data) + _png_chunk(b"IEND", b"")


class TestBundleJson:
    def test_deep_scene_json(
        self, client: TestClient, auth: dict[str, str], settings: Settings, tmp_path: Path
    ) -> None:
        def deep_pose(root: Path) -> None:
            edit_manifest(root, lambda m: m["frames"][0].update(pose=_nested(500)))

        body = _refused(client, auth, _bundle(tmp_path, deep_pose), settings)
        assert any(
            p.startswith("scene.json: nested deeper than the JSON depth limit of 64 levels at frames[0].pose.a.a")
            for p in body["problems"]
        ), body
        assert "the JSON depth limit is set by PANOGS_MAX_JSON_DEPTH" in body["problems"]

    def test_huge_integer_in_scene_json(
        self, client: TestClient, auth: dict[str, str], settings: Settings, tmp_path: Path
    ) -> None:
        def huge_width(root: Path) -> None:
            text = (root / "scene.json").read_text()
            (root / "scene.json").write_text(text.replace('"width": 64', '"width": ' + "7" * 6000, 1))

        body = _refused(client, auth, _bundle(tmp_path, huge_width), settings)
        assert any("scene.json: an integer of 6,000 digits at camera.width" in p for p in body["problems"]), body
        assert "the JSON integer limit is set by PANOGS_MAX_JSON_INT_DIGITS" in body["problems"]

    def test_deep_vocabulary_json(
        self, client: TestClient, auth: dict[str, str], settings: Settings, tmp_path: Path
    ) -> None:
        def deep_vocabulary(root: Path) -> None:
            (root / "vocabulary.json").write_text('{"classes": ' + "[" * 100_000 + "]" * 100_000 + "}")

        body = _refused(client, auth, _bundle(tmp_path, deep_vocabulary), settings)
        assert any(p.startswith("vocabulary.json: nested deeper than the JSON depth limit") for p in body["problems"])

    def test_json_size_is_a_setting(self, make_settings: Callable[..., Settings], tmp_path: Path) -> None:
        settings = make_settings("sqlite", bundle_max_json_bytes=500)
        auth = new_key(settings)
        with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
            body = _refused(client, auth, pack(write_tiny_bundle(tmp_path / "b")), settings)
        assert any("scene.json: " in p and "over the JSON size limit of 500 bytes" in p for p in body["problems"])
        assert "the JSON size limit is set by PANOGS_BUNDLE_MAX_JSON_BYTES" in body["problems"]


class TestImages:
    def test_huge_mask_is_refused_from_its_header(
        self, client: TestClient, auth: dict[str, str], settings: Settings, tmp_path: Path
    ) -> None:
        # 8000 x 8000 x 16 bits = 128 MB of pixels in a PNG of about 130 KB: over the 40 M pixel default.
        mask = _zeros_png(8000, 8000)
        assert len(mask) < 1_000_000
        data = _bundle(tmp_path, lambda root: (root / "masks/000001.png").write_bytes(mask))
        body = _refused(client, auth, data, settings)
        expected = "masks/000001.png: 8000x8000 (64,000,000 pixels), over the pixel limit of 40,000,000"
        assert expected in body["problems"], body
        assert "the pixel limit is set by PANOGS_MAX_IMAGE_PIXELS" in body["problems"]

    def test_pixel_limit_is_a_setting(self, make_settings: Callable[..., Settings], tmp_path: Path) -> None:
        settings = make_settings("sqlite", max_image_pixels=3_000)  # the tiny bundle's images are 64 x 48 = 3,072
        auth = new_key(settings)
        with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
            body = _refused(client, auth, pack(write_tiny_bundle(tmp_path / "b")), settings)
        assert "depth/000000.png: 64x48 (3,072 pixels), over the pixel limit of 3,000" in body["problems"]


def _raw_npy(shape: str, descr: str = "<f4") -> bytes:
    """A .npy holding only a header that says ``shape`` (np.save cannot write a false shape)."""
    text = "{'descr': '%s', 'fortran_order': False, 'shape': %s, }" % (descr, shape)  # noqa: UP031
    header = text.encode("latin1") + b" " * ((64 - (10 + len(text) + 1) % 64) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header


_WRAPPING_DIM = 2**62  # a float-exact features.dim: 4 cells x 2**62 is 2**64, 0 as np.prod(..., int64) computed it


def _wrapping_feature_dim(root: Path) -> None:
    """Empty feature maps whose int64 element count wrapped to 0: main passed them as complete, then a 500."""
    edit_manifest(root, lambda m: m["features"].update(dim=_WRAPPING_DIM))
    for i in range(2):
        (root / f"features/{i:06d}.npy").write_bytes(_raw_npy(f"(4, 1, {_WRAPPING_DIM})"))
    (root / "vocabulary.json").write_text(
        '{"classes": [{"name": "wall", "kind": "stuff"}, {"name": "chair", "kind": "thing"}]}'
    )
    (root / "vocabulary.npy").unlink()


def _gt_with_huge_member(root: Path) -> None:
    (root / "gt").mkdir()
    with zipfile.ZipFile(root / "gt" / "labels.npz", "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("semantic.npy", _raw_npy(f"({10**30},)", "<i8"))
        zf.writestr("instance.npy", _raw_npy(f"({10**17},)", "<i8"))


class TestBinaryHeaders:
    """Numbers in .npy, .npz and PLY headers: each was a 500, or an accepted scene, before."""

    @pytest.mark.parametrize(
        ("mutate", "expected"),
        [
            (
                _wrapping_feature_dim,
                f"features/000000.npy: shape (4, 1, {_WRAPPING_DIM}) of float32 declares {_WRAPPING_DIM * 16:,} data "
                "bytes, the file holds 0 after its header (truncated, or a false shape)",
            ),
            (
                lambda root: (root / "features/000000.npy").write_bytes(_raw_npy(f"({10**19}, 6, 8)")),
                "features/000000.npy: shape (10000000000000000000, 6, 8), expected at most 32 integer sizes in "
                "[0, 2**63)",
            ),
            (
                lambda root: (root / "features/000001.npy").write_bytes(_raw_npy(f"({10**18}, 6, 8)")),
                "features/000001.npy: shape (1000000000000000000, 6, 8) of float32 declares "
                "192,000,000,000,000,000,000 data bytes, the file holds 0 after its header (truncated, or a false "
                "shape)",
            ),
            (  # np.prod raised OverflowError
                _gt_with_huge_member,
                f"gt/labels.npz: semantic.npy: shape ({10**30},), expected at most 32 integer sizes in [0, 2**63)",
            ),
            (  # int() refused the 5,000 digits with a ValueError
                lambda root: (root / "geometry.ply").write_bytes(
                    b"ply\nformat binary_little_endian 1.0\nelement vertex " + b"5" * 5000 + b"\nproperty float x\n"
                ),
                "geometry.ply: line 3: PLY element 'vertex' count of 5,000 digits, expected at most 19 (and no more "
                "rows than the file holds)",
            ),
        ],
        ids=[
            "feature dim wraps",
            "feature size past int64",
            "feature bytes past int64",
            "gt member past any int",
            "ply count digits",
        ],
    )
    def test_refused_naming_the_file(
        self,
        client: TestClient,
        auth: dict[str, str],
        settings: Settings,
        tmp_path: Path,
        mutate: Callable[[Path], object],
        expected: str,
    ) -> None:
        body = _refused(client, auth, _bundle(tmp_path, mutate), settings)
        assert expected in body["problems"], body
        assert client.get("/v1/scenes", headers=auth).json()["count"] == 0


class TestArchiveNames:
    def test_long_member_name_names_no_host_path(
        self, client: TestClient, auth: dict[str, str], settings: Settings, tmp_path: Path
    ) -> None:
        buffer = io.BytesIO(pack(write_tiny_bundle(tmp_path / "b")))
        with zipfile.ZipFile(buffer, "a") as zf:
            zf.writestr("color/" + "c" * 400 + ".png", b"x")
        body = _refused(client, auth, buffer.getvalue(), settings)
        assert any(p.startswith("color/ccc") and "over the limit of 255" in p for p in body["problems"]), body


class TestRequestBodies:
    def test_deep_job_config_is_422_naming_the_limit(
        self, client: TestClient, auth: dict[str, str], tiny_zip: bytes
    ) -> None:
        scene = make_scene(client, auth, tiny_zip)
        for levels in (300, 100_000):  # a few KB (it broke pydantic's serializer), and past the parser's recursion
            response = client.post("/v1/jobs", json={"scene_id": scene["id"], "config": _nested(1)}, headers=auth)
            assert response.status_code == 422  # 'a' is no config key: the ordinary refusal
            deep = '{"a": ' * levels + "1" + "}" * levels
            body = f'{{"scene_id": "{scene["id"]}", "config": {deep}}}'
            response = client.post("/v1/jobs", content=body, headers={**auth, "Content-Type": "application/json"})
            assert response.status_code == 422, response.text
            answer = response.json()
            assert answer["type"] == "invalid_input"
            assert "PANOGS_MAX_JSON_DEPTH" in answer["message"]
            assert answer["problems"][0].startswith(
                "request body: nested deeper than the JSON depth limit of 64 levels at config.a.a.a.a.a..."
            )
        assert client.get("/v1/jobs", headers=auth).json()["count"] == 0

    def test_huge_integer_in_a_body(self, client: TestClient, auth: dict[str, str], tiny_zip: bytes) -> None:
        scene = make_scene(client, auth, tiny_zip)
        stride = "9" * 10_000
        body = f'{{"scene_id": "{scene["id"]}", "config": {{"primitives": {{"frame_stride": {stride}}}}}}}'
        response = client.post("/v1/jobs", content=body, headers={**auth, "Content-Type": "application/json"})
        assert response.status_code == 422, response.text
        assert "PANOGS_MAX_JSON_INT_DIGITS" in response.json()["message"]
        assert "at config.primitives.frame_stride" in response.json()["problems"][0]

    @pytest.mark.parametrize("content_type", [None, "application/json; charset=utf-8", "application/merge-patch+json"])
    def test_every_body_fastapi_reads_as_json_is_checked(
        self, client: TestClient, auth: dict[str, str], content_type: str | None
    ) -> None:
        headers = dict(auth) if content_type is None else {**auth, "Content-Type": content_type}
        response = client.post("/v1/scenes", content=b"[" * 50_000, headers=headers)
        assert response.status_code == 422
        assert "JSON depth limit" in response.json()["problems"][0]

    @pytest.mark.parametrize(
        "headers",
        [
            [("content-type", "application/json"), ("content-type", "text/plain")],  # FastAPI reads the first
            [("content-type", "text/plain"), ("content-type", "application/json")],  # a reader of the last
            [("content-type", "application/json\x1f")],  # str.strip() removes it, bytes.strip() keeps it
            [("content-type", b"application/json\x85")],  # latin-1 NEL, a str space
            [("content-type", " APPLICATION/JSON ;charset=utf-8")],
            [("content-type", "text/plain")],
            [("content-type", "")],
        ],
        ids=["json-then-text", "text-then-json", "x1f", "x85", "upper-spaced", "text", "empty"],
    )
    def test_the_bound_holds_whatever_the_content_type_headers_say(
        self, client: TestClient, auth: dict[str, str], tiny_zip: bytes, headers: list[tuple[str, str | bytes]]
    ) -> None:
        scene = make_scene(client, auth, tiny_zip)
        deep = '{"a": ' * 300 + "1" + "}" * 300
        body = f'{{"scene_id": "{scene["id"]}", "config": {deep}}}'.encode()
        response = client.post(
            "/v1/jobs",
            content=body,
            headers=[(k.encode(), v.encode()) for k, v in auth.items()]
            + [(k.encode(), v if isinstance(v, bytes) else v.encode()) for k, v in headers],
        )
        assert response.status_code == 422, response.text
        assert "PANOGS_MAX_JSON_DEPTH" in response.json()["message"]
        assert client.get("/v1/jobs", headers=auth).json()["count"] == 0

    def test_bodies_within_the_limits_are_unchanged(
        self, make_settings: Callable[..., Settings], tiny_zip: bytes
    ) -> None:
        settings = make_settings("sqlite", max_json_depth=5)  # scene.json needs 5 (frames[i].pose rows)
        auth = new_key(settings)
        with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
            scene = make_scene(client, auth, tiny_zip)
            ok = {"scene_id": scene["id"], "config": {"language_field": {"device": "cpu"}}}  # 3 levels
            assert client.post("/v1/jobs", json=ok, headers=auth).status_code == 202
            five = {"scene_id": scene["id"], "config": {"language_field": {"device": [["cpu"]]}}}
            assert "JSON depth limit" not in client.post("/v1/jobs", json=five, headers=auth).text
            six = {"scene_id": scene["id"], "config": {"language_field": {"device": [[["cpu"]]]}}}
            response = client.post("/v1/jobs", json=six, headers=auth)
            assert response.status_code == 422
            assert "depth limit of 5 levels at config.language_field.device[0][0]" in response.json()["problems"][0]
            bad = client.post(
                "/v1/jobs", content=b'{"scene_id": ', headers={**auth, "Content-Type": "application/json"}
            )
            assert bad.status_code == 422  # not JSON: FastAPI's own answer, which names the position
            assert bad.json()["type"] == "invalid_input"
