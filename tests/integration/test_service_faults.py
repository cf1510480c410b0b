"""Jobs survive faults: a worker killed mid-job and Redis restarted (SIGKILL, with its append-only file) while a
client submits and polls; every accepted job ends succeeded, with the same result. The long version is
``tests/tools/fault_jobs.py`` (figures in BENCHMARKS.md)."""

from __future__ import annotations

import pytest

from tests.tools.fault_jobs import fault_stack, run, scene_bytes

pytestmark = pytest.mark.integration


def test_no_job_is_lost_to_worker_kills_and_redis_restarts() -> None:
    stack = fault_stack(workers=1, lease_s=3)
    try:
        outcome = run(stack, scene_bytes(), jobs=4, kills=1, restarts=2, every=4, pace=2, timeout=150)
    finally:
        stack.cleanup()
    summary = outcome.summary()
    assert summary["faults"] == {"worker killed": 1, "redis killed and restarted": 1, "redis stopped and restarted": 1}
    assert (summary["jobs"], summary["succeeded"], summary["lost"]) == (4, 4, 0), summary
    assert summary["distinct_results"] == 1, summary
