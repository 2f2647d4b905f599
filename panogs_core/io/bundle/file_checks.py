"""The checks of a frame's files: an image by its header, then its data's framing (never decoded here), and a
feature map by its ``.npy`` header. Each appends problem lines of the form ``<file>: <found>, expected <what>``.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path
from typing import Any

from panogs_core.errors import InputError
from panogs_core.io.bundle.format import FEATURE_DTYPES, BundleLimits, max_png_chunks
from panogs_core.io.bundle.problems import reason
from panogs_core.io.image_header import ImageHeader, read_image_header
from panogs_core.io.npy_header import NpyHeader, read_npy_header


def check_image(
    root: Path, rel: str, kind: str, camera_size: tuple[int, int] | None, limits: BundleLimits, problems: list[str]
) -> None:
    """The header's rules (:func:`header_problem`), then the data's framing (:func:`data_problem`).

    No image is decoded here (docs/scene_format.md §5): the header already fixes size, channels and bit depth,
    and a truncated or altered file breaks the framing (a PNG chunk's length or CRC-32, its IEND; a JPEG's end
    marker). An image well framed that still fails to decode is refused by the stage that reads it, naming the
    file. The stages decode each image they use anyway; decoding all of them here was most of the validation's
    time (docs/benchmarks.md, "Speed at ScanNet size").
    """
    try:
        info = read_image_header(root / rel, name=rel)
    except InputError as exc:
        problems.append(str(exc))
        return
    problem = header_problem(rel, kind, info, camera_size, limits.max_image_pixels)
    if problem is None:
        problem = data_problem(root, rel)
    if problem is not None:
        problems.append(problem)


def header_problem(
    rel: str, kind: str, info: ImageHeader, camera_size: tuple[int, int] | None, max_pixels: int
) -> str | None:
    """What is wrong with an image by its header (format, pixel limit, camera size, channels, bits), or None.

    The same rules as the checks after decoding (docs/scene_format.md §1), so that an image that would be
    refused anyway is refused without allocating its pixels.
    """
    want_format = "JPEG" if rel.lower().endswith((".jpg", ".jpeg")) else "PNG"
    if info.format != want_format:
        return f"{rel}: holds {info.format} data, expected {want_format} (by its first bytes)"
    if info.pixels > max_pixels:
        return f"{rel}: {info.width}x{info.height} ({info.pixels:,} pixels), over the pixel limit of {max_pixels:,}"
    if kind == "depth":
        if camera_size is not None and (info.height, info.width) != camera_size:
            return f"{rel}: {info.width}x{info.height}, expected {camera_size[1]}x{camera_size[0]} (camera)"
        if info.channels != 1 or info.bit_depth != 16:
            return f"{rel}: {info.describe()}, expected 16-bit single channel"
    elif kind == "masks" and info.channels != 1:
        return f"{rel}: {info.describe()}, expected 8- or 16-bit single channel"
    elif kind == "color" and (
        info.bit_depth != 8 or info.channels not in (3, 4) or (info.channels == 4 and info.format == "PNG")
    ):
        # A JPEG of 4 components is CMYK, which the decoder turns into 3 channels; a PNG of 4 is RGBA.
        return f"{rel}: {info.describe()}, expected 8-bit 3 channels"
    return None


def data_problem(root: Path, rel: str) -> str | None:
    """What breaks the framing of an image's data (truncation, altered bytes), or None."""
    try:
        data = (root / rel).read_bytes()
    except OSError as exc:
        return f"{rel}: cannot be read ({reason(exc)})"
    if rel.lower().endswith((".jpg", ".jpeg")):
        if not jpeg_complete(data):
            # libjpeg decodes a truncated JPEG with only a warning and grey fill: look for the end marker instead.
            return f"{rel}: truncated JPEG (no end-of-image marker after the image data)"
        return None
    problem = png_framing_problem(data, max_png_chunks(len(data)))
    return None if problem is None else f"{rel}: does not decode as an image ({problem})"


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_framing_problem(data: bytes, max_chunks: int) -> str | None:
    """Why a PNG's chunks are not whole (a length past the end, a CRC-32 that does not match, no IEND), or None.

    Every byte of a PNG after its signature is inside a chunk whose CRC covers its type and data, so a truncated
    or altered file fails here without inflating the image. The walk stops after ``max_chunks`` chunks: each one
    costs a Python step, and no encoder writes that many for the file's size (``format.max_png_chunks``).
    """
    if not data.startswith(_PNG_SIGNATURE):
        return "not a PNG signature"
    view = memoryview(data)
    pos = len(_PNG_SIGNATURE)
    chunks = 0
    while pos + 12 <= len(data):
        chunks += 1
        if chunks > max_chunks:
            return f"more than {max_chunks:,} chunks in {len(data):,} bytes, expected at most that many"
        length = int.from_bytes(data[pos : pos + 4], "big")
        kind = bytes(data[pos + 4 : pos + 8])
        end = pos + 12 + length
        if end > len(data):
            return f"truncated PNG: its {kind.decode('latin-1')!r} chunk runs past the end of the file"
        if zlib.crc32(view[pos + 4 : end - 4]) != int.from_bytes(data[end - 4 : end], "big"):
            return f"corrupt PNG: the CRC of its {kind.decode('latin-1')!r} chunk does not match"
        if kind == b"IEND":
            return None
        pos = end
    return "truncated PNG: no IEND chunk"


