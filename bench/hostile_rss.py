"""The API process's memory and /healthz latency while it validates each class of hostile bundle.

Usage:
    python bench/hostile_rss.py [--classes NAME ...] [--work DIR] [--keep]

Starts the API as a real process (``panogs serve --no-worker``: uvicorn on the embedded SQLite database and the
local storage, what a new user runs), then, one class at a time, uploads a bundle of that class (the tiny test
bundle of tests/service with one file replaced; the classes of issue 29's items 2 and 3 and the image bomb) and
asks for a scene of it. Throughout, a sampler reads the RSS of the API process and of its children (the bundle
validation children and their fork server) from /proc every 20 ms, and a second client asks ``/healthz`` every
50 ms. Prints one table: the class, its archive size, the answer's status and first problem, the API process's
peak RSS, the validation children's peak RSS, the slowest /healthz and the request's wall time. Targets: the API
below 400 MB and /healthz below 1 s throughout.
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "tests" / "service"), str(REPO / "tests" / "support")]

import httpx  # noqa: E402
from bundle_image_bomb import zeros_png  # noqa: E402
from service_harness import Procs, free_port, wait_for  # noqa: E402
from svc_helpers import edit_manifest, write_tiny_bundle  # noqa: E402

PAGE_MB = os.sysconf("SC_PAGE_SIZE") / 1024**2
TARGET_RSS_MB = 400
TARGET_HEALTHZ_MS = 1000


# --- the hostile classes: each replaces or adds files of the tiny bundle ------------------------------------------


def _ply_header(*elements: str, fmt: str = "binary_little_endian") -> bytes:
    return (f"ply\nformat {fmt} 1.0\n" + "".join(elements) + "end_header\n").encode()


def ascii_ply_zeros(root: Path) -> None:
    """A 96 MB ASCII geometry.ply of zeros (16M vertices): was read whole, API 162 -> 1,327 MB."""
    n = 16_000_000
    with (root / "geometry.ply").open("wb") as fh:
        fh.write(
            _ply_header(f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n", fmt="ascii")
        )
        row = b"0 0 0\n" * 100_000
        for _ in range(n // 100_000):
            fh.write(row)


def ply_vertex_lists(root: Path) -> None:
    """A binary geometry.ply whose 64 vertices each carry a list of 1M floats (256 MB of rows)."""
    n, count = 64, 1_000_000
    with (root / "geometry.ply").open("wb") as fh:
        fh.write(_ply_header(f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
                             "property list uint32 float extra\n"))  # fmt: skip
        row = struct.pack("<fffI", 0, 0, 0, count) + bytes(4 * count)
        for _ in range(n):
            fh.write(row)


def ply_faces_before_vertices(root: Path) -> None:
    """5M face rows before the vertices (65 MB; 66 KB zipped): skipped row by row in Python, 77 s."""
    faces = 5_000_000
    with (root / "geometry.ply").open("wb") as fh:
        fh.write(_ply_header(f"element face {faces}\nproperty list uchar int vertex_indices\n",
                             "element vertex 3\nproperty float x\nproperty float y\nproperty float z\n"))  # fmt: skip
        row = struct.pack("<B3i", 3, 0, 1, 2) * 100_000
        for _ in range(faces // 100_000):
            fh.write(row)
        fh.write(bytes(3 * 12))


def vocabulary_npy_256mib(root: Path) -> None:
    """vocabulary.npy of 256 MiB of zeros (733 KB zipped): +1.05 GB when it was loaded whole."""
    header = "{'descr': '<f4', 'fortran_order': False, 'shape': (4, 16777216), }"
    header = header + " " * (63 - (len(header) + 10) % 64) + "\n"
    doc = json.loads((root / "vocabulary.json").read_text())
    doc["embeddings"] = "vocabulary.npy"  # the file the bundle's vocabulary names
    (root / "vocabulary.json").write_text(json.dumps(doc))
    with (root / "vocabulary.npy").open("wb") as fh:
        fh.write(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode())
        block = bytes(4 * 1024 * 1024)
        for _ in range(64):
            fh.write(block)


def vocabulary_131k_classes(root: Path) -> None:
    """131,072 classes in vocabulary.json (3.4 MB): the quadratic duplicate check never answered."""
    doc = json.loads((root / "vocabulary.json").read_text())
    doc["classes"] = [{"name": f"c{i}", "kind": "thing"} for i in range(131_072)]
    doc.pop("embeddings", None)
    (root / "vocabulary.json").write_text(json.dumps(doc))


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_million_chunks(root: Path) -> None:
    """A depth PNG of a million empty chunks (12 MB, 23 KB zipped) named by 12 frames: 21 s a frame."""
    ihdr = struct.pack(">IIBBBBB", 64, 48, 16, 0, 0, 0, 0)
    pixels = zlib.compress(b"".join(b"\x00" + bytes(128) for _ in range(48)))
    empty = _chunk(b"prVt", b"")
    data = b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + empty * 1_000_000 + _chunk(b"IDAT", pixels)
    (root / "depth" / "chunks.png").write_bytes(data + _chunk(b"IEND", b""))

    def edit(doc: dict[str, object]) -> None:
        frames = doc["frames"]
        assert isinstance(frames, list)
        doc["frames"] = [{**frames[i % 2], "id": f"f{i}", "depth": "depth/chunks.png"} for i in range(12)]

    edit_manifest(root, edit)


def image_bomb_20000(root: Path) -> None:
    """A valid 20000 x 20000 16-bit mask (778 KB): decoded whole before header checks (800 MB)."""
    (root / "masks" / "000001.png").write_bytes(zeros_png(20_000))


def many_frames(root: Path) -> None:
    """A 16 MB scene.json of 60,000 frames naming the same files: the frame checks' own CPU."""

    def edit(doc: dict[str, object]) -> None:
        frames = doc["frames"]
        assert isinstance(frames, list)
        doc["frames"] = [{**frames[i % 2], "id": f"f{i}"} for i in range(60_000)]

    edit_manifest(root, edit)


