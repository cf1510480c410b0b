"""``/v1/jobs``: create, read, list, cancel and delete compression jobs."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header, Query, Request, Response
from fastapi.responses import JSONResponse
from starlette.convertors import StringConvertor, register_url_convertor

from api_schemas import Job, JobPage, JobState
from worker.gateway import JobRecord, JobStore, Settings

from ..auth import OwnerDep
from ..deps import CeleryDep, SettingsDep, StorageDep, StoreDep
from ..errors import ApiError, error_responses
from ..job_view import job_headers, owned_record, public_job
from ..submission import submit

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])


class JobIdConvertor(StringConvertor):
    """A job id in a path: no ':' (so ``/v1/jobs/{id}:cancel`` is never read as the job ``{id}:cancel``)."""

    regex = "[^/:]+"


register_url_convertor("job_id", JobIdConvertor())

_MULTIPART = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["scene"],
                    "properties": {
                        "scene": {"type": "string", "format": "binary", "description": "the scene, graphdeco .ply"},
                        "images": {
                            "type": "string",
                            "format": "binary",
                            "description": "optional zip or tar of the NeRF-Synthetic or COLMAP dataset the scene "
                            "was trained from; its test views then judge fidelity",
                        },
                        "params": {
                            "type": "string",
                            "description": "JSON object of JobParams",
                            "example": '{"preset": "balanced", "psnr_budget": 0.3, "device": "auto"}',
                        },
                    },
                },
                "encoding": {"params": {"contentType": "application/json"}},
            }
        },
    }
}


@router.post(
    "",
    status_code=202,
    response_model=Job,
    summary="Submit a scene for compression",
    description="Validates the upload (size, PLY header, dataset archive, params) before answering, stores it and "
    "queues the job. Answers 202 with `Location`; with an `Idempotency-Key` already used by this API key, answers "
    "200 with the job it created.",
    responses={
        200: {"model": Job, "description": "the job an earlier request with the same Idempotency-Key created"},
        **error_responses(401, 413, 422, 503),
    },
    openapi_extra=_MULTIPART,
)
async def create_job(
    request: Request,
    owner: OwnerDep,
    settings: SettingsDep,
    store: StoreDep,
    storage: StorageDep,
    celery: CeleryDep,
    idempotency_key: Annotated[str | None, Header(description="makes retries of one submission safe")] = None,
) -> JSONResponse:
    submitted = await submit(
        request, owner=owner, idempotency_key=idempotency_key, settings=settings, store=store, storage=storage,
        celery=celery,
    )  # fmt: skip
    job = public_job(submitted.record)
    status = 202 if submitted.created else 200
    return JSONResponse(job.model_dump(mode="json"), status_code=status, headers=job_headers(submitted.record))


@router.get(
    "",
    response_model=JobPage,
    summary="List jobs",
    description="The caller's jobs, newest first, optionally only those in one state.",
    responses=error_responses(401, 422, 503),
)
def list_jobs(
    owner: OwnerDep,
    store: StoreDep,
    state: Annotated[JobState | None, Query(description="only jobs in this state")] = None,
    offset: Annotated[int, Query(ge=0, le=1_000_000)] = 0,
    limit: Annotated[int, Query(ge=1, le=200)] = 20,
) -> JobPage:
    records, total = store.list_owned(owner, state=state, offset=offset, limit=limit)
    next_offset = offset + limit if offset + limit < total else None
    items = [public_job(r) for r in records]
    return JobPage(items=items, total=total, offset=offset, limit=limit, next_offset=next_offset)


@router.get(
    "/{job_id:job_id}",
    response_model=Job,
    summary="Get a job",
    description="State, stage, progress, mirrors found, metrics, timestamps and error. While the job is unfinished "
    "the answer carries `Retry-After` (seconds before polling again).",
    responses=error_responses(401, 404, 503),
)
def get_job(job_id: str, owner: OwnerDep, store: StoreDep, response: Response) -> Job:
    record = owned_record(store, owner, job_id)
    response.headers.update(job_headers(record))
    return public_job(record)


@router.post(
    "/{job_id}:cancel",
    status_code=202,
    response_model=Job,
    summary="Cancel a job",
    description="A queued job is cancelled at once; a running one stops within seconds (`cancel_requested` is "
    "true until it has). Cancelling a cancelled job answers 200; a finished one, 409.",
    responses={
        200: {"model": Job, "description": "the job was already cancelled"},
        **error_responses(401, 404, 409, 503),
    },
)
def cancel_job(job_id: str, owner: OwnerDep, store: StoreDep, settings: SettingsDep) -> JSONResponse:
    record = owned_record(store, owner, job_id)
    status = 200 if record.state == "cancelled" else 202
    record = _cancel(record, store, settings)
    return JSONResponse(public_job(record).model_dump(mode="json"), status_code=status, headers=job_headers(record))


def _cancel(record: JobRecord, store: JobStore, settings: Settings) -> JobRecord:
    if record.state == "cancelled":
        return record
    if record.state in ("succeeded", "failed"):
        raise ApiError(409, "already_finished", f"job {record.id} has already {record.state}")
    # Set the flag first: a worker may take the job between the two steps, and it reads the flag.
    store.request_cancel(record.id, settings.job_ttl)
    if record.state == "queued":
        done = store.transition(record.id, "cancelled", message="cancelled by the client")
        if done is not None:
            return done
    return store.get(record.id) or record


@router.delete(
    "/{job_id:job_id}",
    status_code=204,
    summary="Delete a job",
    description="Cancels the job if unfinished and deletes it with its files. A running job is deleted once it has "
    "stopped (202, within seconds); otherwise at once (204).",
    responses={202: {"model": Job, "description": "stopping; deleted once stopped"}, **error_responses(401, 404, 503)},
)
def delete_job(job_id: str, owner: OwnerDep, store: StoreDep, storage: StorageDep, settings: SettingsDep) -> Response:
    record = owned_record(store, owner, job_id)
    if not record.finished:
        record = _cancel(record, store, settings)
    if record.state == "running":
        store.update(record.id, delete_requested=True)
        latest = store.get(record.id)
        if latest is not None and not latest.finished:
            return JSONResponse(public_job(latest).model_dump(mode="json"), status_code=202)
    storage.delete(owner=record.owner, job_id=record.id)
    store.delete(record.id)
    return Response(status_code=204)
