"""One job's task delivered twice (as Celery redelivers a message: the same task id, through the job's queue) to two
workers on s3:// storage: the delivery that finds the job's lease held is refused while the first runs, and one after
the end finds the job done; the job runs once, succeeds once, and its results in the bucket are one whole set."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import redis

from service.api.auth import owner_of
from service.cli.stack import Child
from tests.integration.conftest import KEY_A, TINY, client_for, finished, read_sse, submit, wait_for
from tests.integration.s3_hosts import S3Service, s3_service
from tests.s3_server import BUCKET
from worker.celery_app import COMPRESS_TASK, make_celery
from worker.settings import Settings


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Service]:
    with s3_service(tmp_path_factory.mktemp("hosts")) as running:
        running.start_api("api")
        running.start_worker("worker-0")
        running.start_worker("worker-1")
        yield running


def _delivered_task_id(service: S3Service, job_id: str) -> str:
    """The id of the job's message that a worker has taken and not yet acknowledged (the Redis transport keeps
    such messages in its ``unacked`` hash, to give them back should the worker die)."""
    client = redis.Redis.from_url(service.stack.redis_url, decode_responses=True)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        for entry in client.hvals("unacked"):
            headers = json.loads(entry)[0]["headers"]
            if headers["argsrepr"] == repr([job_id]):
                return headers["id"]
        time.sleep(0.05)
    raise AssertionError(f"no worker holds the message of job {job_id}")


def _skips(workers: list[Child], task_id: str) -> int:
    """Deliveries of ``task_id`` that a worker ended without running the job."""
    return sum(
        line.count(f"{task_id}] succeeded") for w in workers for line in w.log.read_text(errors="replace").splitlines()
        if "'skipped'" in line
    )  # fmt: skip


def _wait_for_skips(service: S3Service, task_id: str, count: int) -> None:
    deadline = time.monotonic() + 30
    while _skips(service.stack.workers, task_id) < count:
        assert time.monotonic() < deadline, "\n".join(w.tail() for w in service.stack.workers)
        time.sleep(0.05)


def test_a_task_delivered_twice_runs_the_job_once(service: S3Service, scene_path: Path) -> None:
    from symgs_core.pipeline import decompress

    celery = make_celery(Settings(redis_url=service.stack.redis_url))
    with client_for(service.stack, KEY_A) as api:
        job = submit(api, scene_path, TINY).json()
        wait_for(api, job["id"], lambda j: j["state"] == "running", timeout=60)
        task_id = _delivered_task_id(service, job["id"])

        # The same message again while the first delivery runs: the idle worker takes it and finds the lease held.
        celery.send_task(COMPRESS_TASK, args=[job["id"]], queue="cpu", routing_key="cpu", task_id=task_id)
        _wait_for_skips(service, task_id, 1)
        assert api.get(f"/v1/jobs/{job['id']}").json()["state"] == "running"

        done = wait_for(api, job["id"], finished, timeout=120)
        assert done["state"] == "succeeded" and done["attempts"] == 1, done
        # Once more after the end: the job is done, nothing runs it again.
        celery.send_task(COMPRESS_TASK, args=[job["id"]], queue="cpu", routing_key="cpu", task_id=task_id)
        _wait_for_skips(service, task_id, 2)
        assert api.get(f"/v1/jobs/{job['id']}").json() == done

        events = _events(api, job["id"])
        assert [e["state"] for e in events if e["kind"] == "state"] == ["queued", "running", "succeeded"]
        assert [e["stage"] for e in events if e["kind"] == "progress"].count("load") == 1  # one run began

        prefix = service.job_prefix(owner_of(KEY_A), job["id"]) + "result/"
        assert [key.removeprefix(prefix) for key in service.server.keys(prefix)] == done["artifacts"]
        archive = api.get(f"/v1/jobs/{job['id']}/result").content
        report = json.loads(api.get(f"/v1/jobs/{job['id']}/report").content)
        assert len(archive) == report["output_bytes"] == done["metrics"]["output_bytes"]
        assert len(decompress(archive)) == report["gaussians"]["decoded"]
        stored = service.server.client().get_object(Bucket=BUCKET, Key=prefix + "result.symgs")["Body"].read()
        assert stored == archive


def _events(api: httpx.Client, job_id: str) -> list[dict]:
    with api.stream("GET", f"/v1/jobs/{job_id}/events") as response:
        return [json.loads(message["data"]) for message in read_sse(response)]
