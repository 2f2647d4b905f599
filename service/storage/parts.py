"""tus uploads into an object storage that cannot append (S3): the bytes go up as the parts of one multipart upload.

S3 takes parts of at least 5 MiB (all but the last), and a tus client sends PATCHes of any size, so each PATCH's
bytes join a *tail* (what did not fill a part yet, at most :data:`PART_BYTES`), and every full part is sent while
the body still streams in (one part in flight at a time). What an upload holds at offset ``N`` is its
:class:`UploadState` (the multipart upload id, the parts sent with their tags, the tail's length), which the
database keeps in the upload's row and moves with the offset in one statement, and the tail's bytes, stored as the
immutable object ``tail-N`` before the offset moves (sent beside the last part). A PATCH that dies halfway leaves
the row and ``tail-<offset>`` of the offset the database still has untouched: the retry reads them and sends its
parts again (a part number sent again replaces the part). So a PATCH costs the parts it fills, one tail object and
the database's update, where it cost five or six requests one after the other when the state was an object too
(docs/benchmarks.md, "Uploads into S3"); the tail a PATCH follows is deleted in the background once the offset has
moved past it. The process keeps the last tail it stored (:class:`Tails`), so that the next PATCH reads it back
only when another API process took the previous one. When the last byte arrives the tail becomes the last part,
the parts are joined into ``uploads/<id>/data`` and every tail goes.

Memory stays flat: a PATCH holds at most the part in flight, the part it fills and one block, whatever the
upload's size.
"""

from __future__ import annotations

import hashlib
import json
import logging
import threading
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

from service.storage.files import sha256_object
from service.storage.objects import MIN_PART_BYTES, ObjectNotFound, ObjectStorage, Part, StorageError

logger = logging.getLogger(__name__)

# S3's smallest part: a PATCH that ends with at least this much buffered sends all of it as one part and stores no
# tail, so that a client's PATCHes of 5 MiB or more go up once each; below it the bytes wait as the tail, which
# is then under 5 MiB. While a body streams in, a part goes up each time MAX_PART_BYTES are buffered (memory per
# PATCH stays bounded; 10,000 parts of 5 MiB at least hold 48 GiB, three times PANOGS_MAX_UPLOAD_BYTES's default).
PART_BYTES = MIN_PART_BYTES
MAX_PART_BYTES = 16 * 1024 * 1024
TAILS_KEPT = 8  # tails of the last PATCHes kept in this process (each at most PART_BYTES)
# The requests sent beside a PATCH's body: its parts and its tail (one of each at a time per PATCH) and the
# deletes of tails done with; shared by the process's PATCHes.
SENDERS = ThreadPoolExecutor(max_workers=8, thread_name_prefix="upload-parts")


class Tails:
    """The tail each upload's last PATCH stored, kept in the API process, so that the next PATCH to reach the same
    process does not read it back from the storage (another process, or a restart, reads the stored one)."""

    def __init__(self, capacity: int = TAILS_KEPT) -> None:
        self._items: OrderedDict[str, tuple[int, bytes]] = OrderedDict()
        self._capacity = capacity
        self._lock = threading.Lock()

    def take(self, data_key: str, offset: int) -> bytes | None:
        with self._lock:
            hit = self._items.pop(data_key, None)
        return hit[1] if hit is not None and hit[0] == offset else None

    def put(self, data_key: str, offset: int, tail: bytes) -> None:
        with self._lock:
            self._items[data_key] = (offset, tail)
            while len(self._items) > self._capacity:
                self._items.popitem(last=False)


TAILS = Tails()  # one per process: the API's PATCHes share it


def _folder(data_key: str) -> str:
    return data_key.rsplit("/", 1)[0] + "/"


def state_key(data_key: str, offset: int) -> str:
    """Where an upload begun before the database kept its state stored the state at ``offset``."""
    return f"{_folder(data_key)}state-{offset}.json"


def tail_key(data_key: str, offset: int) -> str:
    return f"{_folder(data_key)}tail-{offset}"


