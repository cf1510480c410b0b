"""The job store, in Redis, by concern: records with their indexes and checked state changes (``records``), their
event streams (``events``), idempotency keys (``idempotency``), worker leases (``leases``), worker heartbeats
(``heartbeats``) and the figures ``/metrics`` reads (``metrics``). ``keys`` lists every key.
"""

from __future__ import annotations

import redis
from redis.backoff import ExponentialWithJitterBackoff
from redis.retry import Retry

from .heartbeats import Heartbeats
from .idempotency import Idempotency
from .keys import P, events_key, job_key
from .leases import Leases
from .metrics import DURATION_BUCKETS, Metrics
from .records import STATES, JobRecord, Records

# The workers' client waits out a Redis restart (about 30 s of retries) rather than failing the job it runs.
PATIENT = Retry(ExponentialWithJitterBackoff(base=0.1, cap=2.0), retries=20)


class JobStore(Records):
    """Synchronous access to the job store, for the workers and the API's thread pool: the records themselves, and
    each other concern on the same client."""

    def __init__(self, client: redis.Redis) -> None:
        super().__init__(client)
        self.idempotency = Idempotency(client)
        self.leases = Leases(client)
        self.heartbeats = Heartbeats(client)
        self.metrics = Metrics(client)

    @classmethod
    def from_url(cls, url: str, *, patient: bool = False) -> JobStore:
        """A store on Redis at ``url``; ``patient`` (workers) retries through a Redis restart, where the API answers
        503 at once."""
        retry = {"retry": PATIENT} if patient else {}
        return cls(redis.Redis.from_url(url, decode_responses=True, health_check_interval=30, **retry))


__all__ = ["DURATION_BUCKETS", "P", "STATES", "JobRecord", "JobStore", "events_key", "job_key"]
