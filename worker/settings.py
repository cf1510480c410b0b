"""Configuration of the API and the workers: one object, read from ``SYMGS_*`` environment variables."""

from __future__ import annotations

import tempfile
from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Everything the API and the workers read from the environment (prefix ``SYMGS_``).

    Both processes must see the same ``REDIS_URL`` and ``STORAGE``: the API writes uploads where the workers read
    them, and the workers write results where the API serves them.
    """

    model_config = SettingsConfigDict(env_prefix="SYMGS_", extra="ignore")

    redis_url: str = "redis://localhost:6379/0"
    storage: str = "./symgs-data"  # a directory shared by API and workers, or s3://bucket/prefix
    cache_dir: str = ""  # local scratch with s3:// storage (uploads on their way, jobs' inputs); "" = temp dir
    api_keys: str = ""  # comma-separated Bearer tokens; `symgs serve` refuses to start without any...
    auth: Literal["keys", "none"] = "keys"  # ...unless told to run open with "none"

    # Upload limits: sizes in bytes, counts in items.
    max_upload_bytes: int = Field(2 << 30, gt=0)
    max_gaussians: int = Field(10_000_000, gt=0)
    max_images: int = Field(2_000, ge=0)
    max_image_pixels: int = Field(4096 * 4096, gt=0)
    max_archive_entries: int = Field(20_000, gt=0)
    max_extracted_bytes: int = Field(8 << 30, gt=0)

    # The API's connections (``service.api.connections``): seconds a request's head may take to arrive whole, seconds
    # a body may stall while the server waits for it, and connections that may wait for their head at once.
    header_timeout: float = Field(10.0, gt=0)
    body_timeout: float = Field(60.0, gt=0)
    max_pending_connections: int = Field(256, ge=1)

    # Job lifetime and worker limits, in seconds.
    job_ttl: int = Field(7 * 24 * 3600, gt=0)  # finished jobs and their files are deleted this long after the end
    soft_time_limit: int = Field(6 * 3600, gt=0)  # the job fails with code time_limit
    hard_time_limit: int = Field(6 * 3600 + 300, gt=0)  # the worker process is killed
    lease_seconds: float = Field(30.0, gt=0)  # a running job whose worker stayed silent this long is re-queued
    max_attempts: int = Field(3, ge=1)  # runs of one job before it fails (worker_lost, storage_unavailable)
    maintenance_seconds: float = Field(10.0, gt=0)  # period of the worker's re-queue and expiry sweep
    # Seconds a job may spend running the peers' formats (splat-transform, when installed) on its upload, to draw
    # them in its charts; 0 turns that off.
    peer_seconds: float = Field(60.0, ge=0)

    @field_validator("storage")
    @classmethod
    def _storage(cls, value: str) -> str:
        if "://" in value:
            from .storage_s3 import parse_url

            try:
                parse_url(value)
            except ValueError as exc:
                raise ValueError(f"SYMGS_STORAGE must be a directory path or s3://bucket/prefix: {exc}") from None
        return value

    @model_validator(mode="after")
    def _auth(self) -> Settings:
        if self.auth == "none" and self.keys:
            raise ValueError("SYMGS_AUTH=none turns authentication off, but SYMGS_API_KEYS is set: unset one of them")
        return self

    @field_validator("hard_time_limit")
    @classmethod
    def _hard_after_soft(cls, value: int, info) -> int:  # noqa: ANN001 - pydantic ValidationInfo
        soft = info.data.get("soft_time_limit")
        if soft is not None and value <= soft:
            raise ValueError(f"SYMGS_HARD_TIME_LIMIT ({value}) must exceed SYMGS_SOFT_TIME_LIMIT ({soft})")
        return value

    @property
    def keys(self) -> list[str]:
        return [k.strip() for k in self.api_keys.split(",") if k.strip()]

    @property
    def cache_path(self) -> Path:
        return Path(self.cache_dir) if self.cache_dir else Path(tempfile.gettempdir()) / "symgs-cache"

    @property
    def visibility_timeout(self) -> int:
        """Seconds before Redis hands an unacknowledged job to another worker: longer than the longest job."""
        return 2 * self.hard_time_limit


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    return Settings()
