"""Credentials the object storage refuses (an S3 server that checks signatures, as every real one does): the API
answers 503 storage_unavailable without naming the key, secret, endpoint or bucket, reports its storage not ready and
logs that the credentials were refused. A worker whose credentials are refused does not start, and says why; one whose
key is revoked while it runs fails the job cleanly as storage_unavailable once its runs are spent, and goes on
living."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.cli.stack import StackError
from tests.integration.conftest import KEY_A, TINY, finished, read_sse, submit, wait_for
from tests.integration.s3_hosts import PREFIX, S3Service, enforce_credentials, revoke, s3_service
from tests.s3_server import BUCKET

WRONG_SECRET = "wr0ng-secret-of-the-api-4c1d"
UNKNOWN_KEY = {"AWS_ACCESS_KEY_ID": "AKIAUNKNOWNUNKNOWN42", "AWS_SECRET_ACCESS_KEY": "an-unknown-secret-77e1"}


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[S3Service, dict[str, str], dict[str, str]]]:
    # Two runs a job: a worker whose credentials are refused fails it within seconds.
    with s3_service(tmp_path_factory.mktemp("hosts"), env={"SYMGS_MAX_ATTEMPTS": "2"}) as running:
        credentials, revocable = enforce_credentials(running.server)
        running.stack.env.update(credentials)
        yield running, credentials, revocable


def _leaks(text: str, credentials: dict[str, str], endpoint: str) -> list[str]:
    """What of the storage's configuration ``text`` gives away."""
    secrets = [*credentials.values(), *UNKNOWN_KEY.values(), WRONG_SECRET, endpoint, endpoint.split("//")[1],
               BUCKET, f"{PREFIX}/tenants"]  # fmt: skip
    return [s for s in secrets if s in text]


def test_an_api_whose_credentials_are_refused_answers_503_and_says_why_in_its_log(
    service: tuple[S3Service, dict[str, str], dict[str, str]], scene_path: Path
) -> None:
    running, credentials, _ = service
    good_url = running.start_api("api")
    running.start_worker("worker")
    with httpx.Client(base_url=good_url, headers={"Authorization": f"Bearer {KEY_A}"}, timeout=60) as good:
        response = submit(good, scene_path, TINY)
        assert response.status_code == 202, response.text
        job = wait_for(good, response.json()["id"], finished)
        assert job["state"] == "succeeded", job
        assert httpx.get(f"{good_url}/readyz").status_code == 200

    bad_url = running.start_api("api-wrong-secret", env={"AWS_SECRET_ACCESS_KEY": WRONG_SECRET})
    log = running.stack.children[-1].log
    with httpx.Client(base_url=bad_url, headers={"Authorization": f"Bearer {KEY_A}"}, timeout=60) as bad:
        answers = {
            "submit": submit(bad, scene_path, TINY),
            "result": bad.get(f"/v1/jobs/{job['id']}/result"),
            "export": bad.get(f"/v1/jobs/{job['id']}/result.ply"),
            "report": bad.get(f"/v1/jobs/{job['id']}/report"),
            "scene": bad.get(f"/v1/jobs/{job['id']}/scene"),
        }
        for what, answer in answers.items():
            assert answer.status_code == 503, (what, answer.status_code, answer.text)
            assert answer.json()["error"]["code"] == "storage_unavailable", (what, answer.text)
            assert not _leaks(answer.text, credentials, running.server.endpoint), (what, answer.text)
        # What needs only Redis still answers.
        assert bad.get(f"/v1/jobs/{job['id']}").json()["state"] == "succeeded"

    ready = httpx.get(f"{bad_url}/readyz")
    assert ready.status_code == 503 and ready.json()["storage"] is False and ready.json()["redis"] is True, ready.text
    assert not _leaks(ready.text, credentials, running.server.endpoint), ready.text

    text = log.read_text(errors="replace")
    assert "Traceback" not in text, text
    assert "refused the credentials" in text, text
    assert "SignatureDoesNotMatch" in text, text  # the server's own word, to look up
    assert WRONG_SECRET not in text and credentials["AWS_SECRET_ACCESS_KEY"] not in text


def test_a_worker_whose_credentials_are_refused_does_not_start(
    service: tuple[S3Service, dict[str, str], dict[str, str]],
) -> None:
    """It would take jobs only to spend their runs failing (on several hosts, one misconfigured worker would fail
    many); it exits with the reason instead, and the operator's restart policy shows it."""
    running, credentials, _ = service
    with pytest.raises(StackError, match="exited with status 2"):
        running.start_worker("worker-unknown-key", env=UNKNOWN_KEY)
    worker = running.stack.workers.pop()
    text = worker.log.read_text(errors="replace")
    assert "the storage refuses this worker: the storage refused the credentials (InvalidAccessKeyId)" in text, text
    assert "Traceback" not in text, text
    assert UNKNOWN_KEY["AWS_SECRET_ACCESS_KEY"] not in text and credentials["AWS_SECRET_ACCESS_KEY"] not in text


def test_a_worker_whose_key_is_revoked_fails_the_job_cleanly(
    service: tuple[S3Service, dict[str, str], dict[str, str]], scene_path: Path
) -> None:
    running, credentials, revocable = service
    for worker in list(running.stack.workers):
        worker.stop()
        running.stack.workers.remove(worker)
    api_url = running.start_api("api-for-worker")
    worker = running.start_worker("worker-revoked-key", env=revocable)
    revoke(running.server, credentials, revocable)
    with httpx.Client(base_url=api_url, headers={"Authorization": f"Bearer {KEY_A}"}, timeout=60) as api:
        response = submit(api, scene_path, TINY)
        assert response.status_code == 202, response.text
        job = wait_for(api, response.json()["id"], finished, timeout=90)
        assert job["state"] == "failed", job
        assert job["error"]["code"] == "storage_unavailable", job
        assert job["attempts"] == 2, job
        leaked = _leaks(json.dumps(job), credentials, running.server.endpoint)
        assert not leaked and revocable["AWS_SECRET_ACCESS_KEY"] not in json.dumps(job), job
        with api.stream("GET", f"/v1/jobs/{job['id']}/events") as events:
            states = [json.loads(m["data"])["state"] for m in read_sse(events) if m.get("event") == "state"]
        assert states == ["queued", "running", "queued", "running", "failed"], states

    assert worker.alive()
    text = worker.log.read_text(errors="replace")
    assert "refused the credentials" in text and "InvalidAccessKeyId" in text, text
    assert revocable["AWS_SECRET_ACCESS_KEY"] not in text
