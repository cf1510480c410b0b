"""A whole job over HTTP: upload, progress events, results, and what clients may and may not see."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import torch

from api_schemas import Report
from tests.integration.conftest import TINY, finished, read_sse, submit, wait_for


def test_full_job_results_decode(done_job: dict, api_a: httpx.Client, scene_path: Path, tmp_path: Path) -> None:
    from symgs_core.export import read_spz, write_compressed_ply, write_spz
    from symgs_core.pipeline import decompress
    from symgs_core.ply import load_scene

    assert done_job["state"] == "succeeded", done_job
    assert done_job["progress"] == 1.0 and done_job["stage"] == "done" and done_job["error"] is None
    source = load_scene(scene_path)
    assert done_job["scene"] == {"filename": "mirrored.ply", "bytes": scene_path.stat().st_size,
                                 "gaussians": len(source), "sh_degree": 1}  # fmt: skip
    assert done_job["started_at"] >= done_job["created_at"] and done_job["finished_at"] >= done_job["started_at"]
    assert {"result.symgs", "result.ply", "result.spz", "result.compressed.ply", "report.json"} <= set(
        done_job["artifacts"]
    )

    report = api_a.get(f"/v1/jobs/{done_job['id']}/report").json()
    assert Report.model_validate(report).cameras.disjoint  # the contract the OpenAPI document shows
    metrics = done_job["metrics"]
    assert metrics["input_bytes"] == report["input_bytes"] == scene_path.stat().st_size
    assert metrics["output_bytes"] == report["output_bytes"]
    assert [m["level"] for m in done_job["mirrors"]] == [lv["level"] for lv in report["levels"] if lv["accepted"]]

    archive = api_a.get(f"/v1/jobs/{done_job['id']}/result")
    assert archive.status_code == 200 and archive.headers["content-type"] == "application/octet-stream"
    assert len(archive.content) == report["output_bytes"]
    decoded = decompress(archive.content)
    assert len(decoded) == report["gaussians"]["decoded"]

    ply = api_a.get(f"/v1/jobs/{done_job['id']}/result.ply")
    assert ply.status_code == 200
    (tmp_path / "result.ply").write_bytes(ply.content)
    downloaded = load_scene(tmp_path / "result.ply")
    for name, tensor in decoded.tensors().items():
        assert torch.equal(getattr(downloaded, name), tensor.float()), name

    spz = api_a.get(f"/v1/jobs/{done_job['id']}/result.spz")
    assert spz.status_code == 200 and torch.equal(read_spz(spz.content).means, read_spz(write_spz(decoded)).means)
    compressed = api_a.get(f"/v1/jobs/{done_job['id']}/result.compressed.ply")
    assert compressed.status_code == 200 and compressed.content == write_compressed_ply(decoded)
    for name in done_job["artifacts"]:
        if name.startswith("charts/"):
            chart = api_a.get(f"/v1/jobs/{done_job['id']}/{name}")
            assert chart.headers["content-type"] == "image/png" and chart.content.startswith(b"\x89PNG")
    missing = api_a.get(f"/v1/jobs/{done_job['id']}/charts/nope.png")
    assert missing.status_code == 404 and missing.json()["error"]["code"] == "artifact_missing"


def test_events_arrive_in_order_and_replay(done_job: dict, api_a: httpx.Client) -> None:
    url = f"/v1/jobs/{done_job['id']}/events"
    with api_a.stream("GET", url) as response:
        assert response.status_code == 200
        assert response.headers["content-type"].startswith("text/event-stream")
        messages = read_sse(response)
    events = [json.loads(m["data"]) for m in messages]
    states = [e["state"] for e in events if e["kind"] == "state"]
    assert states == ["queued", "running", "succeeded"]
    assert [m["event"] for m in messages] == [e["kind"] for e in events]
    ids = [tuple(map(int, m["id"].split("-"))) for m in messages]
    assert ids == sorted(ids) and len(set(ids)) == len(ids)
    progress = [e["progress"] for e in events]
    assert progress == sorted(progress) and progress[-1] == 1.0
    assert {e["stage"] for e in events if e["kind"] == "progress"} >= {"load", "levels", "encode"}
    # The time left: unknown in state events and in the first seconds of the run, then estimates, never negative
    left = [(e["time"], e["eta_s"]) for e in events if e["kind"] == "progress" and e["eta_s"] is not None]
    assert all(e["eta_s"] is None for e in events if e["kind"] == "state")
    assert left and all(eta >= 0 for _, eta in left), left
    assert left[0][0] - events[1]["time"] >= 2.0  # the worker estimates nothing in a job's first 2 s

    middle = len(messages) // 2
    with api_a.stream("GET", url, headers={"Last-Event-ID": messages[middle]["id"]}) as response:
        replay = read_sse(response)
    assert replay == messages[middle + 1 :]
    with api_a.stream("GET", url, headers={"Last-Event-ID": messages[-1]["id"]}) as response:
        assert read_sse(response) == []
    # The last ones are shaped like stream ids but not ones Redis can read after: past 64 bits, or its largest id
    largest = f"{2**64 - 1}-{2**64 - 1}"
    for bad_id in ("yesterday", f"{2**64}-0", f"0-{2**64}", "99999999999999999999-0", largest):
        bad = api_a.get(url, headers={"Last-Event-ID": bad_id})
        assert bad.status_code == 422 and bad.json()["error"]["code"] == "bad_last_event_id", bad_id
    with api_a.stream("GET", url, headers={"Last-Event-ID": f"{2**64 - 1}-0"}) as response:
        assert response.status_code == 200 and read_sse(response) == []


def test_api_keys_cannot_see_each_others_jobs(done_job: dict, api_b: httpx.Client, stack) -> None:  # noqa: ANN001
    job_id = done_job["id"]
    for method, path in [("GET", ""), ("GET", "/events"), ("GET", "/result"), ("GET", "/result.ply"),
                         ("GET", "/report"), ("POST", ":cancel"), ("DELETE", "")]:  # fmt: skip
        response = api_b.request(method, f"/v1/jobs/{job_id}{path}")
        assert response.status_code == 404, (method, path, response.text)
        assert response.json()["error"]["code"] == "not_found"
    assert job_id not in [j["id"] for j in api_b.get("/v1/jobs", params={"limit": 200}).json()["items"]]

    anonymous = httpx.get(f"{stack.api_url}/v1/jobs/{job_id}")
    assert anonymous.status_code == 401 and anonymous.headers["www-authenticate"] == "Bearer"
    assert anonymous.json()["error"]["code"] == "unauthorized"
    wrong = httpx.get(f"{stack.api_url}/v1/jobs", headers={"Authorization": "Bearer key-a-7f3"})
    assert wrong.status_code == 401


def test_idempotent_resubmission_returns_the_same_job(
    api_a: httpx.Client, api_b: httpx.Client, scene_path: Path
) -> None:
    params = {**TINY, "iterations": 5000}  # long enough to still be unfinished; cancelled below
    first = submit(api_a, scene_path, params, headers={"Idempotency-Key": "upload-42"})
    again = submit(api_a, scene_path, params, headers={"Idempotency-Key": "upload-42"})
    other_key = submit(api_b, scene_path, params, headers={"Idempotency-Key": "upload-42"})
    assert first.status_code == 202 and again.status_code == 200 and other_key.status_code == 202
    assert again.json()["id"] == first.json()["id"] != other_key.json()["id"]
    assert again.headers["location"] == first.headers["location"]
    for api, response in ((api_a, first), (api_b, other_key)):
        assert api.post(f"/v1/jobs/{response.json()['id']}:cancel").status_code == 202
    # A key that is empty, too long or holds control characters is refused by name, before the upload is read.
    for bad in (b"", b"k" * 256, b"upload\x0142", b"upload\x7f"):
        refused = submit(api_a, scene_path, params, headers={"Idempotency-Key": bad})
        assert refused.status_code == 422 and refused.json()["error"]["code"] == "bad_idempotency_key", refused.text


def test_list_paginates_and_filters_by_state(api_a: httpx.Client, done_job: dict) -> None:
    everything = api_a.get("/v1/jobs", params={"limit": 200}).json()
    assert everything["total"] == len(everything["items"]) >= 2 and everything["next_offset"] is None
    created = [j["created_at"] for j in everything["items"]]
    assert created == sorted(created, reverse=True)

    pages, offset = [], 0
    while offset is not None:
        page = api_a.get("/v1/jobs", params={"limit": 1, "offset": offset}).json()
        assert page["total"] == everything["total"] and len(page["items"]) == 1
        pages.append(page["items"][0]["id"])
        offset = page["next_offset"]
    assert pages == [j["id"] for j in everything["items"]]

    succeeded = api_a.get("/v1/jobs", params={"state": "succeeded", "limit": 200}).json()
    assert done_job["id"] in [j["id"] for j in succeeded["items"]]
    assert {j["state"] for j in succeeded["items"]} == {"succeeded"}
    assert succeeded["total"] == sum(j["state"] == "succeeded" for j in everything["items"])
    bad = api_a.get("/v1/jobs", params={"state": "sleeping"})
    assert bad.status_code == 422 and bad.json()["error"]["code"] == "invalid_request"


def test_retry_after_while_unfinished_and_results_not_ready(api_a: httpx.Client, scene_path: Path) -> None:
    job = submit(api_a, scene_path, {**TINY, "iterations": 5000}).json()
    running = wait_for(api_a, job["id"], lambda j: j["state"] == "running", timeout=120)
    response = api_a.get(f"/v1/jobs/{job['id']}")
    assert response.headers["retry-after"] == "2"
    early = api_a.get(f"/v1/jobs/{job['id']}/result")
    assert early.status_code == 409 and early.json()["error"]["code"] == "not_ready"
    assert early.headers["retry-after"] == "2"
    assert running["attempts"] == 1

    cancel = api_a.post(f"/v1/jobs/{job['id']}:cancel")
    assert cancel.status_code == 202 and cancel.json()["cancel_requested"] is True
    stopped = wait_for(api_a, job["id"], finished, timeout=30)
    assert stopped["state"] == "cancelled"
    assert stopped["finished_at"] - cancel.json()["updated_at"] < 15
    assert "retry-after" not in api_a.get(f"/v1/jobs/{job['id']}").headers
    gone = api_a.get(f"/v1/jobs/{job['id']}/result")
    assert gone.status_code == 409 and gone.json()["error"]["code"] == "no_result"
    assert api_a.post(f"/v1/jobs/{job['id']}:cancel").status_code == 200

    assert api_a.delete(f"/v1/jobs/{job['id']}").status_code == 204
    assert api_a.get(f"/v1/jobs/{job['id']}").status_code == 404


def test_health_readiness_and_metrics(api_a: httpx.Client, done_job: dict) -> None:
    assert api_a.get("/healthz").json() == {"status": "ok"}
    ready = api_a.get("/readyz")
    assert ready.status_code == 200 and ready.json()["redis"] is True and ready.json()["workers"]["cpu"] >= 1
    assert ready.json()["storage"] is True
    text = api_a.get("/metrics").text
    assert 'symgs_jobs{state="succeeded"}' in text
    assert 'symgs_queue_depth{queue="cpu"}' in text and 'symgs_workers{mode="cpu"}' in text
    count = next(line for line in text.splitlines() if line.startswith("symgs_job_duration_seconds_count"))
    assert float(count.split()[-1]) >= 1
