"""Objects as files under one folder: the embedded default's storage (``./panogs-data/storage``).

A key is a path below the root, so the layout on disk is the one the service always had (``uploads/<id>/data``,
``scenes/<id>/``, ``artifacts/<job id>/``). Every write goes to a file in ``.staging/`` first and is renamed into
place, so that a reader never sees half an object and a crash leaves only staging files (removed an hour later).
Multipart uploads keep their parts in ``.multipart/<upload id>/`` until they are joined. Signed links are
HMAC-SHA256 of the key and the expiry time with a secret (``PANOGS_STORAGE_SIGNING_KEY``, else one of the process);
the API serves them.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import secrets
import shutil
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import BinaryIO
from urllib.parse import parse_qs, quote, urlsplit

from service.storage.objects import (
    AlreadyExists,
    ObjectInfo,
    ObjectNotFound,
    Part,
    RangeNotSatisfiable,
    StorageError,
    check_key,
    check_part_number,
    check_parts,
)

BLOCK = 1 << 20
STAGING = ".staging"
MULTIPART = ".multipart"
RESERVED = (STAGING, MULTIPART)  # folders of the backend itself, never a key's first part
STALE_S = 3600.0  # a staging file this old belongs to a writer that died


class LocalStorage:
    """:class:`service.storage.objects.ObjectStorage` over a folder."""

    def __init__(self, root: Path, *, signing_key: bytes | None = None, link_base: str = "/v1/files") -> None:
        self.root = root.resolve()
        self.root.mkdir(parents=True, exist_ok=True)
        self._staging = self.root / STAGING
        self._staging.mkdir(exist_ok=True)
        _remove_stale(self._staging, STALE_S)  # what a crashed writer left (another process may be writing now)
        self._parts = self.root / MULTIPART
        self._signing_key = signing_key or secrets.token_bytes(32)
        self._link_base = link_base.rstrip("/")

    @property
    def url(self) -> str:
        return self.root.as_uri()

    def path(self, key: str) -> Path:
        """The file of ``key`` (which need not exist)."""
        check_key(key)
        if key.split("/", 1)[0] in RESERVED:
            raise ValueError(f"storage key {key!r} names a folder of the storage itself")
        return self.root / key

    def _folder(self, prefix: str) -> Path:
        check_key(prefix, prefix=True)
        return self.path(prefix[:-1])

    # Whole objects ----------------------------------------------------------------------------------------------

    def _stage(self) -> Path:
        return self._staging / uuid.uuid4().hex

    def _place(self, staged: Path, key: str, *, if_absent: bool = False) -> ObjectInfo:
        dest = self.path(key)
        dest.parent.mkdir(parents=True, exist_ok=True)
        try:
            if if_absent:
                try:
                    os.link(staged, dest)  # atomic: fails when the name exists, and the bytes are whole
                except FileExistsError:
                    raise AlreadyExists(f"{key}: an object exists under this key") from None
            else:
                os.replace(staged, dest)
        finally:
            staged.unlink(missing_ok=True)
        return self._info(key, dest)

    def put_bytes(self, key: str, data: bytes, *, if_absent: bool = False) -> ObjectInfo:
        self.path(key)
        staged = self._stage()
        with staged.open("wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        return self._place(staged, key, if_absent=if_absent)

    def put_file(self, key: str, path: Path) -> ObjectInfo:
        with path.open("rb") as f:
            return self.put_stream(key, f)

    def link_in(self, key: str, path: Path) -> ObjectInfo:
        """Keep the file at ``path`` as the object ``key`` without copying its bytes: a hard link, placed like any
        write (a copy where ``path`` is on another file system). For files that are only ever replaced by a rename,
        never written in place (the pipeline's checkpoints), since the two names share the bytes."""
        self.path(key)
        staged = self._stage()
        try:
            os.link(path, staged)
        except OSError:  # another file system, or links refused
            return self.put_file(key, path)
        with staged.open("rb") as f:
            os.fsync(f.fileno())  # durable as put_stream's copy would be
        return self._place(staged, key)

    def link_out(self, key: str, path: Path) -> ObjectInfo:
        """Give the object ``key`` a second name ``path`` (a hard link; a copy across file systems), replacing it
        whole; as :meth:`link_in`, for objects replaced only by a rename."""
        try:
            return self._copy_out(key, path, os.link)
        except FileNotFoundError:
            raise ObjectNotFound(key) from None
        except OSError:  # another file system, or links refused
            return self.get_file(key, path)

    def put_stream(self, key: str, stream: BinaryIO) -> ObjectInfo:
        self.path(key)
        staged = self._stage()
        with staged.open("wb") as f:
            shutil.copyfileobj(stream, f, BLOCK)
            f.flush()
            os.fsync(f.fileno())
        return self._place(staged, key)

    def get_bytes(self, key: str) -> bytes:
        try:
            return self.path(key).read_bytes()
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
            raise ObjectNotFound(key) from None

    def get_file(self, key: str, path: Path) -> ObjectInfo:
        return self._copy_out(key, path, shutil.copyfile)

    def _copy_out(self, key: str, path: Path, make: Callable[[Path, Path], object]) -> ObjectInfo:
        """``make(object file, temporary name)`` beside ``path``, then renamed over it: ``path`` is whole or as it
        was."""
        src = self.path(key)
        if not src.is_file():
            raise ObjectNotFound(key)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}")
        try:
            make(src, tmp)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        return self._info(key, src)

    def read_range(self, key: str, start: int = 0, end: int | None = None, *, block: int = BLOCK) -> Iterator[bytes]:
        src = self.path(key)
        try:
            f = src.open("rb")
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
            raise ObjectNotFound(key) from None
        size = os.fstat(f.fileno()).st_size
        if size and start >= size:
            f.close()
            raise RangeNotSatisfiable(key, start, size)
        stop = size if end is None else min(end, size)
        f.seek(start)
        return _blocks(f, stop - start, block)

    def stat(self, key: str) -> ObjectInfo | None:
        path = self.path(key)
        return self._info(key, path) if path.is_file() else None

    def _info(self, key: str, path: Path) -> ObjectInfo:
        st = path.stat()
        return ObjectInfo(key=key, size=st.st_size, etag=f"{st.st_size:x}-{st.st_mtime_ns:x}", modified=st.st_mtime)

    def list_objects(self, prefix: str) -> Iterator[ObjectInfo]:
        folder = self._folder(prefix)
        found: list[tuple[str, Path]] = []
        for dirpath, _dirs, files in os.walk(folder):
            for name in files:
                path = Path(dirpath) / name
                if not path.is_symlink():
                    found.append((path.relative_to(self.root).as_posix(), path))
        for key, path in sorted(found):
            yield self._info(key, path)

    def delete(self, key: str) -> None:
        path = self.path(key)
        try:
            path.unlink()
        except (FileNotFoundError, IsADirectoryError):
            return
        self._prune(path.parent)

    def _prune(self, folder: Path) -> None:
        """Remove empty folders up to the root (S3 has none: an object's folders go with its last object)."""
        while folder != self.root and folder.is_relative_to(self.root):
            try:
                folder.rmdir()
            except OSError:
                return
            folder = folder.parent

    def delete_prefix(self, prefix: str) -> int:
        folder = self._folder(prefix)
        count = sum(1 for _ in self.list_objects(prefix))
        shutil.rmtree(folder, ignore_errors=True)
        for key, upload_id in self.list_multipart(prefix):
            self.abort_multipart(key, upload_id)
        return count

    # Signed links -------------------------------------------------------------------------------------------------

    def _signature(self, key: str, expires: int) -> str:
        return hmac.new(self._signing_key, f"{key}\n{expires}".encode(), hashlib.sha256).hexdigest()

    def signed_url(self, key: str, expires_s: int) -> str:
        self.path(key)
        expires = int(time.time()) + expires_s
        return f"{self._link_base}/{quote(key)}?expires={expires}&signature={self._signature(key, expires)}"

    def verify_link(self, key: str, expires: int, signature: str) -> bool:
        """True when ``signature`` is this storage's for ``key`` until ``expires`` and that time has not passed."""
        if expires < time.time():
            return False
        return hmac.compare_digest(self._signature(key, expires), signature)

    def key_of_link(self, url: str) -> str | None:
        """The key a link of :meth:`signed_url` downloads, when its signature holds; None otherwise."""
        parts = urlsplit(url)
        if not parts.path.startswith(self._link_base + "/"):
            return None
        key = parts.path[len(self._link_base) + 1 :]
        query = parse_qs(parts.query)
        try:
            expires = int(query["expires"][0])
            signature = query["signature"][0]
        except (KeyError, ValueError, IndexError):
            return None
        return key if self.verify_link(key, expires, signature) else None

    # Multipart uploads ------------------------------------------------------------------------------------------

    def _upload_dir(self, key: str, upload_id: str) -> Path:
        folder = self._parts / check_key(upload_id)
        try:
            meta = json.loads((folder / "upload.json").read_text())
        except (FileNotFoundError, ValueError):
            raise ObjectNotFound(f"{key}: no multipart upload {upload_id}") from None
        if meta.get("key") != key:
            raise ObjectNotFound(f"{key}: multipart upload {upload_id} is for another key")
        return folder

    def start_multipart(self, key: str) -> str:
        self.path(key)
        upload_id = uuid.uuid4().hex
        folder = self._parts / upload_id
        folder.mkdir(parents=True)
        (folder / "upload.json").write_text(json.dumps({"key": key}))
        return upload_id

    def put_part(self, key: str, upload_id: str, number: int, data: bytes) -> Part:
        check_part_number(number)
        folder = self._upload_dir(key, upload_id)
        staged = self._stage()
        with staged.open("wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(staged, folder / f"{number:05d}")
        return Part(number=number, size=len(data), etag=hashlib.md5(data, usedforsecurity=False).hexdigest())

    def list_parts(self, key: str, upload_id: str) -> list[Part]:
        folder = self._upload_dir(key, upload_id)
        parts = []
        for path in sorted(folder.glob("[0-9]" * 5)):
            parts.append(Part(number=int(path.name), size=path.stat().st_size, etag=_md5_file(path)))
        return parts

    def complete_multipart(self, key: str, upload_id: str, parts: Iterable[Part]) -> ObjectInfo:
        folder = self._upload_dir(key, upload_id)
        stored = {p.number: p for p in self.list_parts(key, upload_id)}
        ordered = check_parts(key, list(parts))
        for part in ordered:
            if part.number not in stored or stored[part.number].etag != part.etag:
                raise StorageError(f"{key}: part {part.number} is not the one stored (InvalidPart)")
        staged = self._stage()
        with staged.open("wb") as out:
            for part in ordered:
                with (folder / f"{part.number:05d}").open("rb") as f:
                    shutil.copyfileobj(f, out, BLOCK)
            out.flush()
            os.fsync(out.fileno())
        info = self._place(staged, key)
        shutil.rmtree(folder, ignore_errors=True)
        return info

    def abort_multipart(self, key: str, upload_id: str) -> None:
        try:
            folder = self._upload_dir(key, upload_id)
        except ObjectNotFound:
            return
        shutil.rmtree(folder, ignore_errors=True)

    def list_multipart(self, prefix: str) -> list[tuple[str, str]]:
        check_key(prefix, prefix=True)
        found = []
        if self._parts.is_dir():
            for folder in sorted(self._parts.iterdir()):
                try:
                    key = json.loads((folder / "upload.json").read_text())["key"]
                except (FileNotFoundError, ValueError, KeyError):
                    continue
                if key.startswith(prefix):
                    found.append((key, folder.name))
        return found


def _remove_stale(folder: Path, age_s: float) -> None:
    cutoff = time.time() - age_s
    for path in folder.iterdir():
        try:
            if path.stat().st_mtime < cutoff:
                path.unlink()
        except OSError:
            continue


def _blocks(f: BinaryIO, remaining: int, block: int) -> Iterator[bytes]:
    with f:
        while remaining > 0:
            data = f.read(min(block, remaining))
            if not data:
                return
            remaining -= len(data)
            yield data


def _md5_file(path: Path) -> str:
    digest = hashlib.md5(usedforsecurity=False)
    with path.open("rb") as f:
        for data in iter(lambda: f.read(BLOCK), b""):
            digest.update(data)
    return digest.hexdigest()
