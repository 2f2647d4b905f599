"""The storage protocol's contract, the same cases against both backends: ``LocalStorage`` over a folder and
``S3Storage`` over a real S3 server (SeaweedFS, started by the session's ``seaweedfs_server`` fixture).

Multipart uploads with a 1-byte last part, ranges at the start, middle and end and past the end, conditional
creates, signed GET links, prefix deletes that also abort unfinished uploads, and keys that would leave the root.
"""

from __future__ import annotations

import os
import secrets
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from seaweedfs import SeaweedFS

from service.storage.local import LocalStorage
from service.storage.objects import (
    MIN_PART_BYTES,
    AlreadyExists,
    ObjectNotFound,
    ObjectStorage,
    RangeNotSatisfiable,
    StorageError,
)
from service.storage.s3 import S3Storage, parse_s3_url

DATA = bytes(range(256)) * 40  # 10,240 bytes, each offset's value known


@pytest.fixture(params=["local", "s3"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[ObjectStorage]:
    if request.param == "local":
        yield LocalStorage(tmp_path / "storage")
        return
    server: SeaweedFS = request.getfixturevalue("seaweedfs_server")
    prefix = f"contract-{secrets.token_hex(4)}"
    s3 = S3Storage(
        server.url(prefix),
        endpoint_url=server.endpoint,
        access_key_id=server.access_key,
        secret_access_key=server.secret_key,
    )
    yield s3
    s3.delete_prefix("x/")


def fetch_signed(store: ObjectStorage, url: str) -> tuple[int, bytes]:
    """GET a signed link: over HTTP from S3; a local link is one the API serves, checked by its signature here."""
    if isinstance(store, LocalStorage):
        key = store.key_of_link(url)
        return (200, store.get_bytes(key)) if key is not None else (403, b"")
    answer = httpx.get(url, timeout=10)
    return answer.status_code, answer.content


def joined(chunks: Iterator[bytes]) -> bytes:
    return b"".join(chunks)


def test_put_get_stat_list_delete(store: ObjectStorage) -> None:
    info = store.put_bytes("x/a/one", DATA)
    assert info.size == len(DATA)
    assert info.etag
    store.put_bytes("x/a/b/two", b"2")
    store.put_bytes("x/ab/three", b"3")
    assert store.get_bytes("x/a/one") == DATA
    stat = store.stat("x/a/one")
    assert stat is not None
    assert stat.size == len(DATA)
    assert store.stat("x/a/missing") is None
    assert [o.key for o in store.list_objects("x/a/")] == ["x/a/b/two", "x/a/one"]  # key order; x/ab/ is not under x/a/
    store.delete("x/a/one")
    store.delete("x/a/one")  # absent: nothing happens
    assert store.stat("x/a/one") is None
    with pytest.raises(ObjectNotFound):
        store.get_bytes("x/a/one")


def test_files_round_trip_streamed(store: ObjectStorage, tmp_path: Path) -> None:
    src = tmp_path / "src.bin"
    src.write_bytes(os.urandom(17 * 1024 * 1024 + 3))  # above S3Storage's transfer chunk: sent in parts
    info = store.put_file("x/big", src)
    assert info.size == src.stat().st_size
    dest = tmp_path / "out" / "big.bin"
    store.get_file("x/big", dest)
    assert dest.read_bytes() == src.read_bytes()
    assert [p.name for p in dest.parent.iterdir()] == ["big.bin"]  # no temporary file left beside it
    with pytest.raises(ObjectNotFound):
        store.get_file("x/none", tmp_path / "none")


@pytest.mark.parametrize(
    ("start", "end", "expected"),
    [
        (0, 10, DATA[:10]),  # start
        (5000, 5100, DATA[5000:5100]),  # middle
        (len(DATA) - 7, len(DATA), DATA[-7:]),  # end
        (len(DATA) - 7, None, DATA[-7:]),  # to the end
        (len(DATA) - 7, len(DATA) + 500, DATA[-7:]),  # an end past the end is clipped
        (0, None, DATA),
    ],
    ids=["start", "middle", "end", "open-end", "end-past-end", "whole"],
)
def test_ranges(store: ObjectStorage, start: int, end: int | None, expected: bytes) -> None:
    store.put_bytes("x/r", DATA)
    assert joined(store.read_range("x/r", start, end, block=1000)) == expected


def test_range_past_the_end_is_refused(store: ObjectStorage) -> None:
    store.put_bytes("x/r", DATA)
    for start in (len(DATA), len(DATA) + 1000):
        with pytest.raises(RangeNotSatisfiable) as caught:
            store.read_range("x/r", start, None)
        assert caught.value.size == len(DATA)
    with pytest.raises(ObjectNotFound):
        store.read_range("x/missing", 0, 10)


def test_blocks_are_bounded(store: ObjectStorage) -> None:
    store.put_bytes("x/r", DATA)
    chunks = list(store.read_range("x/r", 0, None, block=1024))
    assert max(len(c) for c in chunks) <= 1024
    assert b"".join(chunks) == DATA


def test_empty_object(store: ObjectStorage) -> None:
    store.put_bytes("x/empty", b"")
    assert joined(store.read_range("x/empty")) == b""
    assert store.get_bytes("x/empty") == b""


def test_conditional_create(store: ObjectStorage) -> None:
    store.put_bytes("x/lease", b"first", if_absent=True)
    with pytest.raises(AlreadyExists):
        store.put_bytes("x/lease", b"second", if_absent=True)
    assert store.get_bytes("x/lease") == b"first"
    store.put_bytes("x/lease", b"third")  # an unconditional put replaces
    assert store.get_bytes("x/lease") == b"third"


def test_multipart_with_a_one_byte_last_part(store: ObjectStorage) -> None:
    upload = store.start_multipart("x/mp")
    first = os.urandom(MIN_PART_BYTES)
    p1 = store.put_part("x/mp", upload, 1, first)
    p2 = store.put_part("x/mp", upload, 2, b"!")
    listed = store.list_parts("x/mp", upload)
    assert [(p.number, p.size) for p in listed] == [(1, MIN_PART_BYTES), (2, 1)]
    assert [p.etag for p in listed] == [p1.etag, p2.etag]
    assert store.stat("x/mp") is None  # nothing is visible before the upload completes
    info = store.complete_multipart("x/mp", upload, listed)
    assert info.size == MIN_PART_BYTES + 1
    assert store.get_bytes("x/mp") == first + b"!"
    assert store.list_multipart("x/") == []


def test_multipart_part_replaced_and_small_parts_refused(store: ObjectStorage) -> None:
    upload = store.start_multipart("x/mp")
    small = store.put_part("x/mp", upload, 1, b"a" * 100)
    last = store.put_part("x/mp", upload, 2, b"b")
    with pytest.raises(StorageError):  # a part under 5 MiB before the last, as S3 refuses it
        store.complete_multipart("x/mp", upload, [small, last])
    # The same number again replaces the part. Completing names each part by its tag: SeaweedFS lists both
    # versions of a part sent twice within one second, so the caller keeps what put_part returned.
    again = store.put_part("x/mp", upload, 1, b"c" * MIN_PART_BYTES)
    store.complete_multipart("x/mp", upload, [again, last])
    assert store.get_bytes("x/mp") == b"c" * MIN_PART_BYTES + b"b"


def test_aborted_multipart_leaves_no_parts(store: ObjectStorage) -> None:
    upload = store.start_multipart("x/u/data")
    store.put_part("x/u/data", upload, 1, b"z" * 1000)
    assert store.list_multipart("x/u/") == [("x/u/data", upload)]
    store.abort_multipart("x/u/data", upload)
    store.abort_multipart("x/u/data", upload)  # gone: nothing happens
    assert store.list_multipart("x/u/") == []
    with pytest.raises(ObjectNotFound):
        store.list_parts("x/u/data", upload)


def test_a_folder_push_stores_changes_and_deletes_what_was_removed(store: ObjectStorage, tmp_path: Path) -> None:
    from types import SimpleNamespace

    from service.storage import TreePush

    folder = tmp_path / "tile"
    (folder / "stages").mkdir(parents=True)
    (folder / "labels.npz").write_bytes(b"labels")
    (folder / "stages" / "fusion.npz").write_bytes(b"x" * 1000)
    push = TreePush(SimpleNamespace(objects=store), folder, "jobs/j/tiles/t/")  # type: ignore[arg-type]
    assert push.push() == 1006
    (folder / "stages" / "fusion.npz").unlink()  # a finished tile drops its bulky checkpoints
    (folder / "labels.npz").write_bytes(b"labels, again")
    assert push.push() == 13
    assert sorted(o.key for o in store.list_objects("jobs/j/")) == ["jobs/j/tiles/t/labels.npz"]
    assert store.get_bytes("jobs/j/tiles/t/labels.npz") == b"labels, again"


def test_prefix_delete(store: ObjectStorage) -> None:
    for key in ("x/s/1/a", "x/s/1/b/c", "x/s/2", "x/s1/kept"):
        store.put_bytes(key, b"v")
    upload = store.start_multipart("x/s/1/partial")
    store.put_part("x/s/1/partial", upload, 1, b"p")
    assert store.delete_prefix("x/s/1/") == 2
    assert [o.key for o in store.list_objects("x/s/")] == ["x/s/2"]
    assert store.stat("x/s1/kept") is not None  # a sibling that shares the prefix's letters is kept
    assert store.list_multipart("x/s/") == []  # the unfinished upload under it is aborted
    assert store.delete_prefix("x/s/1/") == 0


def test_signed_get(store: ObjectStorage) -> None:
    store.put_bytes("x/signed/file.ply", DATA)
    url = store.signed_url("x/signed/file.ply", 60)
    assert fetch_signed(store, url) == (200, DATA)
    tampered = url.replace("x/signed/file.ply", "x/signed/other.ply")
    assert fetch_signed(store, tampered)[0] == 403
    short = store.signed_url("x/signed/file.ply", 1)
    time.sleep(2.1)  # S3 signatures count whole seconds
    assert fetch_signed(store, short)[0] == 403


@pytest.mark.parametrize("key", ["../up", "/abs", "x//y", "x/./y", "", "x/y/", "x/ y"])
def test_keys_that_leave_the_root_are_refused(store: ObjectStorage, key: str) -> None:
    with pytest.raises(ValueError):
        store.put_bytes(key, b"no")


def test_s3_urls() -> None:
    assert parse_s3_url("s3://bucket") == ("bucket", "")
    assert parse_s3_url("s3://bucket/a/b/") == ("bucket", "a/b/")
    for bad in ("file:///tmp", "s3:///nobucket", "s3://b/../up"):
        with pytest.raises(ValueError):
            parse_s3_url(bad)


def test_s3_refuses_wrong_keys(seaweedfs_server: SeaweedFS) -> None:
    s3 = S3Storage(
        seaweedfs_server.url(),
        endpoint_url=seaweedfs_server.endpoint,
        access_key_id=seaweedfs_server.access_key,
        secret_access_key="wrong-" + seaweedfs_server.secret_key,
    )
    with pytest.raises(StorageError) as caught:
        s3.put_bytes("x/denied", b"no")
    assert not isinstance(caught.value, AlreadyExists)
