"""Redis or the storage out of reach: the API answers 503 JSON (``unavailable``, ``storage_unavailable``) with
Retry-After, keeps no files of a refused submission, and serves again once they are back. A stack of its own (Redis
and the API; no worker needed)."""

from __future__ import annotations

import json
import shutil
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import pytest

from service.cli.stack import LocalStack
from tests.integration.conftest import KEY_A, TINY, read_sse

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def outage_stack() -> Iterator[LocalStack]:
    stack = LocalStack(env={"SYMGS_API_KEYS": KEY_A}, durable_redis=True)
    try:
        stack.start_redis()
        stack.start_api()
        yield stack
    finally:
        stack.cleanup()


def _files(stack: LocalStack) -> list[str]:
    storage = stack.root / "storage"
    return sorted(p.relative_to(storage).as_posix() for p in storage.rglob("*")) if storage.exists() else []


def test_redis_down_answers_503_and_leaves_no_files(outage_stack: LocalStack, small_ply: bytes) -> None:
    api = httpx.Client(base_url=outage_stack.api_url, headers={"Authorization": f"Bearer {KEY_A}"}, timeout=60)
    data = {"params": json.dumps(TINY)}
    accepted = api.post("/v1/jobs", files={"scene": ("s.ply", small_ply)}, data=data)
    assert accepted.status_code == 202, accepted.text
    job_id = accepted.json()["id"]
    before = _files(outage_stack)

    outage_stack.stop_redis()
    for method, path in (("GET", f"/v1/jobs/{job_id}"), ("GET", "/v1/jobs"), ("POST", f"/v1/jobs/{job_id}:cancel"),
                         ("GET", f"/v1/jobs/{job_id}/result"), ("GET", "/metrics")):  # fmt: skip
        response = api.request(method, path)
        assert response.status_code == 503, (path, response.text)
        assert response.json()["error"]["code"] == "unavailable" and response.headers["retry-after"] == "5"
    for headers in ({}, {"Idempotency-Key": "outage-1"}):
        refused = api.post("/v1/jobs", files={"scene": ("s.ply", small_ply)}, data=data, headers=headers)
        assert refused.status_code == 503, refused.text
        assert refused.json()["error"]["code"] == "unavailable"
    assert _files(outage_stack) == before, "a refused submission left files behind"
    assert api.get("/readyz").status_code == 503 and api.get("/healthz").status_code == 200

    outage_stack.start_redis()
    assert api.get(f"/v1/jobs/{job_id}").json()["state"] == "queued"  # the append-only file kept it
    again = api.post("/v1/jobs", files={"scene": ("s.ply", small_ply)}, data=data)
    assert again.status_code == 202, again.text
    api.close()


def test_storage_out_of_reach_answers_503(outage_stack: LocalStack, small_ply: bytes) -> None:
    """A disk that cannot take an upload or give a file back (full, read-only, unmounted: here a file where a folder
    belongs, and the reverse) is a 503 storage_unavailable, before any byte of a download is sent."""
    api = httpx.Client(base_url=outage_stack.api_url, headers={"Authorization": f"Bearer {KEY_A}"}, timeout=60)
    data = {"params": json.dumps(TINY)}
    accepted = api.post("/v1/jobs", files={"scene": ("s.ply", small_ply)}, data=data)
    assert accepted.status_code == 202, accepted.text
    job_id = accepted.json()["id"]
    storage = outage_stack.root / "storage"
    (scene,) = (p for p in storage.rglob("scene.ply") if job_id in p.parts)
    aside = scene.with_name("aside.ply")
    scene.rename(aside)
    scene.mkdir()
    broken = api.get(f"/v1/jobs/{job_id}/scene")
    assert broken.status_code == 503, broken.text
    assert broken.json()["error"]["code"] == "storage_unavailable" and broken.headers["retry-after"] == "5"
    scene.rmdir()
    aside.rename(scene)
    assert api.get(f"/v1/jobs/{job_id}/scene").content == small_ply

    staging = storage / "staging"
    shutil.rmtree(staging, ignore_errors=True)
    staging.write_bytes(b"")
    refused = api.post("/v1/jobs", files={"scene": ("s.ply", small_ply)}, data=data)
    assert refused.status_code == 503, refused.text
    assert refused.json()["error"]["code"] == "storage_unavailable"
    staging.unlink()
    assert api.post("/v1/jobs", files={"scene": ("s.ply", small_ply)}, data=data).status_code == 202
    api.close()


