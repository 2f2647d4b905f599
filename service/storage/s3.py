"""Objects in an S3 bucket through boto3: the storage of deployments on several hosts (``PANOGS_STORAGE_URL``).

``s3://bucket/prefix`` with ``PANOGS_S3_ENDPOINT_URL`` (SeaweedFS, MinIO, or empty for AWS itself) and the keys
``PANOGS_S3_ACCESS_KEY_ID`` / ``PANOGS_S3_SECRET_ACCESS_KEY``. Every call is synchronous (boto3 is); the API calls
them from a worker thread. Files go up and down streamed, in parts above :data:`TRANSFER_CHUNK` (s3transfer),
ranges are ``GET`` with ``Range`` (206), conditional creates are ``PUT`` with ``If-None-Match: *`` (412 when the key
exists). botocore retries what it knows to be transient (``standard`` mode: connection errors, 5xx, throttling)
:data:`RETRY_ATTEMPTS` times with exponential backoff; what still fails that way is :class:`StorageUnavailable`,
anything else (refused keys, a missing bucket, a malformed request) :class:`StorageError`.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, BinaryIO, TypeVar
from urllib.parse import urlsplit

import boto3
from boto3.s3.transfer import TransferConfig
from botocore.config import Config
from botocore.exceptions import BotoCoreError, ClientError, ConnectionError, HTTPClientError

from service.storage.objects import (
    AlreadyExists,
    ObjectInfo,
    ObjectNotFound,
    Part,
    RangeNotSatisfiable,
    StorageError,
    StorageUnavailable,
    check_key,
    check_part_number,
    check_parts,
)

T = TypeVar("T")
TRANSFER_CHUNK = 16 * 1024 * 1024  # put_file / get_file go in parts of this size above it
RETRY_ATTEMPTS = 5  # botocore's own retries of a transient failure (standard mode: backoff up to 20 s)
_NOT_FOUND = {"NoSuchKey", "NotFound", "404", "NoSuchUpload"}
_TRANSIENT = {"SlowDown", "ServiceUnavailable", "InternalError", "RequestTimeout", "503", "500", "502", "504"}


def parse_s3_url(url: str) -> tuple[str, str]:
    """``s3://bucket/some/prefix`` -> ``("bucket", "some/prefix/")`` (the prefix empty or ending with ``/``)."""
    parts = urlsplit(url)
    if parts.scheme != "s3" or not parts.netloc:
        raise ValueError(f"storage URL {url!r} is not s3://bucket[/prefix]")
    prefix = parts.path.strip("/")
    if prefix:
        check_key(prefix + "/", prefix=True)
    return parts.netloc, f"{prefix}/" if prefix else ""


