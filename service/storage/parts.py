"""tus uploads into an object storage that cannot append (S3): the bytes go up as the parts of one multipart upload.

S3 takes parts of at least 5 MiB (all but the last), and a tus client sends PATCHes of any size, so each PATCH's
bytes join a *tail* (what did not fill a part yet, at most :data:`PART_BYTES`), and every full part is sent at
once; the process keeps the last tail it stored (:class:`Tails`), so that the next PATCH reads it back only
when another API process took the previous one. What an upload holds at offset ``N`` is written, before the
database's offset moves to ``N``, as two immutable objects named by that offset: ``state-N.json`` (the multipart
upload id, the parts sent with their tags, the offset of the state before) and ``tail-N`` (the tail's bytes). A
PATCH that dies halfway leaves the state of the offset the database still has untouched: the retry reads it and
sends its parts again (a part number sent again replaces the part). The next PATCH deletes the state before the
database's; when the last byte arrives the tail becomes the last part, the parts are joined into
``uploads/<id>/data`` and every state goes.

Memory stays flat: a PATCH holds at most one part and one block in memory, whatever the upload's size.
"""

from __future__ import annotations

import hashlib
import json
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

from service.storage.objects import MIN_PART_BYTES, ObjectNotFound, ObjectStorage, Part

# S3's smallest part: the tail a PATCH stores and the next one reads is then at most 5 MiB (10,000 parts hold
# 48 GiB, three times PANOGS_MAX_UPLOAD_BYTES's default).
PART_BYTES = MIN_PART_BYTES
TAILS_KEPT = 8  # tails of the last PATCHes kept in this process (each at most PART_BYTES)


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
    previous: int | None = None  # the offset of the state this one followed (deleted once this one is the database's)

    def to_json(self) -> bytes:
        parts = [[p.number, p.size, p.etag] for p in self.parts]
        raw = {"upload_id": self.upload_id, "offset": self.offset, "parts": parts, "tail": self.tail,
               "previous": self.previous}  # fmt: skip
        return json.dumps(raw).encode()

    @classmethod
    def from_json(cls, data: bytes) -> UploadState:
        raw = json.loads(data)
        parts = [Part(number=int(n), size=int(s), etag=str(e)) for n, s, e in raw["parts"]]
        previous = raw.get("previous")
        return cls(upload_id=str(raw["upload_id"]), offset=int(raw["offset"]), parts=parts, tail=int(raw["tail"]),
                   previous=None if previous is None else int(previous))  # fmt: skip


def begin(objects: ObjectStorage, data_key: str) -> None:
    """A new upload: its multipart upload and the state at offset 0."""
    state = UploadState(upload_id=objects.start_multipart(data_key), offset=0)
    objects.put_bytes(state_key(data_key, 0), state.to_json())


def read_state(objects: ObjectStorage, data_key: str, offset: int) -> UploadState:
    """The state the database's ``offset`` names."""
    try:
        return UploadState.from_json(objects.get_bytes(state_key(data_key, offset)))
    except ObjectNotFound:
        raise ObjectNotFound(f"{data_key}: no upload state at offset {offset}") from None


def forget_other_states(objects: ObjectStorage, data_key: str, offset: int) -> None:
    """Delete the states and tails of every offset but ``offset`` (earlier ones, and the later one of a PATCH that
    died before the database moved; -1: all of them, once the upload is joined)."""
    keep = {state_key(data_key, offset), tail_key(data_key, offset), data_key}
    for info in objects.list_objects(_folder(data_key)):
        if info.key not in keep:
            objects.delete(info.key)


class PartWriter:
    """One PATCH body into the parts of an upload; the :class:`service.storage.ChunkWriter` of S3.

    ``write`` is fed the request's chunks, ``close`` stores the tail and the new state and returns the new
    offset; ``finish`` (after the last byte) joins the parts. ``rollback`` keeps nothing of this PATCH.
    """

    def __init__(
        self, objects: ObjectStorage, data_key: str, offset: int, running: Any, chunk_algo: str | None
    ) -> None:
        self.objects = objects
        self.key = data_key
        self.start = offset
        self.offset = offset
        self.running = running  # the whole upload's SHA-256 so far, or None (rebuilt from the object at the end)
        self.chunk_hash = hashlib.new(chunk_algo) if chunk_algo else None
        self.state = read_state(objects, data_key, offset)
        if self.state.previous is not None:  # the database is at this state: the one before it is done with
            objects.delete(state_key(data_key, self.state.previous))
            objects.delete(tail_key(data_key, self.state.previous))
        kept = TAILS.take(data_key, offset) if self.state.tail else b""
        if kept is None or len(kept) != self.state.tail:
            kept = objects.get_bytes(tail_key(data_key, offset))
        self.buffer = bytearray(kept)

    def write(self, data: bytes | bytearray) -> None:
        """Add ``data``; send every full part."""
        self.buffer += data
        if self.running is not None:
            self.running.update(data)
        if self.chunk_hash is not None:
            self.chunk_hash.update(data)
        self.offset += len(data)
        while len(self.buffer) >= PART_BYTES:
            self._send(bytes(self.buffer[:PART_BYTES]))
            del self.buffer[:PART_BYTES]

    def _send(self, data: bytes) -> None:
        number = len(self.state.parts) + 1
        self.state.parts.append(self.objects.put_part(self.key, self.state.upload_id, number, data))

    def close(self) -> int:
        """Store the tail and the state at the new offset; returns it."""
        if self.offset != self.start:
            self.state.previous, self.state.offset = self.start, self.offset
            self.state.tail = len(self.buffer)
            if self.buffer:
                tail = bytes(self.buffer)
                self.objects.put_bytes(tail_key(self.key, self.offset), tail)
                TAILS.put(self.key, self.offset, tail)
            self.objects.put_bytes(state_key(self.key, self.offset), self.state.to_json())
        return self.offset

    def finish(self) -> str | None:
        """Join the parts into the upload's object; returns the SHA-256 (hex) when known.

        The states stay until the database has the upload complete (``uploads.record_bytes`` drops them).
        """
        if not self.state.parts:  # under one part in all: one plain object, no multipart upload needed
            self.objects.put_bytes(self.key, bytes(self.buffer))
            self.objects.abort_multipart(self.key, self.state.upload_id)
        else:
            if self.buffer:
                self._send(bytes(self.buffer))
            self.objects.complete_multipart(self.key, self.state.upload_id, self.state.parts)
        self.buffer = bytearray()
        return self.running.hexdigest() if self.running is not None else None

    def rollback(self) -> None:
        """Discard this PATCH: the state at its start offset still stands (parts it sent are sent again later)."""
        self.buffer = bytearray()
        self.offset = self.start
