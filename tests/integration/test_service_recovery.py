"""A worker killed mid-job (SIGKILL, the whole process group, as when a machine dies): once a worker runs again,
the job is taken over within seconds and ends with the same result as an uninterrupted run."""

from __future__ import annotations

import json
import time
from pathlib import Path

import httpx

from tests.integration.conftest import TINY, finished, read_sse, submit, wait_for


def test_killed_worker_job_resumes_with_the_same_result(
    stack, api_a: httpx.Client, scene_path: Path, done_job: dict  # noqa: ANN001
) -> None:
    assert done_job["state"] == "succeeded", done_job
    expected = api_a.get(f"/v1/jobs/{done_job['id']}/result").content

    job = submit(api_a, scene_path, TINY).json()
    wait_for(api_a, job["id"], lambda j: j["stage"] == "levels", timeout=60)
    for worker in list(stack.workers):
        worker.kill()
        stack.workers.remove(worker)
    killed_at = time.monotonic()
    assert api_a.get(f"/v1/jobs/{job['id']}").json()["state"] == "running"

    stack.start_worker("cpu")
    wait_for(api_a, job["id"], lambda j: j["state"] == "running" and j["attempts"] == 2, timeout=60)
    takeover = time.monotonic() - killed_at
    # Restarting the worker takes a few seconds, the lease expires 3 s after the kill, sweeps run every second.
    assert takeover < 25, f"took {takeover:.0f} s from the kill to the job running again"
    done = wait_for(api_a, job["id"], finished, timeout=120)
    assert done["state"] == "succeeded", done
    assert done["attempts"] == 2
    assert api_a.get(f"/v1/jobs/{job['id']}/result").content == expected

    with api_a.stream("GET", f"/v1/jobs/{job['id']}/events") as response:
        events = [json.loads(message["data"]) for message in read_sse(response)]
    states = [e["state"] for e in events if e["kind"] == "state"]
    assert states == ["queued", "running", "queued", "running", "succeeded"]