@dataclass
class UploadState:
    """What an upload holds at ``offset``: a multipart upload, its parts so far, and the tail's length."""

    upload_id: str
    offset: int
    parts: list[Part] = field(default_factory=list)
    tail: int = 0
    previous: int | None = None  # the offset of the state this one followed (its tail goes once this one stands)

    def to_record(self) -> dict[str, Any]:
        """The upload row's ``multipart`` value."""
        parts = [[p.number, p.size, p.etag] for p in self.parts]
        return {"upload_id": self.upload_id, "offset": self.offset, "parts": parts, "tail": self.tail,
                "previous": self.previous}  # fmt: skip

    @classmethod
    def from_record(cls, raw: dict[str, Any]) -> UploadState:
        parts = [Part(number=int(n), size=int(s), etag=str(e)) for n, s, e in raw["parts"]]
        previous = raw.get("previous")
        return cls(upload_id=str(raw["upload_id"]), offset=int(raw["offset"]), parts=parts, tail=int(raw["tail"]),
                   previous=None if previous is None else int(previous))  # fmt: skip


def begin(objects: ObjectStorage, data_key: str) -> dict[str, Any]:
    """A new upload: its multipart upload; returns the state at offset 0 for the upload's row."""
    return UploadState(upload_id=objects.start_multipart(data_key), offset=0).to_record()


def read_state(objects: ObjectStorage, data_key: str, offset: int, record: dict[str, Any] | None) -> UploadState:
    """The state at the database's ``offset``: the row's ``record``, or for an upload begun before the row kept
    it, the state object of that offset."""
    if record is not None:
        state = UploadState.from_record(record)
        if state.offset != offset:
            raise StorageError(f"{data_key}: the upload's state is at offset {state.offset}, its row at {offset}")
        return state
    try:
        return UploadState.from_record(json.loads(objects.get_bytes(state_key(data_key, offset))))
    except ObjectNotFound:
        raise ObjectNotFound(f"{data_key}: no upload state at offset {offset}") from None


def forget_other_states(objects: ObjectStorage, data_key: str, offset: int) -> None:
    """Delete the tails (and state objects) of every offset but ``offset`` (earlier ones, and the later one of a
    PATCH that died before the database moved; -1: all of them, once the upload is joined)."""
    keep = {state_key(data_key, offset), tail_key(data_key, offset), data_key}
    for info in objects.list_objects(_folder(data_key)):
        if info.key not in keep:
            objects.delete(info.key)


def _delete_quietly(objects: ObjectStorage, key: str) -> None:
    try:
        objects.delete(key)
    except StorageError:  # left for the sweep when the upload is joined or deleted
        logger.info("%s: not deleted now; the upload's end deletes it", key, exc_info=True)


