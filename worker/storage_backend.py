"""The storage a deployment's settings name: a directory that the API and every worker mount, or an S3 bucket."""

from __future__ import annotations

from .settings import Settings
from .storage import DirectoryStorage, Storage
from .storage_s3 import S3Storage


def storage_from_settings(settings: Settings) -> Storage:
    if settings.storage.startswith("s3://"):
        return S3Storage.from_url(settings.storage, cache=settings.cache_path)
    return DirectoryStorage(settings.storage)
