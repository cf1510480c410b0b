"""What ``GET /metrics`` reads from Redis: the histogram of job durations and the depth of each queue."""

from __future__ import annotations

from collections.abc import Iterable

import redis

from .keys import P

DURATION_BUCKETS = (1, 5, 15, 30, 60, 120, 300, 600, 1800, 3600, 7200, 21600)  # seconds


class Metrics:
    def __init__(self, client: redis.Redis) -> None:
        self.r = client

    def record_duration(self, seconds: float) -> None:
        key = f"{P}metrics:durations"
        with self.r.pipeline(transaction=True) as p:
            for bound in DURATION_BUCKETS:
                if seconds <= bound:
                    p.hincrby(key, f"le:{bound}", 1)
            p.hincrbyfloat(key, "sum", seconds)
            p.hincrby(key, "count", 1)
            p.execute()

    def durations(self) -> tuple[list[tuple[float, int]], float, int]:
        """Cumulative bucket counts ``[(upper bound, count)]``, the sum and the count of job durations."""
        h = self.r.hgetall(f"{P}metrics:durations")
        buckets = [(float(b), int(h.get(f"le:{b}", 0))) for b in DURATION_BUCKETS]
        return buckets, float(h.get("sum", 0)), int(h.get("count", 0))

    def queue_depth(self, queues: Iterable[str]) -> dict[str, int]:
        """Messages waiting in each Celery queue (the Redis transport keeps a queue as a list of its name)."""
        with self.r.pipeline(transaction=False) as p:
            names = list(queues)
            for name in names:
                p.llen(name)
            return dict(zip(names, map(int, p.execute()), strict=True))
