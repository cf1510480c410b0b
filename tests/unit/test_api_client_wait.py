"""SymgsClient.wait rides out an API that answers 503 for a while (its Redis restarting), as the API's Retry-After
asks, and reports the job's real final state; it gives up once its patience is spent, and at once on other errors."""

from __future__ import annotations

import socket
import time

import httpx
import pytest

from service.client import ApiClientError, SymgsClient
from tests.unit._scripted_api import ScriptedApi, events, job, serving, unavailable

JOB = "5" * 32


def test_wait_retries_503_on_the_stream_and_the_poll_then_reports_the_final_job() -> None:
    api = ScriptedApi({
        f"GET /v1/jobs/{JOB}/events": [unavailable("1"), events(("1", "running")), events(("2", "succeeded"))],
        f"GET /v1/jobs/{JOB}": [unavailable("0"), job(JOB, "succeeded", ("result.symgs",))],
    })  # fmt: skip
    seen: list[str] = []
    with serving(api) as url, SymgsClient(url) as client:
        start = time.monotonic()
        final = client.wait(JOB, on_event=lambda event: seen.append(event.state))
        elapsed = time.monotonic() - start
    assert final.state == "succeeded" and final.artifacts == ["result.symgs"]
    assert seen == ["running", "succeeded"]
    # the stream was taken up again after the last event seen, once the API's one second had passed
    assert [headers.get("last-event-id") for headers in api.asked(f"GET /v1/jobs/{JOB}/events")] == [None, None, "1"]
    assert 1.0 <= elapsed < 10


def test_wait_gives_up_on_503_once_its_patience_is_spent() -> None:
    api = ScriptedApi({f"GET /v1/jobs/{JOB}/events": [unavailable("5")]})
    with serving(api) as url, SymgsClient(url, patience=0.3) as client:
        start = time.monotonic()
        with pytest.raises(ApiClientError) as raised:
            client.wait(JOB)
        elapsed = time.monotonic() - start
    assert (raised.value.status, raised.value.code, raised.value.retry_after) == (503, "unavailable", 5.0)
    assert 0.3 <= elapsed < 3  # the Retry-After of 5 s is cut to the patience left


def test_wait_does_not_retry_other_errors() -> None:
    api = ScriptedApi({})
    with serving(api) as url, SymgsClient(url) as client, pytest.raises(ApiClientError) as raised:
        client.wait(JOB)
    assert raised.value.status == 404 and len(api.requests) == 1


def test_wait_gives_up_on_a_server_out_of_reach_once_its_patience_is_spent() -> None:
    with socket.socket() as probe:  # a port nothing listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with SymgsClient(f"http://127.0.0.1:{port}", patience=0.3) as client, pytest.raises(httpx.ConnectError):
        client.wait(JOB)
