"""The storage a configuration names: S3 for ``PANOGS_STORAGE_URL=s3://...``, else the local folder."""

from __future__ import annotations

from service.settings import Settings
from service.storage import Storage
from service.storage.local import LocalStorage
from service.storage.objects import ObjectStorage


def open_objects(settings: Settings) -> ObjectStorage:
    """The object storage backend of ``settings`` (boto3 is imported only for S3)."""
    signing_key = settings.storage_signing_key.encode() if settings.storage_signing_key else None
    if not settings.storage_url:
        return LocalStorage(settings.storage, signing_key=signing_key)
    from service.storage.s3 import S3Storage

    return S3Storage(
        settings.storage_url,
        endpoint_url=settings.s3_endpoint_url,
        access_key_id=settings.s3_access_key_id,
        secret_access_key=settings.s3_secret_access_key,
        region=settings.s3_region,
        public_endpoint_url=settings.s3_public_endpoint_url,
    )


def open_storage(settings: Settings) -> Storage:
    """The service's storage: the local folder itself, or S3 with this process's work folder under the data dir."""
    objects = open_objects(settings)
    root = settings.storage if isinstance(objects, LocalStorage) else settings.data_dir
    return Storage(root, objects)