def jpeg_complete(data: bytes) -> bool:
    """True unless a JPEG's main image data lacks its end-of-image marker (EOI, ``FF D9``).

    The header segments are skipped by their lengths up to the first start-of-scan, so that the EOI of an EXIF
    thumbnail does not count; entropy-coded data never holds ``FF D9``. Data after the EOI (phones append
    trailers) is allowed. A file that is not a JPEG at all is left to the decoder to refuse.
    """
    if not data.startswith(b"\xff\xd8"):
        return True
    pos = 2
    while pos + 4 <= len(data) and data[pos] == 0xFF:
        marker = data[pos + 1]
        if marker == 0xDA:  # start of scan: the image data follows
            return data.find(b"\xff\xd9", pos) != -1
        if marker == 0xFF:  # fill byte
            pos += 1
        elif 0xD0 <= marker <= 0xD8 or marker == 0x01:  # markers without a length
            pos += 2
        else:
            pos += 2 + int.from_bytes(data[pos + 2 : pos + 4], "big")
    return False


def check_features(root: Path, rel: str, dim: int | None, limits: BundleLimits, problems: list[str]) -> None:
    header = npy_header(root / rel, rel, problems)
    if header is None:
        return
    shape, dtype = header.shape, header.dtype
    if dtype not in FEATURE_DTYPES:
        problems.append(f"{rel}: dtype {dtype}, expected float16 or float32")
    if len(shape) != 3 or min(shape, default=0) < 1:
        problems.append(f"{rel}: shape {shape}, expected (Hf, Wf, D) with every size >= 1")
    else:
        if dim is not None and shape[2] != dim:
            problems.append(f"{rel}: last dimension {shape[2]}, expected {dim} (features.dim)")
        if shape[0] * shape[1] > limits.max_image_pixels:
            problems.append(
                f"{rel}: {shape[1]}x{shape[0]} cells ({shape[0] * shape[1]:,}), over the pixel limit of "
                f"{limits.max_image_pixels:,}"
            )
    if header.fortran_order:
        problems.append(f"{rel}: Fortran order, expected C order")


def npy_header(path: Path, rel: str, problems: list[str]) -> NpyHeader | None:
    """The header of a .npy, when it is valid and the file holds exactly the data it declares; else a problem.

    Only the header is read. Declared sizes are exact Python integers compared with the file's real size, so a
    shape that multiplies past int64 is refused, never wrapped to a small size that matches.
    """
    try:
        with path.open("rb") as fh:
            header = read_npy_header(fh, rel)
            available = os.fstat(fh.fileno()).st_size - header.offset
    except InputError as exc:
        problems.append(str(exc))
        return None
    except OSError as exc:
        problems.append(f"{rel}: cannot be read ({reason(exc)})")
        return None
    problem = header.size_problem(available)
    if problem is not None:
        problems.append(f"{rel}: {problem}")
        return None
    return header


def check_rel_path(root: Path, value: Any, where: str, exts: tuple[str, ...], problems: list[str]) -> str | None:
    """A referenced path must be relative, stay in the root, avoid links, exist and be a regular file."""
    if not isinstance(value, str) or not value:
        problems.append(f"{where}: {value!r}, expected a relative path")
        return None
    if value.startswith("/") or "\\" in value or (len(value) > 1 and value[1] == ":"):
        problems.append(f"{value}: absolute or non-posix path ({where}), expected a path relative to the root")
        return None
    parts = value.split("/")
    if ".." in parts or "" in parts:
        problems.append(f"{value}: leaves the bundle root or has empty parts ({where})")
        return None
    if not value.lower().endswith(exts):
        problems.append(f"{value}: extension not allowed ({where}), expected {' or '.join(exts)}")
        return None
    current = root
    for part in parts:
        current = current / part
        if current.is_symlink():
            problems.append(f"{value}: {current.relative_to(root)} is a symbolic link ({where}), not allowed")
            return None
    if not current.exists():
        problems.append(f"{value}: missing ({where})")
        return None
    if not current.is_file():
        problems.append(f"{value}: not a regular file ({where})")
        return None
    if not current.resolve().is_relative_to(root.resolve()):  # belt and braces after the symlink walk
        problems.append(f"{value}: resolves outside the bundle root ({where})")
        return None
    return value
