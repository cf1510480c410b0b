"""Redis out of reach: the API answers 503 JSON ``unavailable`` with Retry-After, keeps no files of a refused
submission, and serves again once Redis is back. A stack of its own (Redis and the API; no worker needed)."""

from __future__ import annotations

import json
from collections.abc import Iterator

import httpx
import pytest

from service.cli.stack import LocalStack
from tests.integration.conftest import KEY_A, TINY

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