class PartWriter:
    """One PATCH body into the parts of an upload; the :class:`service.storage.chunks.ChunkWriter` of S3.

    ``write`` is fed the request's chunks and sends each full part from a thread while the next fills; ``close``
    stores the tail and returns the new offset, whose state :meth:`record` gives for the row; ``finish`` (after
    the last byte) joins the parts. ``rollback`` keeps nothing of this PATCH.
    """

    def __init__(
        self,
        objects: ObjectStorage,
        data_key: str,
        offset: int,
        record: dict[str, Any] | None,
        running: Any,
        chunk_algo: str | None,
    ) -> None:
        self.objects = objects
        self.key = data_key
        self.start = offset
        self.offset = offset
        self.running = running  # the whole upload's SHA-256 so far, or None (rebuilt from the object at the end)
        self.chunk_hash = hashlib.new(chunk_algo) if chunk_algo else None
        self.state = read_state(objects, data_key, offset, record)
        if self.state.previous is not None:  # the database is at this state: the tail before it is done with
            SENDERS.submit(_delete_quietly, objects, tail_key(data_key, self.state.previous))
            if record is None:
                SENDERS.submit(_delete_quietly, objects, state_key(data_key, self.state.previous))
        kept = TAILS.take(data_key, offset) if self.state.tail else b""
        if kept is None or len(kept) != self.state.tail:
            kept = objects.get_bytes(tail_key(data_key, offset))
        self.buffer = bytearray(kept)
        self._sending: Future[Part] | None = None

    def write(self, data: bytes | bytearray) -> None:
        """Add ``data``; send a part each time :data:`MAX_PART_BYTES` are buffered (the part before must have gone:
        one in flight)."""
        self.buffer += data
        if self.running is not None:
            self.running.update(data)
        if self.chunk_hash is not None:
            self.chunk_hash.update(data)
        self.offset += len(data)
        if len(self.buffer) >= MAX_PART_BYTES:
            self._send(bytes(self.buffer))
            self.buffer = bytearray()

    def _send(self, data: bytes) -> None:
        self._sent()
        number = len(self.state.parts) + 1
        self._sending = SENDERS.submit(self.objects.put_part, self.key, self.state.upload_id, number, data)

    def _sent(self) -> None:
        """Wait for the part in flight and add it to the state (raises what sending it raised)."""
        sending, self._sending = self._sending, None
        if sending is not None:
            self.state.parts.append(sending.result())

    def close(self) -> int:
        """Send what is buffered as a part when it is one (then no tail), else store it as the tail beside the part
        in flight; wait for both; returns the new offset."""
        if len(self.buffer) >= PART_BYTES:
            self._send(bytes(self.buffer))
            self.buffer = bytearray()
        if self.offset != self.start:
            self.state.previous, self.state.offset = self.start, self.offset
            self.state.tail = len(self.buffer)
            storing = None
            if self.buffer:
                tail = bytes(self.buffer)
                storing = SENDERS.submit(self.objects.put_bytes, tail_key(self.key, self.offset), tail)
            try:
                self._sent()
            finally:
                if storing is not None:
                    storing.result()
            if self.buffer:
                TAILS.put(self.key, self.offset, bytes(self.buffer))
        return self.offset

    def record(self) -> dict[str, Any]:
        """The state after :meth:`close`, for the upload's row."""
        return self.state.to_record()

    def finish(self) -> str | None:
        """Join the parts into the upload's object; returns the SHA-256 (hex) when known.

        The tails stay until the database has the upload complete (``uploads.record_bytes`` drops them).
        """
        self._sent()
        if not self.state.parts:  # under one part in all: one plain object, no multipart upload needed
            self.objects.put_bytes(self.key, bytes(self.buffer))
            self.objects.abort_multipart(self.key, self.state.upload_id)
        else:
            if self.buffer:
                self.state.parts.append(
                    self.objects.put_part(self.key, self.state.upload_id, len(self.state.parts) + 1, bytes(self.buffer))
                )
            self.objects.complete_multipart(self.key, self.state.upload_id, self.state.parts)
        self.buffer = bytearray()
        return self.running.hexdigest() if self.running is not None else None

    def settle(self, length: int) -> tuple[Any, dict[str, Any] | None]:
        """After :meth:`close`: the running hash (once the last byte is in, the parts are joined and the hash is the
        upload's, made from the joined object when none was kept) and the state for the upload's row."""
        running = self.running
        if self.offset == length:
            digest = self.finish()
            running = _Digest(digest or sha256_object(self.objects, self.key).hexdigest())
        return running, self.record()

    def rollback(self) -> None:
        """Discard this PATCH: the state at its start offset still stands (parts it sent are sent again later).
        A part still in flight is waited for, so that it cannot land after the retry's part of the same number."""
        sending, self._sending = self._sending, None
        if sending is not None:
            try:
                sending.result()
            except StorageError:
                pass
        self.buffer = bytearray()
        self.offset = self.start


class _Digest:
    """A finished hash, as ``uploads.record_bytes`` reads one."""

    def __init__(self, hexdigest: str) -> None:
        self._hex = hexdigest

    def hexdigest(self) -> str:
        return self._hex
