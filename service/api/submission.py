"""Accepting a job: receive the upload, check it, store it, record the job and queue it."""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from pathlib import Path

from celery import Celery
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request

from api_schemas import JobParams
from symgs_core.ply_header import PlyError, PlyHeader, read_header
from worker.celery_app import send_compress
from worker.routing import choose_queue
from worker.settings import Settings
from worker.storage import Storage
from worker.store import JobRecord, JobStore

from .archives import ArchiveLimits, extract_dataset
from .errors import ApiError
from .uploads import Upload, receive_upload


@dataclass
class Submitted:
    record: JobRecord
    created: bool  # False: an earlier request with the same Idempotency-Key created it


def parse_params(text: str | None) -> JobParams:
    try:
        return JobParams.model_validate_json(text or "{}")
    except ValidationError as exc:
        parts = [f"{'.'.join(str(x) for x in e['loc']) or 'params'}: {e['msg']}" for e in exc.errors()]
        raise ApiError(422, "bad_params", "params: " + "; ".join(parts)) from None


def check_scene(path: Path, *, max_gaussians: int, name: str) -> PlyHeader:
    """The uploaded scene's header, checked by the rules the worker's reader applies (413 for too many Gaussians,
    422 otherwise); a scene with no Gaussians is refused too, as there is nothing to compress."""
    try:
        header = read_header(path, max_gaussians=max_gaussians, name=name)
    except PlyError as exc:
        raise ApiError(413 if exc.code == "too_many_gaussians" else 422, exc.code, str(exc)) from None
    if header.count == 0:
        raise ApiError(422, "empty_scene", f"{name}: the scene has no Gaussians")
    return header


def _check(upload: Upload, settings: Settings) -> tuple[JobParams, dict, dict | None, str | None]:
    """The blocking checks, run in a worker thread: params, the PLY header, the dataset archive."""
    params = parse_params(upload.params)
    header = check_scene(upload.scene, max_gaussians=settings.max_gaussians, name=upload.scene_filename)
    scene = {
        "filename": upload.scene_filename, "bytes": upload.scene_bytes, "gaussians": header.count,
        "sh_degree": header.sh_degree,
    }  # fmt: skip
    if upload.images is None:
        return params, scene, None, None
    limits = ArchiveLimits(
        max_entries=settings.max_archive_entries,
        max_bytes=settings.max_extracted_bytes,
        max_images=settings.max_images,
        max_image_pixels=settings.max_image_pixels,
    )
    dataset = extract_dataset(upload.images, upload.images.parent / "images", limits)
    upload.images.unlink()
    images = {"layout": dataset.layout, "images": dataset.images, "bytes": dataset.bytes}
    return params, scene, images, dataset.root


async def submit(
    request: Request,
    *,
    owner: str,
    idempotency_key: str | None,
    settings: Settings,
    store: JobStore,
    storage: Storage,
    celery: Celery,
) -> Submitted:
    if idempotency_key is not None:
        if not 1 <= len(idempotency_key) <= 255:
            raise ApiError(422, "bad_idempotency_key", "Idempotency-Key must have 1 to 255 characters")
        known = await run_in_threadpool(_known_job, store, owner, idempotency_key)
        if known is not None:
            return Submitted(known, created=False)
    staging = storage.new_staging()
    try:
        upload = await receive_upload(request, staging, max_bytes=settings.max_upload_bytes)
        params, scene, images, images_root = await run_in_threadpool(_check, upload, settings)
        job_id = uuid.uuid4().hex
        if idempotency_key is not None:
            winner = await run_in_threadpool(store.claim_idempotency, owner, idempotency_key, job_id, settings.job_ttl)
            known = await run_in_threadpool(store.get, winner) if winner is not None else None
            if known is not None:  # a concurrent request with the same key won
                storage.discard(staging)
                return Submitted(known, created=False)
        await run_in_threadpool(storage.adopt, staging, owner=owner, job_id=job_id)
    except BaseException:
        storage.discard(staging)
        raise
    queue = choose_queue(store, params.device, alive_within_s=settings.lease_seconds)
    record = JobRecord(
        id=job_id, owner=owner, params=params, queue=queue, scene=scene, images=images, images_root=images_root
    )
    await run_in_threadpool(_record_and_queue, record, store, storage, celery)
    return Submitted(record, created=True)


def _known_job(store: JobStore, owner: str, key: str) -> JobRecord | None:
    job_id = store.idempotent_job(owner, key)
    if job_id is None:
        return None
    record = store.get(job_id)
    if record is None:  # the job was deleted: the key is free again
        store.forget_idempotency(owner, key)
    return record


def _record_and_queue(record: JobRecord, store: JobStore, storage: Storage, celery: Celery) -> None:
    store.create(record)
    try:
        send_compress(celery, record.id, record.queue)
    except Exception as exc:
        store.transition(record.id, "failed", error_code="enqueue_failed", error_message=f"could not queue: {exc}")
        raise ApiError(503, "unavailable", "the job queue is not reachable; try again") from None
