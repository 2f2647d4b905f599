"""A worker's copies of a scene's stage checkpoints on its own disk (object storage): a re-run on the same worker
reads no checkpoint from the store, another worker fetches it and keeps a copy, and the copies go with the
worker's cached bundle of the scene. Over a real S3 server (SeaweedFS, the session's ``seaweedfs_server``)."""

from __future__ import annotations

import secrets
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from seaweedfs import SeaweedFS

from service.storage import Storage
from service.storage.s3 import S3Storage
from worker.bundle_cache import COMPLETE, BundleCache
from worker.shared_checkpoints import SceneCheckpoints


class CountingS3(S3Storage):
    """S3 that counts the checkpoint downloads."""

    downloads = 0

    def get_file(self, key: str, path: Path) -> Any:
        CountingS3.downloads += 1
        return super().get_file(key, path)


@pytest.fixture
def s3(seaweedfs_server: SeaweedFS) -> Iterator[CountingS3]:
    store = CountingS3(
        seaweedfs_server.url(f"copies-{secrets.token_hex(4)}"),
        endpoint_url=seaweedfs_server.endpoint,
        access_key_id=seaweedfs_server.access_key,
        secret_access_key=seaweedfs_server.secret_key,
    )
    CountingS3.downloads = 0
    yield store
    store.delete_prefix("scenes/")


def _worker(s3: CountingS3, root: Path) -> tuple[Storage, BundleCache]:
    """One worker host: its own work folder over the shared store, and its bundle cache."""
    storage = Storage(root, s3)
    return storage, BundleCache(storage, root / "work" / "bundles", 1 << 30, lambda ids: set(ids))


def _job(storage: Storage, scene_id: uuid.UUID, copies: Path | None) -> SceneCheckpoints:
    return SceneCheckpoints(storage, scene_id, f"job {uuid.uuid4()}", lease_s=5.0, poll_s=0.05, local_copies=copies)


def test_a_rerun_on_the_same_worker_reads_no_checkpoint_from_the_store(s3: CountingS3, tmp_path: Path) -> None:
    storage, bundles = _worker(s3, tmp_path / "host-a")
    scene_id = uuid.uuid4()
    copies = bundles.stages_folder(scene_id)
    first = _job(storage, scene_id, copies)
    assert first.fetch("fusion", "k1", tmp_path / "run1" / "fusion.npz") is False  # computed by the first job
    made = tmp_path / "run1" / "fusion.npz"
    made.parent.mkdir()
    made.write_bytes(b"fused features")
    first.store("fusion", "k1", made)
    again = _job(storage, scene_id, copies)
    dest = tmp_path / "run2" / "stages" / "fusion.npz"
    assert again.fetch("fusion", "k1", dest) is True
    assert dest.read_bytes() == b"fused features"
    assert CountingS3.downloads == 0, "the worker's own copy was read, not the store"
    assert again.reused == ["fusion"]
    assert dest in again.kept


def test_another_worker_fetches_once_then_keeps_a_copy(s3: CountingS3, tmp_path: Path) -> None:
    scene_id = uuid.uuid4()
    storage_a, bundles_a = _worker(s3, tmp_path / "host-a")
    first = _job(storage_a, scene_id, bundles_a.stages_folder(scene_id))
    assert first.fetch("fusion", "k1", tmp_path / "a.npz") is False
    (tmp_path / "a.npz").write_bytes(b"fused features")
    first.store("fusion", "k1", tmp_path / "a.npz")
    storage_b, bundles_b = _worker(s3, tmp_path / "host-b")  # no copy here: the store has it
    for run in ("b1", "b2"):
        job = _job(storage_b, scene_id, bundles_b.stages_folder(scene_id))
        assert job.fetch("fusion", "k1", tmp_path / run / "fusion.npz") is True
        assert (tmp_path / run / "fusion.npz").read_bytes() == b"fused features"
    assert CountingS3.downloads == 1, "fetched from the store once, then from host B's copy"
    assert (bundles_b.stages_folder(scene_id) / "fusion" / "k1.ckpt").read_bytes() == b"fused features"
    assert not list(bundles_b.stages_folder(scene_id).rglob(".*")), "no half-written copy left"


def test_the_copies_count_in_the_cache_and_go_with_the_scenes_bundle(s3: CountingS3, tmp_path: Path) -> None:
    storage, _ = _worker(s3, tmp_path / "host")
    gone, kept = uuid.uuid4(), uuid.uuid4()
    alive = {kept}
    bundles = BundleCache(storage, tmp_path / "host" / "work" / "bundles", 1 << 30, lambda ids: set(ids) & alive)
    for scene_id in (gone, kept):
        entry = bundles.folder / str(scene_id)  # a cached bundle as a fetch leaves it
        entry.mkdir(parents=True)
        (entry / "scene.json").write_text("{}")
        (entry / COMPLETE).write_text("2")
        copy = bundles.stages_folder(scene_id) / "fusion" / "k1.ckpt"
        copy.parent.mkdir(parents=True)
        copy.write_bytes(b"x" * 1000)
    bundles.sweep()  # the deleted scene's bundle and copies go, the live one's stay
    assert not (bundles.folder / str(gone)).exists()
    assert not bundles.stages_folder(gone).exists()
    assert (bundles.stages_folder(kept) / "fusion" / "k1.ckpt").is_file()
    bundles.max_bytes = 500  # the bundle (2 bytes) fits, with its copies (1,000 bytes) it does not
    bundles.sweep()
    assert not (bundles.folder / str(kept)).exists()
    assert not bundles.stages_folder(kept).exists()
    orphan = bundles.stages_folder(uuid.uuid4()) / "fusion" / "k.ckpt"  # copies whose bundle is not here
    orphan.parent.mkdir(parents=True)
    orphan.write_bytes(b"y")
    bundles.sweep()
    assert not orphan.parent.parent.exists()