def deep_json(root: Path) -> None:
    """scene.json nested 100,000 levels deep (200 KB)."""
    (root / "scene.json").write_text('{"format": "panogs-scene/1", "name": ' + "[" * 100_000 + "]" * 100_000 + "}")


def valid(root: Path) -> None:
    """The tiny bundle as it is (the baseline)."""


CLASSES: dict[str, Callable[[Path], None]] = {
    "valid (baseline)": valid,
    "ascii ply of zeros, 96 MB": ascii_ply_zeros,
    "ply vertex lists, 256 MB": ply_vertex_lists,
    "ply 5M faces before vertices": ply_faces_before_vertices,
    "vocabulary.npy 256 MiB": vocabulary_npy_256mib,
    "vocabulary 131k classes": vocabulary_131k_classes,
    "png 1M empty chunks x 12 frames": png_million_chunks,
    "mask 20000 x 20000": image_bomb_20000,
    "scene.json 60k frames": many_frames,
    "scene.json 100k deep": deep_json,
}


def build_archive(work: Path, name: str) -> Path:
    folder = work / "bundles" / name.replace(" ", "_").replace(",", "").replace(".", "")
    root = write_tiny_bundle(folder)
    CLASSES[name](root)
    archive = folder.with_suffix(".zip")
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for path in sorted(root.rglob("*")):
            zf.write(path, path.relative_to(root).as_posix())
    shutil.rmtree(folder)
    return archive


# --- sampling ---------------------------------------------------------------------------------------------------


def _rss_mb(pid: int) -> float:
    try:
        return int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * PAGE_MB
    except (FileNotFoundError, ProcessLookupError, IndexError, ValueError):
        return 0.0


def _descendants(pid: int) -> list[int]:
    out, todo = [], [pid]
    while todo:
        parent = todo.pop()
        for task in Path(f"/proc/{parent}/task").glob("*"):
            try:
                children = (task / "children").read_text().split()
            except OSError:
                continue
            for child in children:
                out.append(int(child))
                todo.append(int(child))
    return out


