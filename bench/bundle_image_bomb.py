"""Memory and time of validating a bundle that holds one huge image (an image bomb).

Usage:
    python bench/bundle_image_bomb.py [--size 20000] [--work bench/results/image_bomb] [--code CHECKOUT]

Writes the tiny test bundle (two 64 x 48 frames) with ``masks/000001.png`` replaced by a valid ``--size`` x
``--size`` 16-bit grey PNG of zeros (compressed row by row, so the script itself never holds the pixels), then
runs ``open_bundle`` on it in a fresh child process and prints the outcome, the seconds it took and the child's
peak resident memory before and after. ``--code`` names the checkout whose ``panogs_core`` the child measures
(default: this one), so that the same bundle can be measured on an older commit. Before the header check the
bundle was accepted after decoding 800 MB of pixels; with it the mask is refused from its first 33 bytes.
"""

from __future__ import annotations

import argparse
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "tests" / "service"), str(REPO / "tests" / "support")]

CHILD = r"""
import resource, sys, time
from panogs_core.io.bundle import open_bundle
from panogs_core.errors import BundleError
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
start = time.perf_counter()
try:
    open_bundle(sys.argv[1])
    outcome = "accepted"
except BundleError as exc:
    outcome = "refused: " + "; ".join(exc.problems)
seconds = time.perf_counter() - start
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(f"{outcome}\nopen_bundle {seconds:.2f} s; peak RSS {before:.0f} MB before, {after:.0f} MB after")
"""


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def zeros_png(size: int) -> bytes:
    """A valid ``size`` x ``size`` 16-bit grey PNG of zeros."""
    compressor = zlib.compressobj(9)
    row = b"\x00" * (1 + 2 * size)
    data = b"".join(compressor.compress(row) for _ in range(size)) + compressor.flush()
    ihdr = struct.pack(">IIBBBBB", size, size, 16, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", data) + _chunk(b"IEND", b"")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=20_000)
    parser.add_argument("--work", type=Path, default=REPO / "bench" / "results" / "image_bomb")
    parser.add_argument("--code", type=Path, default=REPO, help="checkout whose panogs_core is measured")
    args = parser.parse_args()
    from svc_helpers import write_tiny_bundle

    root = args.work / f"bundle-{args.size}"
    if not (root / "scene.json").exists():
        write_tiny_bundle(root)
        (root / "masks" / "000001.png").write_bytes(zeros_png(args.size))
    mask = root / "masks" / "000001.png"
    print(f"mask {args.size}x{args.size} 16-bit: {mask.stat().st_size:,} bytes on disk")
    env = {**os.environ, "PYTHONPATH": str(args.code.resolve())}
    command = [sys.executable, "-c", CHILD, str(root.resolve())]
    result = subprocess.run(command, capture_output=True, text=True, check=True, env=env, cwd=args.work)
    print(f"code: {args.code.resolve()}")
    print(result.stdout, end="")


if __name__ == "__main__":
    main()
