"""One run of a compression job: the plain function behind the Celery task.

A run takes the job's lease (so two deliveries of one job never run at once), keeps it alive from a heartbeat
thread, calls the pipeline with the job's checkpoint folder (a rerun resumes after the last accepted level), and
writes the results under fixed names (a rerun overwrites). Failures are not handled here: they propagate to the
task's ``on_failure`` hook, the one place that marks a job failed.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

from redis import RedisError

from api_schemas import JobMetrics, MirrorSummary
from symgs_core.progress import Eta

from .maintenance import delete_if_requested
from .settings import Settings
from .storage import Storage, StorageError
from .store import JobRecord, JobStore

if TYPE_CHECKING:
    from symgs_core.pipeline import CompressResult
    from symgs_core.report import Report

Outcome = Literal["succeeded", "cancelled", "skipped", "lost"]
_CANCEL_POLL_S = 0.5  # should_stop is called often; ask Redis at most this often
_PROGRESS_EVERY_S = 0.25  # progress reports within one stage and level are thinned to this rate


class JobInputError(ValueError):
    """A job the pipeline refuses before starting; ``code`` is machine-readable, as in PlyError.

    Both go to the base class: Celery hands the failure hook a pickled copy, rebuilt from ``args``."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(code, message)
        self.code, self.message = code, message

    def __str__(self) -> str:
        return self.message


class _Heartbeat(threading.Thread):
    """Renews the job's lease until stopped; ``lost`` is set when another worker took the job over."""

    def __init__(self, store: JobStore, job_id: str, token: str, lease_s: float) -> None:
        super().__init__(name=f"lease-{job_id[:8]}", daemon=True)
        self.store, self.job_id, self.token, self.lease_s = store, job_id, token, lease_s
        self.lost = threading.Event()
        self._halt = threading.Event()

    def run(self) -> None:
        while not self._halt.wait(self.lease_s / 3):
            try:
                if not self.store.leases.renew(self.job_id, self.token, self.lease_s):
                    self.lost.set()
                    return
            except RedisError:  # Redis unreachable for a moment: try again next beat; the lease outlives 2 misses
                continue

    def stop(self) -> None:
        self._halt.set()
        self.join()


@dataclass
class _Progress:
    """The pipeline's progress callback: writes the job store and its event stream, thinned within a stage, with the
    estimated time left (every report feeds the estimate, thinned or not), and saves checkpoints the pipeline wrote
    since the last event (``save_checkpoints``)."""

    store: JobStore
    job_id: str
    save_checkpoints: Callable[[], None]
    eta: Eta = field(default_factory=Eta)
    clock: Callable[[], float] = time.monotonic
    _last: tuple[str, int | None, float] = ("", None, 0.0)

    def __call__(self, event) -> None:  # noqa: ANN001 - symgs_core.progress.ProgressEvent
        self.save_checkpoints()
        now = self.clock()
        eta_s = self.eta.update(event.fraction, now)
        stage, level, at = self._last
        if (event.stage, event.level) == (stage, level) and now - at < _PROGRESS_EVERY_S and event.fraction < 1:
            return
        self._last = (event.stage, event.level, now)
        fraction = min(max(float(event.fraction), 0.0), 1.0)
        self.store.progress(
            self.job_id, stage=event.stage, level=event.level, fraction=fraction, message=event.message,
            eta_s=None if eta_s is None else round(eta_s, 1),
        )  # fmt: skip


class _StopCheck:
    """The pipeline's ``should_stop``: a client cancelled, or the lease went to another worker."""

    def __init__(self, store: JobStore, job_id: str, heartbeat: _Heartbeat) -> None:
        self.store, self.job_id, self.heartbeat = store, job_id, heartbeat
        self._next = 0.0
        self._cancelled = False

    def __call__(self) -> bool:
        if self.heartbeat.lost.is_set():
            return True
        now = time.monotonic()
        if not self._cancelled and now >= self._next:
            self._next = now + _CANCEL_POLL_S
            self._cancelled = self.store.cancel_requested(self.job_id)
        return self._cancelled


