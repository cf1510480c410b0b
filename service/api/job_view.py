"""Job records as clients see them."""

from __future__ import annotations

import re

from api_schemas import Job, JobError, JobLinks
from symgs_core.export.formats import EXPORTS
from worker.gateway import JobRecord, JobStore

from .errors import not_found

RETRY_AFTER_S = "2"  # polling interval suggested while a job is unfinished
_JOB_ID = re.compile(r"^[0-9a-f]{32}$")


def owned_record(store: JobStore, owner: str, job_id: str) -> JobRecord:
    """The caller's job; 404 when it does not exist or belongs to another API key (the two look the same)."""
    record = store.get_owned(job_id, owner) if _JOB_ID.match(job_id) else None
    if record is None:
        raise not_found(job_id)
    return record


def public_job(record: JobRecord) -> Job:
    base = f"/v1/jobs/{record.id}"
    error = None
    if record.error_code is not None:
        error = JobError(code=record.error_code, message=record.error_message or "")
    return Job(
        id=record.id,
        state=record.state,
        stage=record.stage,
        level=record.level,
        progress=record.progress,
        message=record.message,
        eta_s=record.eta_s,
        params=record.params,
        queue=record.queue,
        scene=record.scene,
        images=record.images,
        mirrors=record.mirrors,
        metrics=record.metrics,
        artifacts=record.artifacts,
        error=error,
        attempts=record.attempts,
        cancel_requested=record.cancel_requested,
        created_at=record.created_at,
        started_at=record.started_at,
        finished_at=record.finished_at,
        updated_at=record.updated_at,
        links=JobLinks(
            self=base, events=f"{base}/events", result=f"{base}/result", report=f"{base}/report",
            scene=f"{base}/scene",
            # A finished job links the exports it has: a scene some format cannot hold has none in it (``message``).
            exports={fmt.name: f"{base}/{fmt.artifact}" for fmt in EXPORTS
                     if not record.finished or fmt.artifact in record.artifacts},
        ),  # fmt: skip
    )


def job_headers(record: JobRecord) -> dict[str, str]:
    headers = {"Location": f"/v1/jobs/{record.id}"}
    if not record.finished:
        headers["Retry-After"] = RETRY_AFTER_S
    return headers
