"""Worker heartbeats: each worker's last sign of life by mode (gpu, cpu), for routing a job and for readiness."""

from __future__ import annotations

import time

import redis

from .keys import P


class Heartbeats:
    def __init__(self, client: redis.Redis) -> None:
        self.r = client

    def beat(self, mode: str, name: str) -> None:
        self.r.zadd(f"{P}workers:{mode}", {name: time.time()})

    def gone(self, mode: str, name: str) -> None:
        self.r.zrem(f"{P}workers:{mode}", name)

    def live(self, mode: str, within_s: float) -> int:
        key = f"{P}workers:{mode}"
        cutoff = time.time() - within_s
        with self.r.pipeline(transaction=False) as p:
            p.zremrangebyscore(key, "-inf", cutoff - 3600)  # forget workers silent for an hour
            p.zcount(key, cutoff, "+inf")
            return int(p.execute()[1])
