"""Image headers read without decoding agree with what OpenCV decodes, and a bad header is an InputError."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from panogs_core.errors import InputError
from panogs_core.io.image_header import PNG_SIGNATURE, read_image_header


@pytest.mark.parametrize(
    ("suffix", "image"),
    [
        (".png", np.zeros((7, 9), np.uint8)),
        (".png", np.zeros((7, 9), np.uint16)),
        (".png", np.zeros((7, 9, 3), np.uint8)),
        (".png", np.zeros((7, 9, 4), np.uint8)),
        (".jpg", np.zeros((7, 9, 3), np.uint8)),
        (".jpg", np.zeros((7, 9), np.uint8)),
    ],
)
def test_header_agrees_with_the_decoder(tmp_path: Path, suffix: str, image: np.ndarray) -> None:
    path = tmp_path / f"img{suffix}"
    assert cv2.imwrite(str(path), image)
    header = read_image_header(path)
    decoded = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert decoded is not None
    assert (header.height, header.width) == decoded.shape[:2]
    assert header.channels == (1 if decoded.ndim == 2 else decoded.shape[2])
    assert header.bit_depth == decoded.dtype.itemsize * 8
    assert header.format == ("JPEG" if suffix == ".jpg" else "PNG")


def test_jpeg_segments_before_the_frame_header_are_skipped(tmp_path: Path) -> None:
    ok, data = cv2.imencode(".jpg", np.zeros((5, 11, 3), np.uint8))
    assert ok
    raw = data.tobytes()
    exif = b"Exif\x00\x00" + b"\xff\xd9" * 100  # an APP1 whose data holds end-of-image markers
    app1 = b"\xff\xe1" + struct.pack(">H", len(exif) + 2) + exif
    path = tmp_path / "a.jpg"
    path.write_bytes(raw[:2] + app1 + raw[2:])
    header = read_image_header(path)
    assert (header.width, header.height, header.channels) == (11, 5, 3)


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def test_a_huge_declared_png_is_read_from_its_first_bytes(tmp_path: Path) -> None:
    ihdr = struct.pack(">IIBBBBB", 20_000, 20_000, 16, 0, 0, 0, 0)
    path = tmp_path / "mask.png"
    path.write_bytes(PNG_SIGNATURE + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IEND", b""))
    header = read_image_header(path, name="masks/000000.png")
    assert (header.width, header.height, header.bit_depth, header.channels) == (20_000, 20_000, 16, 1)
    assert header.pixels == 400_000_000


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        (b"hello", "not a PNG or JPEG"),
        (PNG_SIGNATURE + b"\x00\x00", "without a valid IHDR"),
        (PNG_SIGNATURE + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", 0, 5, 8, 0, 0, 0, 0)), "declares 0x5"),
        (PNG_SIGNATURE + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", 5, 5, 8, 9, 0, 0, 0)), "colour type 9"),
        (b"\xff\xd8\xff\xe0\x00\x10JFIF", "without a frame header"),
        (b"\xff\xd8\xff\xda\x00\x08", "without a frame header"),
    ],
)
def test_bad_headers(tmp_path: Path, data: bytes, expected: str) -> None:
    path = tmp_path / "x.png"
    path.write_bytes(data)
    with pytest.raises(InputError, match=expected) as info:
        read_image_header(path, name="depth/x.png")
    assert str(info.value).startswith("depth/x.png: ")
