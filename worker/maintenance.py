"""Work a worker does besides jobs: announce it is alive, recover jobs of lost workers, expire old jobs.

Redis hands a dead worker's unacknowledged message to another worker only after the visibility timeout, which
must exceed the longest job (hours). Jobs are recovered much sooner by their leases: a running job whose lease
expired has lost its worker, and the first sweep that notices sends it again (each attempt once, whichever worker
sweeps first). Every worker sweeps when it starts and then periodically.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

from celery import Celery
from redis import RedisError

from api_schemas import QUEUES

from .celery_app import send_compress
from .routing import choose_queue
from .settings import Settings
from .storage import Storage, StorageError
from .store import JobStore

log = logging.getLogger(__name__)
STAGING_MAX_AGE_S = 6 * 3600  # an upload still staging after this long belongs to an API process that died
QUARANTINE_S = 3600  # an expired job whose files would not delete is tried again this much later


@dataclass
class SweepReport:
    requeued: list[str] = field(default_factory=list)
    rerouted: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    cancelled: list[str] = field(default_factory=list)
    expired: list[str] = field(default_factory=list)
    quarantined: list[str] = field(default_factory=list)  # expired, but their files would not delete: set aside
    abandoned: list[str] = field(default_factory=list)  # files of unrecorded submissions, deleted late


def delete_if_requested(store: JobStore, storage: Storage, job_id: str) -> None:
    """Delete a finished job, record and files, that its client asked to delete while it ran."""
    record = store.get(job_id)
    if record is not None and record.delete_requested and record.finished:
        storage.delete(owner=record.owner, job_id=job_id)
        store.delete(job_id)


def recover_lost(store: JobStore, storage: Storage, celery: Celery, settings: Settings, report: SweepReport) -> None:
    """Re-queue running jobs whose lease expired; fail them after ``max_attempts`` runs or past the time limit.
    A job whose client asked to delete it while it ran is deleted once it ends here, as its worker would have."""
    now = time.time()
    for job_id in store.ids_in_state("running"):
        if store.leases.held(job_id):
            continue
        record = store.get(job_id)
        if record is None or record.state != "running":
            continue
        if not store.leases.claim_requeue(job_id, record.attempts, settings.job_ttl):
            continue  # another worker's sweep took this attempt
        if record.cancel_requested:
            store.transition(job_id, "cancelled", message="cancelled by the client")
            report.cancelled.append(job_id)
        elif record.attempts >= settings.max_attempts:
            store.transition(
                job_id, "failed", error_code="worker_lost",
                error_message=f"the worker running this job was lost {record.attempts} times",
            )  # fmt: skip
            report.failed.append(job_id)
        elif record.started_at is not None and now - record.started_at > settings.hard_time_limit:
            store.transition(
                job_id, "failed", error_code="time_limit",
                error_message=f"the job ran past the time limit of {settings.hard_time_limit} s",
            )  # fmt: skip
            report.failed.append(job_id)
        else:
            queue = choose_queue(store, record.params.device, alive_within_s=settings.lease_seconds)
            if store.transition(job_id, "queued", queue=queue, message="worker lost; queued again") is not None:
                send_compress(celery, job_id, queue)
                report.requeued.append(job_id)
                log.warning("job %s lost its worker; queued again on %s", job_id, queue)
            continue
        delete_if_requested(store, storage, job_id)


def recover_dropped(store: JobStore, celery: Celery, settings: Settings, report: SweepReport) -> None:
    """Send again a queued job whose message is neither waiting in its queue nor being run.

    A worker that took a message and lost Redis before starting the job lets it go: acknowledged with the failed
    task, or left in the broker's set of unacknowledged messages until the visibility timeout, hours away. Such a
    job has waited longer than a lease while its queue is empty and no worker holds its lease. It is sent once per
    lease period; should the first message surface after all, the lease lets one delivery run the job and the other
    skip it.
    """
    empty = {queue for queue, depth in store.metrics.queue_depth(QUEUES).items() if depth == 0}
    if not empty:
        return
    stale = time.time() - settings.lease_seconds
    for job_id in store.ids_in_state("queued"):
        record = store.get(job_id)
        if record is None or record.state != "queued" or record.queue not in empty or record.updated_at > stale:
            continue
        if store.leases.held(job_id) or not store.leases.claim_resend(job_id, settings.lease_seconds):
            continue
        send_compress(celery, job_id, record.queue)
        report.requeued.append(job_id)
        log.warning("job %s waited with no message in queue %s; sent again", job_id, record.queue)


def reroute_stranded(store: JobStore, celery: Celery, settings: Settings, report: SweepReport) -> None:
    """Send ``auto`` jobs waiting on the gpu queue to the cpu queue when no GPU worker is alive any more.

    The gpu message stays queued; whichever delivery runs first takes the job and the other finds it done."""
    if store.heartbeats.live("gpu", settings.lease_seconds) > 0:
        return
    for job_id in store.ids_in_state("queued"):
        record = store.get(job_id)
        if record is None or record.state != "queued" or record.queue != "gpu" or record.params.device != "auto":
            continue
        store.update(job_id, queue="cpu")
        send_compress(celery, job_id, "cpu")
        report.rerouted.append(job_id)


def _deleted(storage: Storage, owner: str, job_id: str) -> bool:
    """Delete a job's files: True when they are gone; False, logged, when they would not go although the storage
    answers (the job's own fault: a name the storage refuses, a file it may not remove). StorageError when the storage
    does not answer: an outage, under which every job would fail alike, for the next sweep to try again."""
    try:
        storage.delete(owner=owner, job_id=job_id)
    except StorageError as exc:
        if not storage.reachable():
            raise
        log.error("job %s of %s: its files could not be deleted (%s)", job_id, owner, exc)
        return False
    return True


def delete_abandoned(store: JobStore, storage: Storage, report: SweepReport) -> None:
    """Delete the files of submissions refused while the storage was failing, which the API could not delete then;
    those that would not go stay listed, for the next sweep."""
    for owner, job_id in store.abandoned():
        if _deleted(storage, owner, job_id):
            store.forget_abandoned(owner, job_id)
            report.abandoned.append(job_id)


def expire(store: JobStore, storage: Storage, settings: Settings, report: SweepReport) -> None:
    """Delete jobs (records and files) that finished more than ``job_ttl`` seconds ago, and stale uploads.

    A job whose files would not delete is set aside (``quarantine``) and tried again ``QUARANTINE_S`` later, and the
    sweep goes on: the oldest job comes first, so one that fails on every try kept every tenant's jobs, and the
    staging uploads, from ever expiring."""
    now = time.time()
    for job_id in store.finished_before(now - settings.job_ttl) + store.quarantined_until(now):
        record = store.get(job_id)
        if record is not None and not _deleted(storage, record.owner, job_id):
            store.quarantine(job_id, now + QUARANTINE_S)
            report.quarantined.append(job_id)
            log.error("job %s set aside; its deletion is tried again in %d s", job_id, QUARANTINE_S)
            continue
        store.delete(job_id)
        report.expired.append(job_id)
    storage.sweep_staging(STAGING_MAX_AGE_S)


def sweep(store: JobStore, storage: Storage, celery: Celery, settings: Settings) -> SweepReport:
    report = SweepReport()
    recover_lost(store, storage, celery, settings, report)
    recover_dropped(store, celery, settings, report)
    reroute_stranded(store, celery, settings, report)
    expire(store, storage, settings, report)
    delete_abandoned(store, storage, report)
    return report


class Maintenance(threading.Thread):
    """A worker's background work: a liveness heartbeat every third of a lease, and on a thread of its own a sweep
    every ``maintenance_seconds`` (and at once on start). Apart, so that a sweep held up by a slow storage or Redis
    never lets the heartbeat lapse: the worker would look dead, and its jobs be taken over."""

    def __init__(
        self, *, store: JobStore, storage: Storage, celery: Celery, settings: Settings, mode: str, name: str
    ) -> None:
        super().__init__(name="symgs-maintenance", daemon=True)
        self.store, self.storage, self.celery, self.settings = store, storage, celery, settings
        self.mode, self.worker_name = mode, name
        self._halt = threading.Event()
        self._sweeper = threading.Thread(target=self._sweep_loop, name="symgs-sweep", daemon=True)

    def run(self) -> None:
        self._sweeper.start()
        while True:
            try:
                self.store.heartbeats.beat(self.mode, self.worker_name)
            except Exception:  # noqa: BLE001 - Redis away: beat again next time
                log.exception("worker heartbeat failed; retrying")
            if self._halt.wait(self.settings.lease_seconds / 3):
                break
        try:
            self.store.heartbeats.gone(self.mode, self.worker_name)
        except RedisError:
            log.warning("could not remove worker %s from the live set", self.worker_name)

    def _sweep_loop(self) -> None:
        while True:
            try:
                sweep(self.store, self.storage, self.celery, self.settings)
            except (RedisError, StorageError) as exc:  # away for a while: a line a sweep, not a traceback
                log.warning("maintenance sweep failed (%s: %s); retrying", type(exc).__name__, exc)
            except Exception:  # noqa: BLE001 - a failed sweep must not end the thread
                log.exception("maintenance sweep failed; retrying")
            if self._halt.wait(self.settings.maintenance_seconds):
                break

    def stop(self) -> None:
        self._halt.set()
        self.join(timeout=5)
        if self._sweeper.is_alive():
            self._sweeper.join(timeout=5)