class S3Storage:
    """:class:`service.storage.objects.ObjectStorage` over one bucket and key prefix."""

    def __init__(
        self,
        url: str,
        *,
        endpoint_url: str | None = None,
        access_key_id: str | None = None,
        secret_access_key: str | None = None,
        region: str = "us-east-1",
        connect_timeout_s: float = 5.0,
        read_timeout_s: float = 60.0,
        public_endpoint_url: str | None = None,
    ) -> None:
        self.bucket, self.prefix = parse_s3_url(url)
        self._url = url
        config = Config(
            region_name=region,
            s3={"addressing_style": "path"},  # SeaweedFS and MinIO serve buckets as paths, not host names
            retries={"mode": "standard", "max_attempts": RETRY_ATTEMPTS},
            connect_timeout=connect_timeout_s,
            read_timeout=read_timeout_s,
            signature_version="s3v4",
            request_checksum_calculation="when_required",  # S3-compatible servers reject the newer default trailers
            response_checksum_validation="when_required",
        )
        session = boto3.session.Session()  # sessions are not thread-safe; the client made from one is

        def client_for(endpoint: str | None) -> Any:
            return session.client("s3", endpoint_url=endpoint or None, aws_access_key_id=access_key_id,
                                  aws_secret_access_key=secret_access_key, config=config)  # fmt: skip

        self.client = client_for(endpoint_url)
        # Links for clients are signed for the address they reach the server at (the signature covers the host):
        # the public endpoint when one is given, else AWS itself; None where only this network reaches the server.
        self.public_signer = client_for(public_endpoint_url) if public_endpoint_url or not endpoint_url else None
        self._transfer = TransferConfig(
            multipart_threshold=TRANSFER_CHUNK, multipart_chunksize=TRANSFER_CHUNK, max_concurrency=4
        )

    @property
    def url(self) -> str:
        return self._url

    def _key(self, key: str, *, prefix: bool = False) -> str:
        return self.prefix + check_key(key, prefix=prefix)

    def _call(self, what: str, fn: Callable[..., T], **kwargs: Any) -> T:
        """``fn(**kwargs)`` with boto's errors turned into the storage's."""
        try:
            return fn(**kwargs)
        except ClientError as exc:
            raise _translate(exc, what) from exc
        except (ConnectionError, HTTPClientError) as exc:
            raise StorageUnavailable(f"{what}: the object storage did not answer ({type(exc).__name__})") from exc
        except BotoCoreError as exc:
            raise StorageError(f"{what}: {type(exc).__name__}: {exc}") from exc

    def _on_key(self, what: str, fn: Callable[..., T], key: str, **kwargs: Any) -> T:
        """``fn`` on the object ``key`` of this bucket (``Bucket`` and the full ``Key`` given), through ``_call``."""
        return self._call(what, fn, Bucket=self.bucket, Key=self._key(key), **kwargs)

    # Whole objects ----------------------------------------------------------------------------------------------

    def put_bytes(self, key: str, data: bytes, *, if_absent: bool = False) -> ObjectInfo:
        extra = {"IfNoneMatch": "*"} if if_absent else {}
        answer = self._on_key(f"put {key}", self.client.put_object, key, Body=data, **extra)
        return ObjectInfo(key=key, size=len(data), etag=_etag(answer))

    def put_file(self, key: str, path: Path) -> ObjectInfo:
        self._on_key(f"upload {key}", self.client.upload_file, key, Filename=str(path), Config=self._transfer)
        return self._head(key)

    def put_stream(self, key: str, stream: BinaryIO) -> ObjectInfo:
        self._on_key(f"upload {key}", self.client.upload_fileobj, key, Fileobj=stream, Config=self._transfer)
        return self._head(key)

    def get_bytes(self, key: str) -> bytes:
        answer = self._on_key(f"get {key}", self.client.get_object, key)
        with answer["Body"] as body:
            return bytes(self._call(f"read {key}", body.read))

    def get_file(self, key: str, path: Path) -> ObjectInfo:
        info = self._head(key)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}")
        try:
            self._on_key(f"download {key}", self.client.download_file, key, Filename=str(tmp), Config=self._transfer)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        return info

    def read_range(self, key: str, start: int = 0, end: int | None = None, *, block: int = 1 << 20) -> Iterator[bytes]:
        if end is not None and end <= start:
            info = self._head(key)
            if info.size and start >= info.size:
                raise RangeNotSatisfiable(key, start, info.size)
            return iter(())
        extra = {}
        if start > 0 or end is not None:
            extra["Range"] = f"bytes={start}-{'' if end is None else end - 1}"
        try:
            answer = self._on_key(f"get {key}", self.client.get_object, key, **extra)
        except _RangeRefused:
            raise RangeNotSatisfiable(key, start, self._head(key).size) from None
        return _stream(answer["Body"], block, f"read {key}")

    def _head(self, key: str) -> ObjectInfo:
        answer = self._on_key(f"head {key}", self.client.head_object, key)
        return ObjectInfo(key=key, size=int(answer["ContentLength"]), etag=_etag(answer))

    def stat(self, key: str) -> ObjectInfo | None:
        try:
            return self._head(key)
        except ObjectNotFound:
            return None

    def list_objects(self, prefix: str) -> Iterator[ObjectInfo]:
        full = self._key(prefix, prefix=True)
        pages = self.client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=full)
        for page in self._call(f"list {prefix}", lambda: list(pages)):
            for item in page.get("Contents", []):
                modified = item["LastModified"].timestamp() if "LastModified" in item else 0.0
                key = item["Key"][len(self.prefix) :]
                yield ObjectInfo(key=key, size=int(item["Size"]), etag=_etag(item), modified=modified)

    def delete(self, key: str) -> None:
        try:
            self._on_key(f"delete {key}", self.client.delete_object, key)
        except ObjectNotFound:
            return

    def delete_prefix(self, prefix: str) -> int:
        keys = [self.prefix + info.key for info in self.list_objects(prefix)]
        for i in range(0, len(keys), 1000):  # DeleteObjects takes at most 1,000 keys
            batch = {"Objects": [{"Key": k} for k in keys[i : i + 1000]], "Quiet": True}
            answer = self._call(f"delete {prefix}", self.client.delete_objects, Bucket=self.bucket, Delete=batch)
            if answer.get("Errors"):
                first = answer["Errors"][0]
                raise StorageError(f"delete {prefix}: {len(answer['Errors'])} keys refused, first {first}")
        for key, upload_id in self.list_multipart(prefix):
            self.abort_multipart(key, upload_id)
        return len(keys)

    def signed_url(self, key: str, expires_s: int) -> str:
        params = {"Bucket": self.bucket, "Key": self._key(key)}
        return str(self._call(f"sign {key}", self.client.generate_presigned_url, ClientMethod="get_object",
                              Params=params, ExpiresIn=expires_s))  # fmt: skip

    def public_url(self, key: str, expires_s: int) -> str | None:
        """A link that downloads the object from where the API's clients are (the public endpoint, or AWS), or None
        when the server is reachable only from the service's own network."""
        if self.public_signer is None:
            return None
        params = {"Bucket": self.bucket, "Key": self._key(key)}
        return str(self._call(f"sign {key}", self.public_signer.generate_presigned_url, ClientMethod="get_object",
                              Params=params, ExpiresIn=expires_s))  # fmt: skip

    # Multipart uploads ------------------------------------------------------------------------------------------

    def start_multipart(self, key: str) -> str:
        answer = self._on_key(f"start upload {key}", self.client.create_multipart_upload, key)
        return str(answer["UploadId"])

    def put_part(self, key: str, upload_id: str, number: int, data: bytes) -> Part:
        check_part_number(number)
        answer = self._on_key(
            f"upload part {number} of {key}",
            self.client.upload_part,
            key,
            UploadId=upload_id,
            PartNumber=number,
            Body=data,
        )
        return Part(number=number, size=len(data), etag=_etag(answer))

    def list_parts(self, key: str, upload_id: str) -> list[Part]:
        pages = self.client.get_paginator("list_parts").paginate(
            Bucket=self.bucket, Key=self._key(key), UploadId=upload_id
        )
        latest: dict[int, tuple[Any, Part]] = {}
        for page in self._call(f"list parts of {key}", lambda: list(pages)):
            for item in page.get("Parts", []):
                part = Part(number=int(item["PartNumber"]), size=int(item["Size"]), etag=_etag(item))
                # SeaweedFS lists a part sent twice under both versions; the later one is the part
                seen = latest.get(part.number)
                if seen is None or item.get("LastModified") >= seen[0]:
                    latest[part.number] = (item.get("LastModified"), part)
        return [latest[n][1] for n in sorted(latest)]

    def complete_multipart(self, key: str, upload_id: str, parts: Iterable[Part]) -> ObjectInfo:
        ordered = check_parts(key, list(parts))
        body = {"Parts": [{"PartNumber": p.number, "ETag": f'"{p.etag}"'} for p in ordered]}
        self._on_key(
            f"complete upload {key}",
            self.client.complete_multipart_upload,
            key,
            UploadId=upload_id,
            MultipartUpload=body,
        )
        return self._head(key)

    def abort_multipart(self, key: str, upload_id: str) -> None:
        try:
            self._on_key(f"abort upload {key}", self.client.abort_multipart_upload, key, UploadId=upload_id)
        except ObjectNotFound:
            return

    def list_multipart(self, prefix: str) -> list[tuple[str, str]]:
        full = self._key(prefix, prefix=True)
        pages = self.client.get_paginator("list_multipart_uploads").paginate(Bucket=self.bucket, Prefix=full)
        found = []
        for page in self._call(f"list uploads under {prefix}", lambda: list(pages)):
            for item in page.get("Uploads", []):
                found.append((item["Key"][len(self.prefix) :], str(item["UploadId"])))
        return found


class _RangeRefused(StorageError):
    """S3's 416 InvalidRange, before the object's size is known."""


def _translate(exc: ClientError, what: str) -> StorageError:
    error = exc.response.get("Error", {})
    code = str(error.get("Code", ""))
    status = int(exc.response.get("ResponseMetadata", {}).get("HTTPStatusCode", 0) or 0)
    message = f"{what}: {code or status}: {error.get('Message', '')}".rstrip(": ")
    if code in _NOT_FOUND or status == 404:
        return ObjectNotFound(message)
    if code == "InvalidRange" or status == 416:
        return _RangeRefused(message)
    if code == "PreconditionFailed" or status == 412:
        return AlreadyExists(message)
    if code in _TRANSIENT or status >= 500:
        return StorageUnavailable(message)
    return StorageError(message)


def _etag(answer: Any) -> str:
    return str(answer.get("ETag", "")).strip('"')


def _stream(body: Any, block: int, what: str) -> Iterator[bytes]:
    with body:
        try:
            yield from body.iter_chunks(block)
        except (ConnectionError, HTTPClientError, BotoCoreError) as exc:
            raise StorageUnavailable(f"{what}: the object storage stopped answering ({type(exc).__name__})") from exc
