"""Idempotency keys: a client's ``Idempotency-Key`` bound to the job it created and to its request's fingerprint, so
a retried submission finds its job instead of making another."""

from __future__ import annotations

import hashlib

import redis

from .keys import P


def _binding(value: str | None) -> tuple[str, str] | None:
    if value is None:
        return None
    job_id, _, fingerprint = value.partition(" ")
    return job_id, fingerprint


class Idempotency:
    def __init__(self, client: redis.Redis) -> None:
        self.r = client

    def _key(self, owner: str, key: str) -> str:
        return f"{P}idem:{owner}:{hashlib.sha256(key.encode()).hexdigest()}"

    def bound(self, owner: str, key: str) -> tuple[str, str] | None:
        """(job id, request fingerprint) bound to ``key``, or None."""
        return _binding(self.r.get(self._key(owner, key)))

    def forget(self, owner: str, key: str) -> None:
        self.r.delete(self._key(owner, key))

    def claim(
        self, owner: str, key: str, job_id: str, fingerprint: str, ttl_s: int
    ) -> tuple[str, str] | None:
        """Bind ``key`` to ``job_id`` and the request's ``fingerprint``; returns the (job id, fingerprint) already
        bound to it, or None when the claim won."""
        name = self._key(owner, key)
        if self.r.set(name, f"{job_id} {fingerprint}", nx=True, ex=ttl_s):
            return None
        return _binding(self.r.get(name))