def headline(report: Report) -> tuple[list[MirrorSummary], JobMetrics]:
    """Accepted mirrors and the headline metrics of a pipeline report, as the Job model holds them."""
    finite = lambda x: x if math.isfinite(x) else None  # noqa: E731 - JSON has no infinity
    mirrors = [
        MirrorSummary(level=lv.level, normal=list(lv.normal), offset=lv.offset, left=lv.left, right=lv.right,
                      psnr_after=finite(lv.psnr_after))
        for lv in report.accepted_levels
    ]  # fmt: skip
    metrics = JobMetrics(
        input_bytes=report.input_bytes, output_bytes=report.output_bytes, ratio_to_ply=report.ratio_to_ply or 0.0,
        ratio_to_baseline=report.ratio_to_baseline, psnr=finite(report.fidelity.psnr),
        psnr_object=finite(report.fidelity.psnr_object), ssim=report.fidelity.ssim,
        seconds=float(sum(report.seconds.values())), notes=list(report.notes),
    )  # fmt: skip
    return mirrors, metrics


def _write_results(storage: Storage, record: JobRecord, result: CompressResult) -> str:
    """Write the job's files; returns what could not be written and why ("" when every export was)."""
    from symgs_core.export.formats import EXPORTS

    def write(name: str, data: bytes) -> None:
        storage.write_artifact(owner=record.owner, job_id=record.id, name=name, data=data)

    write("result.symgs", result.archive)
    write("report.json", json.dumps(result.report.as_json(), indent=1).encode())
    for name, png in result.images.items():
        write(f"charts/{name}.png", png)
    skipped = []
    for fmt in EXPORTS:  # the decoded scene is what viewers get: the pipeline's decode of the archive stored here
        try:
            write(fmt.artifact, fmt.write(result.decoded))
        except ValueError as exc:  # a scene some format cannot hold (its fixed point, its ranges): the rest stand
            skipped.append(f"{fmt.artifact} not written: {exc}")
    return "; ".join(skipped)


def run_job(
    job_id: str, *, store: JobStore, storage: Storage, settings: Settings, token: str, device: str
) -> Outcome:
    """Run (or resume) a job. ``token`` names this delivery; ``device`` is ``cuda`` or ``cpu``.

    Returns what happened; raises whatever the pipeline raised (input errors carry a ``code``)."""
    record = store.get(job_id)
    if record is None or record.finished:
        return "skipped"  # deleted, or done by an earlier delivery of the same message
    if not store.leases.acquire(job_id, token, settings.lease_seconds):
        return "skipped"  # another worker runs it; if that worker dies, a reaper re-queues the job
    heartbeat = _Heartbeat(store, job_id, token, settings.lease_seconds)
    heartbeat.start()
    failed = True
    try:
        outcome = _run_leased(record, store=store, storage=storage, settings=settings, heartbeat=heartbeat,
                              device=device)  # fmt: skip
        failed = False
        return outcome
    finally:
        heartbeat.stop()
        if not failed:  # after a failure the on_failure hook marks the job first, then releases the lease
            store.leases.release(job_id, token)
            delete_if_requested(store, storage, job_id)


