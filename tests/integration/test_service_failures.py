"""Failures tell the truth at the client: a bad input found by the worker is named by its code, the operations
routes want a key when keys are set, OPTIONS names the methods a path takes, and an Idempotency-Key is bound to
one request."""

from __future__ import annotations

import json
import struct
import time

import httpx

from tests.integration.conftest import TINY, finished, wait_for
from tests.integration.test_service_cli import symgs


def _nan_positions(ply: bytes) -> bytes:
    """The same scene with the first Gaussian's x set to NaN: the header is valid, so the API accepts it."""
    body = ply.index(b"end_header\n") + len(b"end_header\n")
    return ply[:body] + struct.pack("<f", float("nan")) + ply[body + 4 :]


def _logged_since(stack, sizes: dict, words: str, timeout: float = 10) -> str:  # noqa: ANN001
    """What the workers logged past ``sizes`` (log path -> bytes), once ``words`` is among it or time runs out."""
    deadline = time.monotonic() + timeout
    while True:
        added = "".join(w.log.read_bytes()[sizes.get(w.log, 0) :].decode(errors="replace") for w in stack.workers)
        if words in added or time.monotonic() > deadline:
            return added
        time.sleep(0.1)


def test_nan_positions_fail_as_non_finite(api_a: httpx.Client, small_ply: bytes, stack, tmp_path) -> None:  # noqa: ANN001
    sizes = {w.log: w.log.stat().st_size for w in stack.workers}
    response = api_a.post(
        "/v1/jobs", files={"scene": ("nan.ply", _nan_positions(small_ply))}, data={"params": json.dumps(TINY)}
    )
    assert response.status_code == 202, response.text
    job = wait_for(api_a, response.json()["id"], finished, timeout=60)
    assert job["state"] == "failed" and job["error"]["code"] == "non_finite", job["error"]
    assert "NaN" in job["error"]["message"] and "x (1 values)" in job["error"]["message"]
    assert job["error"]["message"].startswith("nan.ply: "), job["error"]  # the name it was sent by, not stored as
    # The input's fault is logged by the worker in a line, not as a crash with its traceback.
    logged = _logged_since(stack, sizes, "raised expected")
    assert "raised expected" in logged and "Traceback" not in logged, logged

    path = tmp_path / "nan.ply"
    path.write_bytes(_nan_positions(small_ply))
    run = symgs(stack, "submit", str(path), "--params", json.dumps(TINY))
    assert run.returncode == 1, run.stdout + run.stderr
    assert "nan.ply: failed: non_finite: " in run.stdout, run.stdout


def test_metrics_want_a_key(stack, api_a: httpx.Client) -> None:  # noqa: ANN001
    anonymous = httpx.get(f"{stack.api_url}/metrics")
    assert anonymous.status_code == 401 and anonymous.json()["error"]["code"] == "unauthorized"
    assert anonymous.headers["www-authenticate"] == "Bearer"
    assert api_a.get("/metrics").status_code == 200


def test_options_name_every_method_of_the_path(api_a: httpx.Client) -> None:
    job_id = "0" * 32
    expected = {f"/v1/jobs/{job_id}:cancel": "POST, OPTIONS", f"/v1/jobs/{job_id}": "GET, HEAD, DELETE, OPTIONS",
                "/v1/jobs": "GET, HEAD, POST, OPTIONS"}  # fmt: skip
    for path, allow in expected.items():
        response = api_a.options(path)
        assert (response.status_code, response.headers["allow"]) == (204, allow), path
    for method, path in (("GET", f"/v1/jobs/{job_id}:cancel"), ("PUT", f"/v1/jobs/{job_id}"), ("PATCH", "/v1/jobs")):
        wrong = api_a.request(method, path)
        assert wrong.status_code == 405 and wrong.headers["allow"] == expected[path], (method, path)
        assert wrong.json()["error"]["code"] == "method_not_allowed"


def test_head_answers_as_get_without_the_body(stack, done_job: dict, api_a: httpx.Client) -> None:  # noqa: ANN001
    for path in (f"/v1/jobs/{done_job['id']}", f"/v1/jobs/{done_job['id']}/result", "/healthz"):
        got, head = api_a.get(path), api_a.head(path)
        assert (head.status_code, head.content) == (got.status_code, b""), path
        assert head.headers["content-type"] == got.headers["content-type"], path
    assert api_a.head(f"/v1/jobs/{'0' * 32}").status_code == 404
    assert httpx.head(f"{stack.api_url}/v1/jobs").status_code == 401  # the GET's key check holds for HEAD


