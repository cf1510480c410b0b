"""The HTTP API: ``create_app()`` builds it (``symgs serve`` runs it with uvicorn).

This process never imports torch: it checks uploads by their headers, stores them, records
the job and queues its id; workers do the rest.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import redis.asyncio as aioredis
from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from api_schemas import JobEvent
from worker.gateway import JobStore, Settings, make_celery, storage_from_settings

from ..dashboard.routes import router as dashboard_router
from ..docs.routes import router as docs_router
from .allow import AllowedMethods
from .errors import install_handlers
from .metrics import make_registry
from .routes import events, jobs, ops, presets, results

log = logging.getLogger(__name__)
API_VERSION = "1.0.0"
DESCRIPTION = """\
Compression of 3D Gaussian Splatting scenes that removes reflective symmetry (SymGS).

Submit a trained scene (`.ply`, graphdeco layout or PlayCanvas compressed) and optionally the posed images it was
trained from; follow the job's progress; download the compressed archive, the decoded scene and the metrics.

When the server is configured with API keys, send one as `Authorization: Bearer <key>`; each job belongs to the key
that created it, and other keys get 404 for it. Errors are `{"error": {"code": "...", "message": "..."}}`.
"""


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if not settings.keys:
            log.warning("authentication is OFF (SYMGS_AUTH=none): anyone who reaches this API can use it")
        yield
        await app.state.aredis.aclose()
        app.state.store.r.close()

    app = FastAPI(
        title="SymGS",
        version=API_VERSION,
        description=DESCRIPTION,
        lifespan=lifespan,
        docs_url=None,  # FastAPI's pages load their scripts from a CDN: ours are served from shipped files
        redoc_url=None,
        swagger_ui_oauth2_redirect_url=None,
        openapi_tags=[
            {"name": "jobs", "description": "Submit, inspect, list, cancel and delete compression jobs"},
            {"name": "events", "description": "Live progress as Server-Sent Events"},
            {"name": "results", "description": "Archives, decoded scenes, reports and charts of finished jobs"},
            {"name": "operations", "description": "Health, readiness and metrics"},
        ],
    )
    store = JobStore.from_url(settings.redis_url)
    app.state.settings = settings
    app.state.store = store
    app.state.aredis = aioredis.Redis.from_url(settings.redis_url, decode_responses=True)
    app.state.storage = storage_from_settings(settings)
    app.state.celery = make_celery(settings)
    app.state.registry = make_registry(store, settings)
    install_handlers(app)
    app.add_middleware(AllowedMethods)
    for module in (jobs, presets, events, results, ops):
        app.include_router(module.router)
    app.include_router(dashboard_router)
    app.include_router(docs_router)
    app.openapi = lambda: _openapi(app)  # type: ignore[method-assign]
    return app


def _openapi(app: FastAPI) -> dict:
    """FastAPI's document, plus the schema of the SSE messages' data (JobEvent), which no JSON body references."""
    if app.openapi_schema is None:
        doc = get_openapi(
            title=app.title, version=app.version, description=app.description, routes=app.routes, tags=app.openapi_tags
        )
        schema = JobEvent.model_json_schema(ref_template="#/components/schemas/{model}")
        doc["components"]["schemas"]["JobEvent"] = schema
        stream = doc["paths"]["/v1/jobs/{job_id}/events"]["get"]["responses"]["200"]["content"]["text/event-stream"]
        stream["x-event-data"] = {"$ref": "#/components/schemas/JobEvent"}
        app.openapi_schema = doc
    return app.openapi_schema
