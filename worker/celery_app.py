"""The Celery application: Redis broker, queues ``gpu`` and ``cpu``, settings for long jobs that must not be lost.

The API imports this module to send tasks by name; it never imports ``worker.tasks`` (which pulls in torch).
"""

from __future__ import annotations

from celery import Celery
from kombu import Queue

from api_schemas import QUEUES

from .settings import Settings, get_settings

COMPRESS_TASK = "symgs.compress"


def make_celery(settings: Settings) -> Celery:
    app = Celery("symgs", broker=settings.redis_url, include=["worker.tasks"])
    app.conf.update(
        task_queues=[Queue(name, routing_key=name) for name in QUEUES],
        task_default_queue="cpu",
        # Jobs are idempotent (fixed output paths, checkpoints), so a message may be delivered twice but must never
        # be lost: acknowledge after the job, and give the message back when the worker process dies.
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        # Redis hands an unacknowledged message to another worker after this long; it must exceed the longest job,
        # or a running job would start twice. Lost workers are detected much sooner by job leases (maintenance.py).
        broker_transport_options={"visibility_timeout": settings.visibility_timeout},
        # On a lost broker connection the running job goes on: its lease, not the connection, tells others it lives.
        worker_cancel_long_running_tasks_on_connection_loss=False,
        task_soft_time_limit=settings.soft_time_limit,
        task_time_limit=settings.hard_time_limit,
        task_ignore_result=True,  # state and results live in the job store and the storage
        broker_connection_retry_on_startup=True,
        worker_hijack_root_logger=False,
    )
    return app


def send_compress(app: Celery, job_id: str, queue: str, *, countdown: float | None = None) -> None:
    app.send_task(COMPRESS_TASK, args=[job_id], queue=queue, routing_key=queue, countdown=countdown)


app = make_celery(get_settings())
