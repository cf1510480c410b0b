"""``/v1/jobs/{id}/...``: the results of a finished job."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path
from fastapi.responses import StreamingResponse

from api_schemas import Report
from symgs_core.export.formats import EXPORTS, ExportFormat
from worker.gateway import JobStore, Storage

from ..auth import OwnerDep
from ..deps import StorageDep, StoreDep
from ..errors import ApiError, error_responses
from ..job_view import RETRY_AFTER_S, owned_record

router = APIRouter(prefix="/v1/jobs", tags=["results"])
_ERRORS = error_responses(401, 404, 409, 503)


def _artifact(
    job_id: str, name: str, owner: str, store: JobStore, storage: Storage, media_type: str, filename: str
) -> StreamingResponse:
    record = owned_record(store, owner, job_id)
    if record.state in ("queued", "running"):
        raise ApiError(409, "not_ready", f"job {job_id} is {record.state}", headers={"Retry-After": RETRY_AFTER_S})
    if record.state != "succeeded":
        raise ApiError(409, "no_result", f"job {job_id} {record.state}; it has no results")
    artifact = storage.open_artifact(owner=record.owner, job_id=job_id, name=name)
    if artifact is None:
        raise ApiError(404, "artifact_missing", f"job {job_id} has no {name}")
    headers = {"Content-Length": str(artifact.size), "Content-Disposition": f'attachment; filename="{filename}"'}
    return StreamingResponse(artifact.chunks, media_type=media_type, headers=headers)


def _binary(description: str, media_type: str = "application/octet-stream") -> dict:
    content = {media_type: {"schema": {"type": "string", "format": "binary"}}}
    return {200: {"description": description, "content": content}}


@router.get(
    "/{job_id}/result",
    summary="Download the compressed archive",
    description="The `.symgs` archive; `symgs decompress` or `symgs_core.decompress` decodes it.",
    response_class=StreamingResponse,
    responses={**_binary("the .symgs archive"), **_ERRORS},
)
def get_result(job_id: str, owner: OwnerDep, store: StoreDep, storage: StorageDep) -> StreamingResponse:
    return _artifact(job_id, "result.symgs", owner, store, storage, "application/octet-stream", f"{job_id}.symgs")


def _export_route(fmt: ExportFormat) -> None:
    """``GET /v1/jobs/{id}/result<extension>`` for one row of the export table."""

    def get_export(job_id: str, owner: OwnerDep, store: StoreDep, storage: StorageDep) -> StreamingResponse:
        return _artifact(job_id, fmt.artifact, owner, store, storage, fmt.media_type, f"{job_id}{fmt.extension}")

    router.add_api_route(
        f"/{{job_id}}/{fmt.artifact}",
        get_export,
        methods=["GET"],
        name=f"get_result_{fmt.name}",
        summary=f"Download the decoded scene as {fmt.title}",
        description=fmt.description,
        response_class=StreamingResponse,
        responses={**_binary(fmt.title, fmt.media_type), **_ERRORS},
    )


for _fmt in EXPORTS:
    _export_route(_fmt)


@router.get(
    "/{job_id}/scene",
    summary="Download the uploaded scene",
    description="The `.ply` scene as this job received it, whatever the job's state; the dashboard's viewer shows "
    "it beside the decoded result.",
    response_class=StreamingResponse,
    responses={**_binary("the uploaded scene", "application/x-ply"), **error_responses(401, 404, 503)},
)
def get_scene(job_id: str, owner: OwnerDep, store: StoreDep, storage: StorageDep) -> StreamingResponse:
    record = owned_record(store, owner, job_id)
    upload = storage.open_upload(owner=record.owner, job_id=job_id)
    if upload is None:
        raise ApiError(404, "artifact_missing", f"job {job_id} has no uploaded scene")
    headers = {"Content-Length": str(upload.size), "Content-Disposition": f'attachment; filename="{job_id}-scene.ply"'}
    return StreamingResponse(upload.chunks, media_type="application/x-ply", headers=headers)


@router.get(
    "/{job_id}/report",
    summary="Get the metrics report",
    description="Sizes, compression ratios, PSNR/SSIM, time per stage, every mirror level tried.",
    response_class=StreamingResponse,
    responses={200: {"model": Report, "description": "the report"}, **_ERRORS},
)
def get_report(job_id: str, owner: OwnerDep, store: StoreDep, storage: StorageDep) -> StreamingResponse:
    return _artifact(job_id, "report.json", owner, store, storage, "application/json", f"{job_id}-report.json")


@router.get(
    "/{job_id}/charts/{name}.png",
    summary="Get a chart",
    description="A PNG chart of the job: rate_distortion, speed_accuracy, mirrors, compare_0, ... (those the "
    "pipeline drew).",
    response_class=StreamingResponse,
    responses={**_binary("the chart", "image/png"), **_ERRORS},
)
def get_chart(
    job_id: str,
    name: Annotated[str, Path(pattern=r"^[A-Za-z0-9_-]{1,64}$")],
    owner: OwnerDep,
    store: StoreDep,
    storage: StorageDep,
) -> StreamingResponse:
    return _artifact(job_id, f"charts/{name}.png", owner, store, storage, "image/png", f"{job_id}-{name}.png")
