"""What routes depend on: settings, the job store, storage, the Celery app, and the caller's identity."""

from __future__ import annotations

import hmac
from typing import Annotated

from celery import Celery
from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from worker.settings import Settings
from worker.storage import Storage
from worker.store import JobStore, owner_of

from .errors import ApiError

_bearer = HTTPBearer(auto_error=False, description="an API key, when the server is configured with SYMGS_API_KEYS")


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_store(request: Request) -> JobStore:
    return request.app.state.store


def get_storage(request: Request) -> Storage:
    return request.app.state.storage


def get_celery(request: Request) -> Celery:
    return request.app.state.celery


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[JobStore, Depends(get_store)]
StorageDep = Annotated[Storage, Depends(get_storage)]
CeleryDep = Annotated[Celery, Depends(get_celery)]


def authenticate(
    settings: SettingsDep, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> str:
    """The owner id of the caller: from its Bearer API key, or ``anonymous`` when no keys are configured."""
    keys = settings.keys
    if not keys:
        return owner_of(None)
    token = credentials.credentials if credentials is not None else ""
    # Compare against every key, so the time taken does not tell which prefix matched.
    matched = [key for key in keys if hmac.compare_digest(key.encode(), token.encode())]
    if not matched:
        raise ApiError(401, "unauthorized", "a valid API key is required", headers={"WWW-Authenticate": "Bearer"})
    return owner_of(matched[0])


OwnerDep = Annotated[str, Depends(authenticate)]
