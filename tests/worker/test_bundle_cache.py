"""The bundles a worker keeps between jobs (object storage): fetched once per host, removed with their scene, kept
within the bound (least recently used first), never removed while a job reads them. The store is the local
backend used as object storage by a worker with a folder of its own (as with S3: the worker's disk is not it)."""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterable
from pathlib import Path

from service.storage import Storage
from service.storage.local import LocalStorage
from worker.bundle_cache import BundleCache


def _store_bundle(objects: LocalStorage, scene_id: uuid.UUID, size: int) -> str:
    prefix = f"scenes/{scene_id}/bundle/"
    objects.put_bytes(prefix + "scene.json", b"{}")
    objects.put_bytes(prefix + "features/000000.npy", os.urandom(size))
    return prefix


def _cache(tmp_path: Path, max_bytes: int, alive: set[uuid.UUID]) -> tuple[BundleCache, LocalStorage]:
    objects = LocalStorage(tmp_path / "store")
    storage = Storage(tmp_path / "worker", objects)
    assert storage.root != objects.root  # the worker's folder is not the store

    def live(ids: Iterable[uuid.UUID]) -> set[uuid.UUID]:
        return set(ids) & alive

    return BundleCache(storage, tmp_path / "worker" / "work" / "bundles", max_bytes, live), objects


def test_a_scene_bundle_is_fetched_once_per_host(tmp_path: Path) -> None:
    scene = uuid.uuid4()
    cache, objects = _cache(tmp_path, 1 << 20, {scene})
    prefix = _store_bundle(objects, scene, 1000)
    with cache.use(scene, prefix) as bundle:
        first = (bundle / "features" / "000000.npy").read_bytes()
    objects.delete_prefix(prefix)  # the next use must not need the store
    with cache.use(scene, prefix) as bundle:
        assert (bundle / "features" / "000000.npy").read_bytes() == first
        assert (bundle / "scene.json").read_bytes() == b"{}"


def test_the_sweep_removes_deleted_scenes_and_the_oldest_beyond_the_bound(tmp_path: Path) -> None:
    old, recent, deleted = uuid.uuid4(), uuid.uuid4(), uuid.uuid4()
    cache, objects = _cache(tmp_path, 150_000, {old, recent})
    for scene in (old, recent, deleted):
        with cache.use(scene, _store_bundle(objects, scene, 100_000)):
            pass
    os.utime(cache.folder / str(old), (1, 1))  # used longest ago
    cache.sweep()
    kept = sorted(p.name for p in cache.folder.iterdir() if p.is_dir())
    assert kept == [str(recent)]  # the deleted scene's went, and the oldest: two would pass 150 kB


def test_a_bundle_in_use_is_not_removed(tmp_path: Path) -> None:
    scene = uuid.uuid4()
    cache, objects = _cache(tmp_path, 0, set())  # nothing may be kept, and the scene is gone
    with cache.use(scene, _store_bundle(objects, scene, 1000)) as bundle:
        cache.sweep()  # as another worker process would, while this job reads the bundle
        assert (bundle / "scene.json").is_file()
    cache.sweep()
    assert not (cache.folder / str(scene)).exists()


def test_a_fetch_that_died_is_fetched_again(tmp_path: Path) -> None:
    scene = uuid.uuid4()
    cache, objects = _cache(tmp_path, 1 << 20, {scene})
    prefix = _store_bundle(objects, scene, 1000)
    half = cache.folder / str(scene)
    half.mkdir(parents=True)
    (half / "scene.json").write_bytes(b"half")  # no completion mark: a fetch killed half way
    with cache.use(scene, prefix) as bundle:
        assert (bundle / "scene.json").read_bytes() == b"{}"
        assert (bundle / "features" / "000000.npy").stat().st_size == 1000
