"""What an image declares about itself (format, width, height, channels, bit depth), read from its header alone.

A decoder allocates what the header declares: a 3 MB PNG declaring 20000 x 20000 16-bit pixels took the API from
188 to 1,686 MB. So the bundle validator reads the header first, compares it with the camera and the pixel limit,
and decodes only an image that passes. Only the two formats a bundle holds are read: PNG (the ``IHDR`` chunk,
which the format requires first) and JPEG (the first start-of-frame segment, found by skipping the segments
before it by their lengths, without reading their data).

``channels`` and ``bit_depth`` are what OpenCV's ``IMREAD_UNCHANGED`` yields for the common cases: a palette PNG
decodes to 8-bit RGB, a grey PNG of 1, 2 or 4 bits to 8 bits.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Literal

from panogs_core.errors import InputError

__all__ = ["ImageHeader", "read_image_header"]

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}  # IHDR colour type -> channels (palette: decoded to RGB)
# Start-of-frame markers: C0-CF except DHT (C4), JPG (C8) and DAC (CC), which share the range.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_JPEG_NO_LENGTH = frozenset({0x01, *range(0xD0, 0xD9)})  # TEM, RSTn, SOI: markers without a length field
_MAX_JPEG_SEGMENTS = 10_000  # a header of more segments than this is not a photo; stop walking


@dataclass(frozen=True)
class ImageHeader:
    """What an image's header declares."""

    format: Literal["PNG", "JPEG"]
    width: int
    height: int
    channels: int
    bit_depth: int  # bits per sample after decoding (8 or 16 for the images a bundle holds)

    @property
    def pixels(self) -> int:
        """width x height."""
        return self.width * self.height

    def describe(self) -> str:
        """E.g. ``16-bit 1 channel(s)``, in the words the validator uses for a decoded image."""
        return f"{self.bit_depth}-bit {self.channels} channel(s)"


def read_image_header(path: str | Path, *, name: str | None = None) -> ImageHeader:
    """The header of a PNG or JPEG file; reads a few bytes per header segment, never the pixel data.

    Args:
        path: The image file.
        name: What messages call the file (default: its name); inside a bundle, its bundle-relative path.

    Raises:
        InputError: not a PNG or JPEG, or a header that is truncated or malformed.
    """
    path = Path(path)
    name = name or path.name
    try:
        with path.open("rb") as fh:
            start = fh.read(8)
            if start == PNG_SIGNATURE:
                return _png_header(fh, name)
            if start[:2] == b"\xff\xd8":
                fh.seek(2)
                return _jpeg_header(fh, name)
    except OSError as exc:
        raise InputError(f"{name}: cannot be read ({exc.strerror or type(exc).__name__})") from exc
    raise InputError(f"{name}: does not decode as an image (not a PNG or JPEG by its first bytes)")


def _png_header(fh: BinaryIO, name: str) -> ImageHeader:
    chunk = fh.read(8 + 13)  # length and type, then the 13 bytes of IHDR
    if len(chunk) < 21 or chunk[4:8] != b"IHDR" or int.from_bytes(chunk[:4], "big") != 13:
        raise InputError(f"{name}: PNG without a valid IHDR header (truncated or corrupt)")
    width, height = int.from_bytes(chunk[8:12], "big"), int.from_bytes(chunk[12:16], "big")
    bit_depth, colour_type = chunk[16], chunk[17]
    if width == 0 or height == 0 or colour_type not in _PNG_CHANNELS or bit_depth not in (1, 2, 4, 8, 16):
        raise InputError(
            f"{name}: PNG header declares {width}x{height}, colour type {colour_type}, bit depth {bit_depth} (corrupt)"
        )
    decoded_depth = 16 if bit_depth == 16 else 8
    return ImageHeader("PNG", width, height, _PNG_CHANNELS[colour_type], decoded_depth)


def _jpeg_header(fh: BinaryIO, name: str) -> ImageHeader:
    for _ in range(_MAX_JPEG_SEGMENTS):
        prefix = fh.read(1)
        if prefix != b"\xff":
            break
        marker = fh.read(1)
        while marker == b"\xff":  # fill bytes before a marker
            marker = fh.read(1)
        if not marker:
            break
        code = marker[0]
        if code in _JPEG_NO_LENGTH:
            continue
        if code == 0xDA:  # start of scan before any frame header
            break
        size = fh.read(2)
        if len(size) < 2 or int.from_bytes(size, "big") < 2:
            break
        length = int.from_bytes(size, "big") - 2
        if code in _JPEG_SOF:
            frame = fh.read(6)
            if len(frame) < 6:
                break
            precision = frame[0]
            height, width = int.from_bytes(frame[1:3], "big"), int.from_bytes(frame[3:5], "big")
            if height == 0 or width == 0:
                raise InputError(f"{name}: JPEG frame header declares {width}x{height} (corrupt or unsupported)")
            return ImageHeader("JPEG", width, height, frame[5], precision)
        fh.seek(length, 1)
    raise InputError(f"{name}: JPEG without a frame header before its image data (truncated or corrupt)")