def test_a_reused_idempotency_key_with_another_request_is_refused(api_a: httpx.Client, small_ply: bytes) -> None:
    def post(params: dict, scene: bytes = small_ply) -> httpx.Response:
        files, data = {"scene": ("s.ply", scene)}, {"params": json.dumps(params)}
        return api_a.post("/v1/jobs", files=files, data=data, headers={"Idempotency-Key": "reuse-7"})

    params = {**TINY, "iterations": 5000}
    first = post(params)
    assert first.status_code == 202, first.text
    assert post(params).json()["id"] == first.json()["id"]
    for other in (post({**params, "iterations": 4000}), post(params, small_ply[:-4] + b"\0\0\0\0")):
        assert other.status_code == 422 and other.json()["error"]["code"] == "idempotency_key_reused", other.text
    assert api_a.post(f"/v1/jobs/{first.json()['id']}:cancel").status_code in (200, 202)


def test_photographs_of_another_scene_fail_as_images_mismatch(
    api_a: httpx.Client, scene_path, stack, tmp_path  # noqa: ANN001
) -> None:
    """The worker renders the upload against its photographs before any work: photographs of another scene are
    named by their code at the client, over HTTP and in the command line."""
    from symgs_core.bench.photos import photographed

    photographed("local", tmp_path / "shots", n=600, photos=6, tests=2, resolution=32)
    run = symgs(stack, "submit", str(scene_path), "--images", str(tmp_path / "shots"), "--params", json.dumps(TINY))
    assert run.returncode == 1, run.stdout + run.stderr
    assert f"{scene_path.name}: failed: images_mismatch: " in run.stdout, run.stdout
    failed = api_a.get("/v1/jobs", params={"state": "failed"}).json()
    codes = {job["error"]["code"] for job in failed["items"]}
    assert "images_mismatch" in codes, failed


def test_too_few_photographs_fail_as_too_few_images(api_a: httpx.Client, small_ply: bytes, stack, tmp_path) -> None:  # noqa: ANN001
    """Two photographs and no test split leave one to train and none to fit once every 8th is held out: the worker
    names that by its code (not ``internal_error``) and its message names no folder of the server."""
    from tests.integration.test_service_uploads import _nerf, _zip

    files = {"scene": ("s.ply", small_ply), "images": ("lego.zip", _zip(_nerf()))}
    response = api_a.post("/v1/jobs", files=files, data={"params": json.dumps(TINY)})
    assert response.status_code == 202, response.text
    job = wait_for(api_a, response.json()["id"], finished, timeout=60)
    assert job["state"] == "failed" and job["error"]["code"] == "too_few_images", job["error"]
    assert job["error"]["message"].startswith("lego: "), job["error"]

    for name, data in _nerf().items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_bytes(data)
    scene = tmp_path / "s.ply"
    scene.write_bytes(small_ply)
    run = symgs(stack, "submit", str(scene), "--images", str(tmp_path / "lego"), "--params", json.dumps(TINY))
    assert run.returncode == 1, run.stdout + run.stderr
    assert "s.ply: failed: too_few_images: " in run.stdout, run.stdout


def test_status_and_fetch_of_a_failed_job_name_its_code(api_a: httpx.Client, small_ply: bytes, stack, tmp_path) -> None:  # noqa: ANN001
    """``symgs status`` and ``symgs fetch`` of a job the worker failed name its code in full, whatever the width of
    the terminal (the status table cuts its cells)."""
    response = api_a.post(
        "/v1/jobs", files={"scene": ("nan.ply", _nan_positions(small_ply))}, data={"params": json.dumps(TINY)}
    )
    assert response.status_code == 202, response.text
    job = wait_for(api_a, response.json()["id"], finished, timeout=60)
    assert job["error"]["code"] == "non_finite", job

    shown = symgs(stack, "status", job["id"])
    assert shown.returncode == 0, shown.stdout + shown.stderr
    assert f"nan.ply: failed: non_finite: {job['error']['message']}" in shown.stdout, shown.stdout
    fetched = symgs(stack, "fetch", job["id"], "-o", str(tmp_path / "out"))
    assert fetched.returncode == 2, fetched.stdout + fetched.stderr
    assert f"is failed (non_finite: {job['error']['message']})" in fetched.stderr, fetched.stderr
