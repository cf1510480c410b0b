"""Accepting a job: receive the upload, check it, store it, record the job and queue it."""

from __future__ import annotations

import hashlib
import logging
import uuid
from dataclasses import dataclass
from pathlib import Path

from celery import Celery
from pydantic import ValidationError
from redis import RedisError
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request

from api_schemas import JobParams
from symgs_core.ply_header import PlyError, PlyHeader, read_header
from worker.gateway import JobRecord, JobStore, Settings, Storage, StorageError, choose_queue, send_compress

from .archives import ArchiveLimits, extract_dataset
from .errors import ApiError
from .uploads import Upload, receive_upload

log = logging.getLogger(__name__)


@dataclass
class Submitted:
    record: JobRecord
    created: bool  # False: an earlier request with the same Idempotency-Key created it


def parse_params(text: str | None) -> JobParams:
    try:
        return JobParams.model_validate_json(text or "{}")
    except ValidationError as exc:
        parts = [f"{'.'.join(str(x) for x in e['loc'])}: {e['msg']}" if e["loc"] else e["msg"] for e in exc.errors()]
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


def fingerprint(params: JobParams, upload: Upload) -> str:
    """What makes two submissions the same request: the parameters as validated and the bytes of each file."""
    digest = hashlib.sha256(params.model_dump_json().encode())
    for path in (upload.scene, upload.images):
        part = hashlib.sha256()
        if path is not None:
            with open(path, "rb") as f:
                while chunk := f.read(1 << 20):
                    part.update(chunk)
        digest.update(part.digest())
    return digest.hexdigest()


def _check(upload: Upload, settings: Settings) -> tuple[dict, dict | None, str | None]:
    """The blocking checks, run in a worker thread: the PLY header, the dataset archive."""
    header = check_scene(upload.scene, max_gaussians=settings.max_gaussians, name=upload.scene_filename)
    scene = {
        "filename": upload.scene_filename, "bytes": upload.scene_bytes, "gaussians": header.count,
        "sh_degree": header.sh_degree,
    }  # fmt: skip
    if upload.images is None:
        return scene, None, None
    limits = ArchiveLimits(
        max_entries=settings.max_archive_entries,
        max_bytes=settings.max_extracted_bytes,
        max_images=settings.max_images,
        max_image_pixels=settings.max_image_pixels,
    )
    dataset = extract_dataset(upload.images, upload.images.parent / "images", limits)
    upload.images.unlink()
    images = {"layout": dataset.layout, "images": dataset.images, "bytes": dataset.bytes}
    return scene, images, dataset.root


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
    """Receive, check, store, record and queue a job. Whatever fails (a refused upload, Redis or the queue out of
    reach) leaves no files behind; Redis errors reach the client as 503 ``unavailable`` (``errors``)."""
    # Printable ASCII, as the header's draft standard has it: the key is logged and shown back to its client.
    if idempotency_key is not None and not (
        1 <= len(idempotency_key) <= 255 and all(" " <= c <= "~" for c in idempotency_key)
    ):
        raise ApiError(422, "bad_idempotency_key", "Idempotency-Key must be 1 to 255 printable ASCII characters")
    staging = await run_in_threadpool(storage.new_staging)
    job_id: str | None = None
    try:
        upload = await receive_upload(request, staging, max_bytes=settings.max_upload_bytes)
        params = parse_params(upload.params)
        mark = None
        if idempotency_key is not None:
            mark = await run_in_threadpool(fingerprint, params, upload)
            known = await run_in_threadpool(_known_job, store, owner, idempotency_key, mark)
            if known is not None:
                return Submitted(known, created=False)
        scene, images, images_root = await run_in_threadpool(_check, upload, settings)
        new_id = uuid.uuid4().hex
        if idempotency_key is not None and mark is not None:
            winner = await run_in_threadpool(
                store.idempotency.claim, owner, idempotency_key, new_id, mark, settings.job_ttl
            )
            if winner is not None:  # a concurrent request with the same key won
                known = await run_in_threadpool(_same_request, store, idempotency_key, winner, mark)
                if known is not None:
                    return Submitted(known, created=False)
        queue = await run_in_threadpool(choose_queue, store, params.device, alive_within_s=settings.lease_seconds)
        record = JobRecord(
            id=new_id, owner=owner, params=params, queue=queue, scene=scene, images=images, images_root=images_root
        )
        job_id = new_id  # from here, whatever adopt wrote goes again if the job is not recorded
        await run_in_threadpool(lambda: storage.adopt(staging, owner=owner, job_id=new_id))
        await run_in_threadpool(_record_and_queue, record, store, celery)
        return Submitted(record, created=True)
    except BaseException:
        if job_id is not None:
            await run_in_threadpool(_abandon, store, storage, owner, job_id)
        raise
    finally:
        await run_in_threadpool(storage.discard, staging)  # nothing left to remove once adopted


def _abandon(store: JobStore, storage: Storage, owner: str, job_id: str) -> None:
    """Delete the files of a job that was not recorded; where the storage is failing (the likely reason it was not),
    leave them to the workers' sweep, which no record would lead to otherwise."""
    try:
        storage.delete(owner=owner, job_id=job_id)
    except StorageError:
        try:
            store.abandon(owner, job_id)
        except RedisError:
            log.warning("job %s of %s: its files could not be deleted nor recorded for deletion", job_id, owner)


def _same_request(store: JobStore, key: str, binding: tuple[str, str], mark: str) -> JobRecord | None:
    """The job an Idempotency-Key is bound to, when this request is the one that created it; 422 when the key
    was used for a different request (its scene, images or params differ); None when that job is gone."""
    job_id, known_mark = binding
    if known_mark != mark:
        raise ApiError(
            422, "idempotency_key_reused",
            f"Idempotency-Key {key[:64]!r} was used for a different request (scene, images or params); "
            "send this one with a new key",
        )  # fmt: skip
    return store.get(job_id)


def _known_job(store: JobStore, owner: str, key: str, mark: str) -> JobRecord | None:
    binding = store.idempotency.bound(owner, key)
    if binding is None:
        return None
    record = _same_request(store, key, binding, mark)
    if record is None:  # the job was deleted: the key is free again
        store.idempotency.forget(owner, key)
    return record


def _record_and_queue(record: JobRecord, store: JobStore, celery: Celery) -> None:
    """Record the job and send its message; when either fails, the record is taken back (as far as Redis answers)
    and the caller removes the files."""
    try:
        store.create(record)
        send_compress(celery, record.id, record.queue)
    except Exception as exc:
        try:
            store.delete(record.id)
        except RedisError:
            pass  # Redis went away meanwhile: the record stays, and the job fails for want of its files
        if isinstance(exc, RedisError):
            raise
        raise ApiError(503, "unavailable", "the job queue is not reachable; try again") from None
