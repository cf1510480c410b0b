"""Leases: which worker runs a job. A worker holds a job's lease while it runs it and renews it from a heartbeat;
a lease that lapses tells the sweep the worker is gone. One sweep wins each resend and re-queue."""

from __future__ import annotations

import redis

from .keys import P

# Renew or release a lease only while it still holds our token.
_RENEW = "if redis.call('get', KEYS[1]) == ARGV[1] then return redis.call('pexpire', KEYS[1], ARGV[2]) end return 0"
_RELEASE = "if redis.call('get', KEYS[1]) == ARGV[1] then return redis.call('del', KEYS[1]) end return 0"


class Leases:
    def __init__(self, client: redis.Redis) -> None:
        self.r = client
        self._renew = client.register_script(_RENEW)
        self._release = client.register_script(_RELEASE)

    def acquire(self, job_id: str, token: str, ttl_s: float) -> bool:
        return bool(self.r.set(f"{P}job:{job_id}:lease", token, nx=True, px=int(ttl_s * 1000)))

    def renew(self, job_id: str, token: str, ttl_s: float) -> bool:
        """Extend our lease; False when it expired or another worker holds it now."""
        return bool(self._renew(keys=[f"{P}job:{job_id}:lease"], args=[token, int(ttl_s * 1000)]))

    def release(self, job_id: str, token: str) -> None:
        self._release(keys=[f"{P}job:{job_id}:lease"], args=[token])

    def held(self, job_id: str) -> bool:
        return bool(self.r.exists(f"{P}job:{job_id}:lease"))

    def claim_resend(self, job_id: str, ttl_s: float) -> bool:
        """One sweep wins the resending of a queued job's message, once per ``ttl_s``."""
        return bool(self.r.set(f"{P}job:{job_id}:resent", "1", nx=True, px=int(ttl_s * 1000)))

    def claim_requeue(self, job_id: str, attempt: int, ttl_s: int) -> bool:
        """One reaper wins the re-queue of a given attempt of a job."""
        return bool(self.r.set(f"{P}job:{job_id}:requeue:{attempt}", "1", nx=True, ex=ttl_s))
