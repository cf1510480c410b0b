"""Who is calling, decided here alone: API keys as Bearer tokens (``SYMGS_API_KEYS``), each key's jobs its own and
invisible to the others; or no authentication at all, only when a deployment says so (``SYMGS_AUTH=none``)."""

from __future__ import annotations

import hashlib
import hmac
from typing import Annotated

from fastapi import Depends
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from worker.gateway import Settings

from .deps import SettingsDep
from .errors import ApiError

ANONYMOUS = "anonymous"  # the owner of every job where no keys are configured
_bearer = HTTPBearer(auto_error=False, description="an API key, when the server is configured with SYMGS_API_KEYS")


def owner_of(api_key: str | None) -> str:
    """The owner id of jobs created with an API key: a digest, so the key itself is never stored."""
    if not api_key:
        return ANONYMOUS
    return hashlib.sha256(api_key.encode()).hexdigest()[:24]


def refusal(settings: Settings) -> str | None:
    """Why the API must not serve with ``settings`` (None: it may): no keys, and not told to run open."""
    if not settings.keys and settings.auth != "none":
        return ("no API keys: set SYMGS_API_KEYS to comma-separated Bearer keys (e.g. SYMGS_API_KEYS=$(openssl rand "
                "-hex 24)), or SYMGS_AUTH=none to run without authentication")  # fmt: skip
    return None


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
