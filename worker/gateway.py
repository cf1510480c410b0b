"""What the service (the API and the ``symgs`` commands) takes from the worker package, and all it takes: the
settings both read, the job store, the artifact storage, and sending a job to its queue (or running a worker). The
service imports this module alone of ``worker``; it imports no torch, and ``worker`` imports nothing of ``service``.
"""

from __future__ import annotations

from .celery_app import make_celery, send_compress
from .routing import choose_queue
from .settings import Settings, get_settings
from .storage import Storage, StorageError, stored_name_problem
from .storage_backend import storage_from_settings
from .store import JobRecord, JobStore
from .store.events import follow as follow_events


def run_worker(mode: str, *, concurrency: int, loglevel: str) -> None:
    """Run a Celery worker for the ``mode`` queue (``symgs worker``), with its maintenance thread."""
    from .launch import run_worker as run

    run(mode, concurrency=concurrency, loglevel=loglevel)


__all__ = [
    "JobRecord",
    "JobStore",
    "Settings",
    "Storage",
    "StorageError",
    "choose_queue",
    "follow_events",
    "get_settings",
    "make_celery",
    "run_worker",
    "send_compress",
    "storage_from_settings",
    "stored_name_problem",
]