def test_an_upload_declared_over_the_cap_is_refused_before_its_body(outage_stack: LocalStack) -> None:
    """A client that asks before sending (``Expect: 100-continue``, as curl does for large bodies) gets the 413 at
    once instead of a go-ahead and a read of what it sends."""
    url = urlsplit(outage_stack.api_url)
    head = (f"POST /v1/jobs HTTP/1.1\r\nHost: {url.netloc}\r\nAuthorization: Bearer {KEY_A}\r\n"
            "Content-Type: multipart/form-data; boundary=b\r\nContent-Length: 1000000000000\r\n"
            "Expect: 100-continue\r\n\r\n")  # fmt: skip
    with socket.create_connection((url.hostname, url.port), timeout=30) as sock:
        sock.sendall(head.encode())
        answer = b""
        while chunk := sock.recv(65536):  # the server closes: it will not read a body it refused
            answer += chunk
    assert answer.startswith(b"HTTP/1.1 413"), answer[:200]
    assert b"upload_too_large" in answer


def test_a_submission_during_a_redis_restart_waits_and_makes_one_job(
    outage_stack: LocalStack, tmp_path: Path, small_ply: bytes
) -> None:
    """The client tries again as the 503's Retry-After asks, every try under one Idempotency-Key: the job is made
    once Redis is back, and only once."""
    from service.client import SymgsClient

    scene = tmp_path / "s.ply"
    scene.write_bytes(small_ply)
    api = httpx.Client(base_url=outage_stack.api_url, headers={"Authorization": f"Bearer {KEY_A}"}, timeout=60)
    before = api.get("/v1/jobs", params={"limit": 100}).json()["total"]
    outage_stack.stop_redis()
    restart = threading.Timer(3.0, outage_stack.start_redis)
    restart.start()
    try:
        with SymgsClient(outage_stack.api_url, KEY_A, patience=60) as client:
            job = client.submit(scene, params=TINY)
    finally:
        restart.join()
    assert job.state == "queued"
    assert api.get("/v1/jobs", params={"limit": 100}).json()["total"] == before + 1
    api.close()


def test_an_event_stream_ends_cleanly_when_redis_goes_away(outage_stack: LocalStack, small_ply: bytes) -> None:
    """The stream of a waiting job ends, its body whole, when Redis goes: the client reconnects with the last id it
    has, as SSE clients do, rather than reading a body cut short."""
    api = httpx.Client(base_url=outage_stack.api_url, headers={"Authorization": f"Bearer {KEY_A}"}, timeout=60)
    accepted = api.post("/v1/jobs", files={"scene": ("s.ply", small_ply)}, data={"params": json.dumps(TINY)})
    assert accepted.status_code == 202, accepted.text
    outcome: dict = {}

    def follow() -> None:
        try:
            with api.stream("GET", f"/v1/jobs/{accepted.json()['id']}/events") as response:
                outcome["messages"] = read_sse(response)
        except Exception as exc:  # noqa: BLE001 - what the client would see, kept for the assertion
            outcome["error"] = exc

    reader = threading.Thread(target=follow)
    reader.start()
    time.sleep(1.0)  # the stream has sent the job's first event and waits for more
    outage_stack.stop_redis()
    reader.join(timeout=30)
    outage_stack.start_redis()
    assert not reader.is_alive(), "the stream did not end"
    assert "error" not in outcome, outcome
    assert [json.loads(m["data"])["state"] for m in outcome["messages"]] == ["queued"]
    api.close()
