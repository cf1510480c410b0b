"""Start a Celery worker for one queue, with its maintenance thread (``symgs worker --mode gpu|cpu``)."""

from __future__ import annotations

import os
import socket
import uuid

from celery import signals

from .celery_app import app
from .maintenance import Maintenance
from .settings import get_settings
from .storage_backend import storage_from_settings
from .store import JobStore


def run_worker(mode: str, *, concurrency: int = 1, loglevel: str = "INFO") -> None:
    """Consume queue ``mode`` (gpu or cpu) in this process until stopped. A GPU worker runs one job at a time."""
    if mode not in ("gpu", "cpu"):
        raise ValueError(f"mode must be 'gpu' or 'cpu', got {mode!r}")
    if mode == "gpu" and concurrency != 1:
        raise ValueError(f"a gpu worker runs one job at a time, got concurrency {concurrency}")
    if mode == "gpu":
        # Ask NVML, not the CUDA runtime: pool processes are forked from this one, and CUDA does not survive a fork.
        os.environ.setdefault("PYTORCH_NVML_BASED_CUDA_CHECK", "1")
        import torch

        if not torch.cuda.is_available():
            raise ValueError("no CUDA device is visible to this process; run a cpu worker here")
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
