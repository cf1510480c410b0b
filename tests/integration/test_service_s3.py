"""The service on s3:// storage, with a standalone S3 server process: the API and the worker run from different
folders with different HOME and TMPDIR, so they share no disk. A job succeeds, its result downloads and decodes,
its objects are in the bucket under the tenant's and the job's prefix, another key gets 404, and deleting the job
empties its prefix."""

from __future__ import annotations

import io
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.api.auth import owner_of
from service.cli.stack import LocalStack
from tests.integration.conftest import KEY_A, KEY_B, TINY, client_for, finished, submit, wait_for
from tests.integration.s3_hosts import PREFIX, host_folder
from tests.s3_server import BUCKET, S3Server, start_s3_server


@pytest.fixture(scope="module")
def s3_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[LocalStack, S3Server, Path]]:
    root = tmp_path_factory.mktemp("hosts")
    stack = LocalStack(env={"SYMGS_API_KEYS": f"{KEY_A},{KEY_B}"}, storage=f"s3://{BUCKET}/{PREFIX}")
    try:
        stack.start_redis()
        server = start_s3_server(stack.root)
        stack.children.append(server.child)
        stack.env.update(server.env())
        api_dir, api_env = host_folder(root, "api")
        stack.start_api(env=api_env, cwd=api_dir)
        worker_dir, worker_env = host_folder(root, "worker")
        stack.start_worker("cpu", env=worker_env, cwd=worker_dir)
        yield stack, server, root
    finally:
        stack.cleanup()


def test_job_on_s3_storage_runs_downloads_and_lives_in_the_bucket(
    s3_stack: tuple[LocalStack, S3Server, Path], scene_path: Path
) -> None:
    from symgs_core.pipeline import decompress

    stack, server, root = s3_stack
    with client_for(stack, KEY_A) as api, client_for(stack, KEY_B) as other:
        response = submit(api, scene_path)
        assert response.status_code == 202, response.text
        job = wait_for(api, response.json()["id"], finished)
        assert job["state"] == "succeeded", job

        archive = api.get(f"/v1/jobs/{job['id']}/result")
        assert archive.status_code == 200 and archive.headers["content-length"] == str(len(archive.content))
        decoded = decompress(archive.content)
        assert len(decoded) > 0 and decoded.sh_degree == 1
        ply = api.get(f"/v1/jobs/{job['id']}/result.ply")
        assert ply.status_code == 200 and ply.content.startswith(b"ply\n")
        assert other.get(f"/v1/jobs/{job['id']}/result").status_code == 404

        prefix = f"{PREFIX}/tenants/{owner_of(KEY_A)}/jobs/{job['id']}/"
        keys = [key.removeprefix(prefix) for key in server.keys(prefix)]
        assert {"upload/scene.ply", "checkpoints/levels.pt", "result/result.symgs", "result/report.json"} <= set(keys)
        assert {f"result/{name}" for name in job["artifacts"]} <= set(keys)
        stored = server.client().get_object(Bucket=BUCKET, Key=prefix + "result/result.symgs")["Body"].read()
        assert stored == archive.content
        assert server.keys(f"{PREFIX}/tenants/{owner_of(KEY_B)}/") == []

        # Nothing of the job stays on either host: the upload left the API's cache, the inputs the worker's.
        for host in ("api", "worker"):
            cache = root / host / "tmp" / "symgs-cache"
            assert not [p for p in cache.rglob("*") if p.is_file()], f"{host} kept files: {list(cache.rglob('*'))}"
            assert not (root / host / "symgs-data").exists()

        assert api.delete(f"/v1/jobs/{job['id']}").status_code == 204
        assert server.keys(prefix) == []


def test_a_refused_upload_leaves_nothing_in_the_bucket(s3_stack: tuple[LocalStack, S3Server, Path]) -> None:
    stack, server, _ = s3_stack
    before = server.keys()
    with client_for(stack, KEY_A) as api:
        response = api.post(
            "/v1/jobs", files={"scene": ("bad.ply", b"ply\nformat ascii 1.0\nend_header\n")}, data={"params": "{}"}
        )
    assert response.status_code == 422, response.text
    assert server.keys() == before


def test_a_dataset_file_name_no_key_may_carry_is_refused_at_the_door(
    s3_stack: tuple[LocalStack, S3Server, Path], scene_path: Path
) -> None:
    """A name S3's DeleteObjects cannot carry made its job undeletable, and stopped expiry for every tenant."""
    stack, server, _ = s3_stack
    before = server.keys()
    images = io.BytesIO()
    with zipfile.ZipFile(images, "w") as zf:
        zf.writestr("scene/transforms.json", '{"camera_angle_x": 0.7, "frames": []}')
        zf.writestr("scene/notes/a\x01b.txt", "notes")
    with client_for(stack, KEY_A) as api:
        files = {"scene": ("scene.ply", scene_path.read_bytes()), "images": ("images.zip", images.getvalue())}
        response = api.post("/v1/jobs", files=files, data={"params": "{}"})
    assert response.status_code == 422 and response.json()["error"]["code"] == "bad_name", response.text
    assert server.keys() == before


def test_storage_outage_is_a_503(s3_stack: tuple[LocalStack, S3Server, Path], scene_path: Path) -> None:
    """With the S3 server gone, a submission is refused with a machine-readable 503, not a crash."""
    stack, server, _ = s3_stack
    server.child.stop()
    with client_for(stack, KEY_A) as api:
        response = submit(api, scene_path, TINY)
        assert response.status_code == 503, response.text
        assert response.json()["error"]["code"] == "storage_unavailable"
        assert httpx.get(f"{stack.api_url}/healthz").status_code == 200
