"""Upload throughput into S3 (SeaweedFS on loopback) through the API, and the API's memory while it runs.

Usage:
    python bench/service/bench_s3_upload.py [--mib 300] [--chunk-mib 4] [--repeats 2] [--backend s3|local]

Starts a SeaweedFS (``weed mini``, tests/support/seaweedfs.py) and the API with the compose command on the embedded
SQLite with ``PANOGS_STORAGE_URL`` pointing at it, then sends ``--mib`` of random bytes as one tus upload in
``--chunk-mib`` PATCHes, ``--repeats`` times. Prints MB/s (10^6 bytes per second, creation to the last 204) and
the API process's resident memory (VmRSS) before the upload and its peak during it, sampled every 50 ms.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests" / "support"))

import httpx
from seaweedfs import seaweedfs
from service_harness import Procs

TUS = {"Tus-Resumable": "1.0.0", "Content-Type": "application/offset+octet-stream"}


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


class Peak:
    """The peak RSS of a process, sampled in a thread."""

    def __init__(self, pid: int) -> None:
        self.pid, self.peak, self._stop = pid, 0.0, threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            self.peak = max(self.peak, rss_mb(self.pid))

    def __enter__(self) -> Peak:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        self._thread.join()


def upload(url: str, headers: dict[str, str], data: bytes, chunk: int) -> float:
    """Seconds from creation to the last PATCH's answer."""
    with httpx.Client(base_url=url, headers=headers, timeout=120) as c:
        start = time.perf_counter()
        created = c.post("/v1/uploads", headers={**TUS, "Upload-Length": str(len(data))})
        assert created.status_code == 201, created.text
        upload_id = created.json()["id"]
        for offset in range(0, len(data), chunk):
            answer = c.patch(f"/v1/uploads/{upload_id}", content=data[offset : offset + chunk],
                             headers={**TUS, "Upload-Offset": str(offset)})  # fmt: skip
            assert answer.status_code == 204, answer.text
        seconds = time.perf_counter() - start
        assert c.get(f"/v1/uploads/{upload_id}").json()["state"] == "complete"
        c.delete(f"/v1/uploads/{upload_id}")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--mib", type=int, default=300)
    parser.add_argument("--chunk-mib", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--backend", choices=["s3", "local"], default="s3", help="local: the same upload to disk")
    args = parser.parse_args()
    data = os.urandom(args.mib * 1024 * 1024)
    with tempfile.TemporaryDirectory() as tmp_name, seaweedfs(Path(tmp_name) / "s3") as s3:
        tmp = Path(tmp_name)
        storage_env = s3.env("bench") if args.backend == "s3" else {}
        procs = Procs({**storage_env, "PANOGS_DATA_DIR": str(tmp / "api-data")}, tmp)
        try:
            import subprocess

            key = subprocess.run(
                [sys.executable, "-m", "service.cli", "keys", "create", "--name", "bench"],
                env=procs.env, cwd=tmp, capture_output=True, text=True, check=True, timeout=120,
            ).stdout.strip()  # fmt: skip
            url = procs.api()
            pid = procs.procs["api"].pid
            headers = {"Authorization": f"Bearer {key}"}
            where = "SeaweedFS on loopback" if args.backend == "s3" else "the local disk"
            print(f"upload of {args.mib} MiB in {args.chunk_mib} MiB PATCHes to {where}")
            print("| run | MB/s | API RSS before (MB) | API RSS peak (MB) |")
            print("|---|---|---|---|")
            for run in range(1, args.repeats + 1):
                before = rss_mb(pid)
                with Peak(pid) as peak:
                    seconds = upload(url, headers, data, args.chunk_mib * 1024 * 1024)
                print(f"| {run} | {len(data) / seconds / 1e6:.1f} | {before:.0f} | {peak.peak:.0f} |")
        finally:
            procs.kill_all()


if __name__ == "__main__":
    main()
