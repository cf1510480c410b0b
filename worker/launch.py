"""Start a Celery worker for one queue, with its maintenance thread (``symgs worker --mode gpu|cpu``)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import uuid

from celery import signals

from symgs_core.heap import one_arena

from .celery_app import app
from .maintenance import Maintenance
from .settings import get_settings
from .storage_backend import storage_from_settings
from .store import JobStore

GPU_CHECK_S = 900  # the first check on a machine may compile gsplat's kernels (about a minute on 16 cores)


def _check_gpu() -> None:
    """Refuse to start where no job could render: no CUDA device, gsplat missing, or its kernels unbuildable or
    broken. The check runs in a child process: this one forks the job pool, and CUDA does not survive a fork."""
    check = [sys.executable, "-m", "symgs_core.render.gpu"]
    try:
        done = subprocess.run(check, capture_output=True, text=True, timeout=GPU_CHECK_S)
    except subprocess.TimeoutExpired:
        raise ValueError(f"the GPU check did not finish in {GPU_CHECK_S} s; run a cpu worker here") from None
    if done.returncode != 0:
        why = (done.stderr.strip().splitlines() or [f"exit status {done.returncode}"])[-1]
        raise ValueError(f"this machine cannot run GPU jobs: {why}; run a cpu worker here")


def run_worker(mode: str, *, concurrency: int = 1, loglevel: str = "INFO") -> None:
    """Consume queue ``mode`` (gpu or cpu) in this process until stopped. A GPU worker runs one job at a time."""
    if mode not in ("gpu", "cpu"):
        raise ValueError(f"mode must be 'gpu' or 'cpu', got {mode!r}")
    one_arena()  # before this process starts a thread, so that the jobs it forks allocate from one heap
    if mode == "gpu" and concurrency != 1:
        raise ValueError(f"a gpu worker runs one job at a time, got concurrency {concurrency}")
    if mode == "gpu":
        # Jobs ask NVML, not the CUDA runtime, whether there is a device: the pool is forked from this process.
        os.environ.setdefault("PYTORCH_NVML_BASED_CUDA_CHECK", "1")
        _check_gpu()
    settings = get_settings()
    # A worker the storage refuses would take jobs only to spend their runs failing; an outage, though, may pass.
    if (refused := storage_from_settings(settings).refused()) is not None:
        raise ValueError(f"the storage refuses this worker: {refused}")
    name = f"{mode}-{uuid.uuid4().hex[:8]}@{socket.gethostname()}"
    maintenance: list[Maintenance] = []

    @signals.worker_ready.connect(weak=False)
    def _start(**_: object) -> None:
        thread = Maintenance(
            store=JobStore.from_url(settings.redis_url, patient=True), storage=storage_from_settings(settings),
            celery=app, settings=settings, mode=mode, name=name,
        )  # fmt: skip
        thread.start()
        maintenance.append(thread)

    @signals.worker_shutdown.connect(weak=False)
    def _stop(**_: object) -> None:
        for thread in maintenance:
            thread.stop()

    app.worker_main(
        [
            "worker", "--queues", mode, "--concurrency", str(concurrency), "--pool", "prefork",
            "--hostname", name, "--loglevel", loglevel,
            # Liveness is the maintenance heartbeat; the cluster chatter would only slow start-up.
            "--without-mingle", "--without-gossip", "--without-heartbeat",
        ]
    )  # fmt: skip