def _run_leased(
    record: JobRecord, *, store: JobStore, storage: Storage, settings: Settings, heartbeat: _Heartbeat, device: str
) -> Outcome:
    from symgs_core.config import CompressConfig
    from symgs_core.datasets import pixel_limit
    from symgs_core.pipeline import compress
    from symgs_core.progress import Cancelled

    job_id = record.id
    if store.cancel_requested(job_id):
        store.transition(job_id, "cancelled", stage=record.stage)
        return "cancelled"
    started = record.started_at or time.time()
    running = store.transition(
        job_id, "running", started_at=started, attempts=record.attempts + 1, stage="load", message="starting"
    )
    if running is None:
        return "skipped"  # cancelled between the checks

    try:
        config = CompressConfig.for_preset(**record.params.pipeline_overrides(), device=device)
    except ValueError as exc:  # a combination the schema's per-field bounds let through
        raise JobInputError("bad_params", f"params: {exc}") from None
    stop = _StopCheck(store, job_id, heartbeat)
    with storage.workspace(owner=record.owner, job_id=job_id) as work:
        folder = work.folder
        images = folder / "upload" / "images" / record.images_root if record.images_root is not None else None
        scene = folder / "upload" / "scene.ply"
        try:
            with pixel_limit(settings.max_image_pixels):  # the API checked what it took for images; this, what is read
                result = compress(
                    scene,
                    images=images,
                    config=config,
                    progress=_Progress(store, job_id, work.save_checkpoints),
                    checkpoint_dir=folder / "checkpoints",
                    should_stop=stop,
                    charts=False,  # drawn below, once, with the peers beside the job's own points
                )
        except Cancelled:
            if heartbeat.lost.is_set():
                return "lost"
            store.transition(job_id, "cancelled", message="cancelled by the client")
            return "cancelled"
        except input_errors() as exc:
            raise _as_uploaded(exc, scene.name, record.scene.get("filename") or scene.name) from None
        work.save_checkpoints()
        if result.images and not heartbeat.lost.is_set():
            from symgs_core.pictures import job_charts

            from .peers import upload_peers

            peers = []
            if settings.peer_seconds > 0:
                store.progress(job_id, stage="peers", level=None, fraction=1.0, message="running the peers' formats")
                peers = upload_peers(scene, images, result.report, seconds=settings.peer_seconds,
                                     work=folder / "peers")  # fmt: skip
            result.images.update(job_charts(result.report, peers=peers))
    if heartbeat.lost.is_set():
        return "lost"  # the worker that took the job over writes the same files
    skipped = _write_results(storage, record, result)
    mirrors, metrics = headline(result.report)
    artifacts = storage.artifact_names(owner=record.owner, job_id=job_id)
    done = store.transition(
        job_id, "succeeded", stage="done", progress=1.0, message=skipped, artifacts=artifacts,
        mirrors=[m.model_dump() for m in mirrors], metrics=metrics.model_dump(),
    )  # fmt: skip
    if done is not None and done.finished_at is not None:
        store.metrics.record_duration(done.finished_at - started)
    return "succeeded"


def input_errors() -> tuple[type[ValueError], ...]:
    """The errors that are the input's, each with a machine-readable ``code``: what the client sent must change."""
    from symgs_core.datasets import DatasetError
    from symgs_core.ply_header import PlyError

    return PlyError, DatasetError, JobInputError


def _as_uploaded(exc: ValueError, stored: str, uploaded: str) -> ValueError:
    """``exc`` naming the scene as the client named its upload, not as the job's storage keeps it."""
    message = str(exc)
    if message.startswith(f"{stored}:"):
        message = uploaded + message[len(stored) :]
    return type(exc)(exc.code, message)  # type: ignore[attr-defined]


def failure_of(exc: BaseException) -> tuple[str, str]:
    """The code and message a failed job records: an input error keeps its own code (the client is told what is
    wrong with what it sent); anything else is ``internal_error``."""
    if isinstance(exc, input_errors()):
        return exc.code, str(exc)  # type: ignore[attr-defined]
    if isinstance(exc, StorageError):  # its text names the bucket and endpoint: the log keeps it, not the client
        return "storage_unavailable", "the job's storage stopped answering, on every try; submit the job again"
    return "internal_error", str(exc) or type(exc).__name__


def mark_failed(
    job_id: str, code: str, message: str, *, store: JobStore, storage: Storage, token: str, lease_s: float
) -> JobRecord | None:
    """The failure hook's work: record a machine-readable code and the message, then free the job. Nothing is
    marked when another worker holds the job's lease (this delivery failed while that one runs it)."""
    if not store.leases.renew(job_id, token, lease_s) and store.leases.held(job_id):
        return None
    record = store.transition(job_id, "failed", error_code=code, error_message=message[:2000])
    store.leases.release(job_id, token)
    delete_if_requested(store, storage, job_id)
    return record