@dataclass
class Samples:
    api_pid: int
    api_mb: float = 0.0
    children_mb: float = 0.0
    healthz_ms: float = 0.0
    healthz_failures: int = 0
    stop: threading.Event = field(default_factory=threading.Event)

    def rss_loop(self) -> None:
        while not self.stop.is_set():
            self.api_mb = max(self.api_mb, _rss_mb(self.api_pid))
            self.children_mb = max(self.children_mb, sum(_rss_mb(p) for p in _descendants(self.api_pid)))
            time.sleep(0.02)

    def healthz_loop(self, url: str) -> None:
        with httpx.Client(timeout=30) as client:
            while not self.stop.is_set():
                start = time.perf_counter()
                try:
                    ok = client.get(f"{url}/healthz").status_code == 200
                except httpx.HTTPError:
                    ok = False
                self.healthz_ms = max(self.healthz_ms, 1000 * (time.perf_counter() - start))
                self.healthz_failures += not ok
                time.sleep(0.05)


def send(url: str, key: str, archive: Path, pid: int) -> tuple[int, str, Samples, float]:
    samples = Samples(pid)
    threads = [threading.Thread(target=samples.rss_loop), threading.Thread(target=samples.healthz_loop, args=(url,))]
    for t in threads:
        t.start()
    auth = {"Authorization": f"Bearer {key}"}
    data = archive.read_bytes()
    start = time.perf_counter()
    try:
        with httpx.Client(base_url=url, headers=auth, timeout=600) as client:
            headers = {"Tus-Resumable": "1.0.0", "Upload-Length": str(len(data)),
                       "Content-Type": "application/offset+octet-stream",
                       "Upload-Metadata": "filename " + base64.b64encode(archive.name.encode()).decode()}  # fmt: skip
            upload = client.post("/v1/uploads", content=data, headers=headers)
            assert upload.status_code == 201, upload.text
            answer = client.post("/v1/scenes", json={"upload_id": upload.json()["id"]})
        seconds = time.perf_counter() - start
        time.sleep(0.2)  # a last sample after the answer
    finally:
        samples.stop.set()
        for t in threads:
            t.join()
    body = answer.json()
    first = (body.get("problems") or [body.get("message", "")])[0] if answer.status_code >= 400 else "scene made"
    return answer.status_code, first, samples, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--classes", nargs="*", default=list(CLASSES), help="which classes (default: all)")
    parser.add_argument("--work", type=Path, default=None, help="folder for the bundles and the service's data")
    parser.add_argument("--keep", action="store_true", help="keep the work folder")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="hostile-rss-"))
    work.mkdir(parents=True, exist_ok=True)
    env = {"PANOGS_DATA_DIR": str(work / "data"), "PANOGS_LOG_LEVEL": "WARNING",
           "PANOGS_MIN_FREE_DISK_BYTES": "0"}  # fmt: skip
    procs = Procs(env, work)
    try:
        argv = [sys.executable, "-m", "service.cli", "keys", "create", "--name", "bench"]
        key = subprocess.run(argv, env=procs.env, cwd=work, capture_output=True, text=True, check=True).stdout.strip()
        port = free_port()
        api = procs.start("api", [sys.executable, "-m", "service.cli", "serve", "--no-worker", "--port", str(port)])
        url = f"http://127.0.0.1:{port}"
        wait_for(lambda: httpx.get(f"{url}/healthz", timeout=1).status_code == 200, 120, "the API", procs.tail("api"))
        print(f"API pid {api.pid}, idle RSS {_rss_mb(api.pid):.0f} MB; {os.cpu_count()} CPUs", flush=True)
        print("| class | archive KB | answer | first problem | API peak RSS MB | validation children peak RSS MB "
              "| max /healthz ms | request s |")  # fmt: skip
        print("|---|---:|---|---|---:|---:|---:|---:|")
        for name in args.classes:
            archive = build_archive(work, name)
            code, first, s, seconds = send(url, key, archive, api.pid)
            first = first if len(first) <= 110 else first[:107] + "..."
            fails = f" ({s.healthz_failures} failed)" if s.healthz_failures else ""
            kib = f"{archive.stat().st_size / 1024:,.0f}"
            row = [name, kib, str(code), first.replace("|", "/"), f"{s.api_mb:.0f}", f"{s.children_mb:.0f}",
                   f"{s.healthz_ms:.0f}{fails}", f"{seconds:.1f}"]  # fmt: skip
            print("| " + " | ".join(row) + " |", flush=True)
            archive.unlink()
    finally:
        procs.stop_all()
        if not args.keep and args.work is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
