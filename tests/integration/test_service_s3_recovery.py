"""A worker killed mid-job (SIGKILL, the whole process group, as when a machine dies) on s3:// storage, where the
workers share no disk: another worker, on another host, resumes the job from the checkpoint in the bucket and ends
with the bytes of an uninterrupted run; a kill while results are being written never has a part of a file served;
deleting the job leaves nothing of it in the bucket, unfinished multipart uploads included."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.api.auth import owner_of
from tests.integration.conftest import KEY_A, TINY, client_for, finished, read_sse, submit, wait_for
from tests.integration.s3_hosts import S3Service, s3_service
from tests.s3_server import BUCKET
from worker.store import JobStore

# moto lists every unfinished upload as begun in 2010, so each sweep would take a live one for a dead process's and
# abort it: these workers sweep once, as they start.
SWEEP_ONCE = {"SYMGS_MAINTENANCE_SECONDS": "3600"}
# Its decoded scene (result.ply, result.glb) is over a part (8 MiB): those results go up as multipart uploads.
LARGE = {"preset": "fast", "train_views": 2, "fit_views": 2, "eval_views": 2, "resolution": 64, "eval_resolution": 64,
         "device": "cpu"}  # fmt: skip


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Service]:
    with s3_service(tmp_path_factory.mktemp("hosts")) as running:
        running.start_api("api")
        yield running


@pytest.fixture(scope="module")
def large_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from symgs_core.export import save_scene
    from symgs_core.synthetic import synthetic_scene

    path = tmp_path_factory.mktemp("large") / "large.ply"
    save_scene(synthetic_scene("global", n=40000, seed=4, sh_degree=3).scene, path)
    return path


def _kill_workers(service: S3Service) -> None:
    for worker in list(service.stack.workers):
        worker.kill()
        service.stack.workers.remove(worker)


def _events(api: httpx.Client, job_id: str) -> list[dict]:
    with api.stream("GET", f"/v1/jobs/{job_id}/events") as response:
        return [json.loads(message["data"]) for message in read_sse(response)]


def _run(api: httpx.Client, scene: Path, params: dict) -> tuple[dict, bytes]:
    response = submit(api, scene, params)
    assert response.status_code == 202, response.text
    job = wait_for(api, response.json()["id"], finished, timeout=180)
    assert job["state"] == "succeeded", job
    return job, api.get(f"/v1/jobs/{job['id']}/result").content


def _wait_for_key(service: S3Service, key: str, timeout: float = 120) -> None:
    client = service.server.client()
    deadline = time.monotonic() + timeout
    while client.list_objects_v2(Bucket=BUCKET, Prefix=key).get("KeyCount", 0) == 0:
        assert time.monotonic() < deadline, f"{key} did not appear in {timeout} s"
        time.sleep(0.02)


def test_a_job_whose_worker_is_killed_resumes_from_the_checkpoint_in_the_bucket(
    service: S3Service, scene_path: Path
) -> None:
    service.start_worker("worker-0")
    with client_for(service.stack, KEY_A) as api:
        _, expected = _run(api, scene_path, TINY)

        job = submit(api, scene_path, TINY).json()
        prefix = service.job_prefix(owner_of(KEY_A), job["id"])
        _wait_for_key(service, prefix + "checkpoints/levels.pt")
        _kill_workers(service)
        killed = api.get(f"/v1/jobs/{job['id']}").json()
        assert killed["state"] == "running" and killed["stage"] != "done", killed

        service.start_worker("worker-1")  # another host: the checkpoint can only come from the bucket
        done = wait_for(api, job["id"], finished, timeout=120)
        assert done["state"] == "succeeded" and done["attempts"] == 2, done
        assert api.get(f"/v1/jobs/{job['id']}/result").content == expected

        events = _events(api, job["id"])
        assert [e["state"] for e in events if e["kind"] == "state"] == [
            "queued", "running", "queued", "running", "succeeded"
        ]  # fmt: skip
        second = max(i for i, e in enumerate(events) if e["kind"] == "state" and e["state"] == "running")
        detected = [i for i, e in enumerate(events) if "detecting mirrors" in e["message"]]
        assert detected and all(i < second for i in detected), "the second run searched the levels again"

        assert api.delete(f"/v1/jobs/{job['id']}").status_code == 204
        client = service.server.client()
        assert service.server.keys(prefix) == []
        assert service.unfinished_uploads(client, prefix) == []


def test_a_kill_while_results_are_written_serves_no_part_of_a_file_and_deletes_every_part(
    service: S3Service, large_scene: Path
) -> None:
    from symgs_core.export.formats import EXPORTS
    from symgs_core.pipeline import decompress

    _kill_workers(service)
    service.start_worker("worker-2", env=SWEEP_ONCE)
    client = service.server.client()
    with client_for(service.stack, KEY_A) as api:
        job = submit(api, large_scene, LARGE).json()
        prefix = service.job_prefix(owner_of(KEY_A), job["id"])
        # The first multipart upload of a result: kill the worker while its parts go up.
        deadline = time.monotonic() + 180
        while not service.unfinished_uploads(client, prefix + "result/"):
            assert time.monotonic() < deadline, "no result went up in parts"
            assert not finished(api.get(f"/v1/jobs/{job['id']}").json()), "the results were written before a kill"
            time.sleep(0.01)
        _kill_workers(service)
        left = service.unfinished_uploads(client, prefix + "result/")
        assert left, "the upload completed before the kill"
        running = api.get(f"/v1/jobs/{job['id']}")
        assert running.json()["state"] == "running"
        for name in ("result", "result.ply", "result.glb", "report"):
            answer = api.get(f"/v1/jobs/{job['id']}/{name}")
            assert answer.status_code == 409 and answer.json()["error"]["code"] == "not_ready", answer.text

        store = JobStore.from_url(service.stack.redis_url)
        while store.leases.held(job["id"]):  # expired, the first sweep of the next worker takes the job over
            time.sleep(0.1)
        service.start_worker("worker-3", env=SWEEP_ONCE)
        done = wait_for(api, job["id"], finished, timeout=180)
        assert done["state"] == "succeeded" and done["attempts"] == 2, done
        archive = api.get(f"/v1/jobs/{job['id']}/result").content
        report = json.loads(api.get(f"/v1/jobs/{job['id']}/report").content)
        decoded = decompress(archive)
        assert len(archive) == report["output_bytes"] and len(decoded) == report["gaussians"]["decoded"]
        for fmt in EXPORTS:  # every export is the whole of what the archive decodes to
            if fmt.artifact in done["artifacts"]:
                assert api.get(f"/v1/jobs/{job['id']}/{fmt.artifact}").content == fmt.write(decoded), fmt.artifact

        assert api.delete(f"/v1/jobs/{job['id']}").status_code == 204
        assert service.server.keys(prefix) == []
        assert service.unfinished_uploads(client, prefix) == [], "the killed worker's parts stay in the bucket"
