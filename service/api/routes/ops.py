"""Operations: liveness, readiness and Prometheus metrics."""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from pydantic import BaseModel, ConfigDict
from redis import RedisError

from api_schemas import QUEUES

from ..auth import OwnerDep
from ..deps import SettingsDep, StorageDep, StoreDep
from ..errors import error_responses

router = APIRouter(tags=["operations"])


class Health(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{"status": "ok"}]})

    status: Literal["ok"]


class Readiness(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [{"status": "ready", "redis": True, "storage": True, "workers": {"gpu": 0, "cpu": 2}}]
        }
    )

    status: Literal["ready", "not_ready"]
    redis: bool
    storage: bool
    workers: dict[str, int]


@router.get("/healthz", response_model=Health, summary="Liveness", description="The API process answers.")
def healthz() -> Health:
    return Health(status="ok")


@router.get(
    "/readyz",
    response_model=Readiness,
    summary="Readiness",
    description="Ready when Redis and the storage answer and at least one worker sent a heartbeat within one lease; "
    "503 otherwise.",
    responses={503: {"model": Readiness, "description": "Redis, the storage or every worker is unreachable"}},
)
def readyz(store: StoreDep, storage: StorageDep, settings: SettingsDep) -> JSONResponse:
    try:
        store.r.ping()
        workers = {mode: store.heartbeats.live(mode, settings.lease_seconds) for mode in QUEUES}
        redis_ok = True
    except RedisError:
        redis_ok, workers = False, {mode: 0 for mode in QUEUES}
    storage_ok = storage.reachable()
    ready = redis_ok and storage_ok and sum(workers.values()) > 0
    body = Readiness(status="ready" if ready else "not_ready", redis=redis_ok, storage=storage_ok, workers=workers)
    return JSONResponse(body.model_dump(), status_code=200 if ready else 503)


@router.get(
    "/metrics",
    summary="Prometheus metrics",
    description="symgs_jobs{state}, symgs_job_duration_seconds, symgs_queue_depth{queue}, symgs_workers{mode}. "
    "When the server has API keys, any of them (Prometheus sends it as `authorization: {credentials: ...}`).",
    response_class=Response,
    responses={
        200: {"content": {CONTENT_TYPE_LATEST: {"schema": {"type": "string"}}}, "description": "metrics"},
        **error_responses(401, 503),
    },
)
def metrics(request: Request, _: OwnerDep) -> Response:
    return Response(generate_latest(request.app.state.registry), media_type=CONTENT_TYPE_LATEST)
