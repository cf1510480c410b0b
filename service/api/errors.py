"""API errors: every 4xx/5xx answer is ``{"error": {"code": "...", "message": "..."}}``."""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from redis import RedisError
from starlette.exceptions import HTTPException as StarletteHTTPException

from api_schemas import ErrorResponse
from worker.gateway import StorageError

log = logging.getLogger(__name__)


class ApiError(Exception):
    """An answer other than success: HTTP status, machine-readable code, message, optional headers."""

    def __init__(self, status: int, code: str, message: str, headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.status, self.code, self.message, self.headers = status, code, message, headers


def not_found(job_id: str) -> ApiError:
    return ApiError(404, "not_found", f"no job {job_id}")


def error_body(code: str, message: str) -> dict:
    return {"error": {"code": code, "message": message}}


def error_responses(*statuses: int) -> dict[int | str, dict]:
    """OpenAPI entries of the error answers a route gives."""
    what = {
        401: "missing or unknown API key",
        404: "no such job (or it belongs to another API key)",
        409: "the job is not in a state that allows this",
        413: "the upload exceeds a limit",
        422: "the request is invalid",
        503: "Redis, the workers or the object storage are not reachable",
    }
    return {s: {"model": ErrorResponse, "description": what[s]} for s in statuses}


_STATUS_CODES = {
    400: "bad_request", 401: "unauthorized", 403: "forbidden", 404: "not_found", 405: "method_not_allowed",
    406: "not_acceptable", 409: "conflict", 413: "too_large", 415: "unsupported_media_type", 422: "invalid",
    429: "too_many_requests",
}  # fmt: skip


def install_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api_error(_: Request, exc: ApiError) -> JSONResponse:
        return JSONResponse(error_body(exc.code, exc.message), status_code=exc.status, headers=exc.headers)

    @app.exception_handler(StorageError)
    async def _storage(_: Request, exc: StorageError) -> JSONResponse:
        log.warning("storage failed: %s", exc)
        return JSONResponse(
            error_body("storage_unavailable", "the artifact storage is not reachable; try again"),
            status_code=503, headers={"Retry-After": "5"},
        )  # fmt: skip
    @app.exception_handler(RedisError)
    async def _redis_down(_: Request, exc: RedisError) -> JSONResponse:
        # Redis holds every job: while it is out of reach nothing can be read or accepted, so say so and when to retry.
        message = f"the job store is not reachable ({type(exc).__name__}); try again"
        return JSONResponse(error_body("unavailable", message), status_code=503, headers={"Retry-After": "5"})

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        parts = [f"{'.'.join(str(x) for x in e['loc'])}: {e['msg']}" for e in exc.errors()]
        return JSONResponse(error_body("invalid_request", "; ".join(parts)), status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = _STATUS_CODES.get(exc.status_code, "error")
        return JSONResponse(
            error_body(code, str(exc.detail)), status_code=exc.status_code, headers=getattr(exc, "headers", None)
        )
