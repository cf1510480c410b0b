"""Celery tasks. A task takes a job id, re-loads the job from the store and hands it to ``runner.run_job``."""

from __future__ import annotations

import logging
import os
import socket

from celery import Task
from celery.exceptions import SoftTimeLimitExceeded

from .celery_app import COMPRESS_TASK, app, send_compress
from .runner import failure_of, input_errors, mark_failed, run_job
from .settings import Settings, get_settings
from .storage import StorageError
from .storage_backend import storage_from_settings
from .store import JobStore

log = logging.getLogger(__name__)


def _token(task_id: str | None) -> str:
    """Names one delivery in one process: a redelivered message (same task id) in a new process differs."""
    return f"{socket.gethostname()}:{os.getpid()}:{task_id}"


class CompressTask(Task):
    """Holds one store and storage per worker process; ``on_failure`` is the one place a job is marked failed."""

    _store: JobStore | None = None

    @property
    def store(self) -> JobStore:
        if self._store is None:
            self._store = JobStore.from_url(get_settings().redis_url, patient=True)
        return self._store

    def on_failure(self, exc, task_id, args, kwargs, einfo) -> None:  # noqa: ANN001 - Celery's signature
        job_id = args[0]
        if isinstance(exc, SoftTimeLimitExceeded):
            code, message = "time_limit", f"the job ran past the time limit of {get_settings().soft_time_limit} s"
        else:
            code, message = failure_of(exc)
        if code in ("internal_error", "storage_unavailable"):
            log.error("job %s failed: %s", job_id, einfo)
        settings = get_settings()
        mark_failed(
            job_id, code, message, store=self.store, storage=storage_from_settings(settings),
            token=_token(task_id), lease_s=settings.lease_seconds,
        )  # fmt: skip


# Input errors are expected: Celery logs them in a line, without a traceback; ``on_failure`` records their code.
@app.task(name=COMPRESS_TASK, base=CompressTask, bind=True, throws=input_errors())
def compress_job(self: CompressTask, job_id: str) -> str:
    settings = get_settings()
    queue = (self.request.delivery_info or {}).get("routing_key", "cpu")
    token = _token(self.request.id)
    outcome: str
    try:
        outcome = run_job(
            job_id,
            store=self.store,
            storage=storage_from_settings(settings),
            settings=settings,
            token=token,
            device="cuda" if queue == "gpu" else "cpu",
        )
    except StorageError as exc:
        if not _queue_again(self.store, job_id, token, settings):
            raise  # on_failure records storage_unavailable
        # The operator's log keeps why (an outage, or credentials refused); the job's message, read by clients, not.
        log.warning("job %s: %s; queued again in %s s", job_id, exc, settings.lease_seconds)
        outcome = "queued again"
    log.info("job %s: %s", job_id, outcome)
    return outcome


def _queue_again(store: JobStore, job_id: str, token: str, settings: Settings) -> bool:
    """After the storage failed under a run: queue the job again, a lease later, to resume from its last checkpoint
    (a storage that restarts, a network that drops for a minute), within ``max_attempts`` runs; False past them, or
    when the client asked to cancel."""
    record = store.get(job_id)
    if record is None or record.state != "running" or record.attempts >= settings.max_attempts:
        return False
    if store.cancel_requested(job_id) or not store.leases.renew(job_id, token, settings.lease_seconds):
        return False
    if store.transition(job_id, "queued", message="the storage stopped answering; queued again") is None:
        return False
    store.leases.release(job_id, token)
    send_compress(app, job_id, record.queue, countdown=settings.lease_seconds)
    return True
