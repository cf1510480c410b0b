"""S3 storage against a standalone S3 server process (moto's server mode on loopback): the tenant/job layout,
multipart transfers, workspaces that copy a job in and send checkpoints back, streaming reads, deletion, the sweep
of unfinished uploads, and hostile object names."""

from __future__ import annotations

import hashlib
import os
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.s3_server import BUCKET, S3Server, start_s3_server
from worker.storage import StorageError
from worker.storage_s3 import S3Storage, parse_url

JOB = "0123456789abcdef0123456789abcdef"
OWNER = "0f1e2d3c4b5a69788796a5b4"
PREFIX = "deploy/eu"
PART = 5 << 20  # S3's smallest part


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Server]:
    running = start_s3_server(tmp_path_factory.mktemp("s3"))
    yield running
    running.child.stop()


def _storage(server: S3Server, cache: Path, bucket: str = BUCKET) -> S3Storage:
    return S3Storage(bucket, PREFIX, cache=cache, client=server.client(), part_bytes=PART)


def _job_keys(server: S3Server, owner: str = OWNER, job_id: str = JOB) -> list[str]:
    prefix = f"{PREFIX}/tenants/{owner}/jobs/{job_id}/"
    return [key[len(prefix) :] for key in server.keys(prefix)]


def test_urls_name_a_bucket_and_a_prefix() -> None:
    assert parse_url("s3://symgs-jobs") == ("symgs-jobs", "")
    assert parse_url("s3://symgs-jobs/prod/eu/") == ("symgs-jobs", "prod/eu")
    for bad in ("s3://Upper/x", "s3://ab", "s3://symgs-jobs/a/../b", "s3://symgs-jobs/a//b", "gs://symgs-jobs/x"):
        with pytest.raises(ValueError):
            parse_url(bad)


def test_upload_goes_to_the_bucket_and_a_workspace_on_another_host_gets_it(server: S3Server, tmp_path: Path) -> None:
    api = _storage(server, tmp_path / "api-cache")
    staging = api.new_staging()
    big = os.urandom(PART + 1000)  # two parts
    (staging / "scene.ply").write_bytes(big)
    (staging / "images" / "lego" / "train").mkdir(parents=True)
    (staging / "images" / "lego" / "train" / "r_0.png").write_bytes(b"png")
    api.adopt(staging, owner=OWNER, job_id=JOB)
    assert not staging.exists()
    assert _job_keys(server) == ["upload/images/lego/train/r_0.png", "upload/scene.ply"]
    head = server.client().head_object(Bucket=BUCKET, Key=f"{PREFIX}/tenants/{OWNER}/jobs/{JOB}/upload/scene.ply")
    assert head["ETag"].endswith('-2"'), head["ETag"]  # a multipart upload of two parts

    worker = _storage(server, tmp_path / "worker-cache")
    with worker.workspace(owner=OWNER, job_id=JOB) as work:
        assert work.folder.is_relative_to(tmp_path / "worker-cache")
        assert (work.folder / "upload" / "scene.ply").read_bytes() == big
        assert (work.folder / "upload" / "images" / "lego" / "train" / "r_0.png").read_bytes() == b"png"
        checkpoint = work.folder / "checkpoints" / "levels.pt"
        checkpoint.parent.mkdir()
        checkpoint.write_bytes(b"level 0")
        work.save_checkpoints()
        assert "checkpoints/levels.pt" in _job_keys(server)
        checkpoint.write_bytes(b"level 0, level 1")
        work.save_checkpoints()
        folder = work.folder
    assert not folder.exists()

    # A worker that takes the job over resumes from the last checkpoint saved.
    with _storage(server, tmp_path / "third-cache").workspace(owner=OWNER, job_id=JOB) as work:
        assert (work.folder / "checkpoints" / "levels.pt").read_bytes() == b"level 0, level 1"


def test_results_stream_back_per_tenant_and_are_deleted(server: S3Server, tmp_path: Path) -> None:
    storage = _storage(server, tmp_path)
    large = os.urandom(2 * PART + 123)
    storage.write_artifact(owner=OWNER, job_id=JOB, name="result.ply", data=large)
    storage.write_artifact(owner=OWNER, job_id=JOB, name="result.symgs", data=b"first")
    storage.write_artifact(owner=OWNER, job_id=JOB, name="result.symgs", data=b"second")
    storage.write_artifact(owner=OWNER, job_id=JOB, name="charts/rate_distortion.png", data=b"png")
    names = storage.artifact_names(owner=OWNER, job_id=JOB)
    assert names == ["charts/rate_distortion.png", "result.ply", "result.symgs"]

    artifact = storage.open_artifact(owner=OWNER, job_id=JOB, name="result.ply")
    chunks = list(artifact.chunks)
    assert artifact.size == len(large) and len(chunks) > 1
    assert hashlib.sha256(b"".join(chunks)).digest() == hashlib.sha256(large).digest()
    assert b"".join(storage.open_artifact(owner=OWNER, job_id=JOB, name="result.symgs").chunks) == b"second"
    assert storage.open_artifact(owner="anonymous", job_id=JOB, name="result.symgs") is None
    assert storage.open_artifact(owner=OWNER, job_id=JOB, name="report.json") is None
    with pytest.raises(ValueError, match="artifact"):
        storage.open_artifact(owner=OWNER, job_id=JOB, name="../upload/scene.ply")

    storage.delete(owner=OWNER, job_id=JOB)
    assert _job_keys(server) == [] and storage.artifact_names(owner=OWNER, job_id=JOB) == []
    storage.delete(owner=OWNER, job_id=JOB)  # nothing left: no error


def test_unfinished_uploads_and_stale_local_copies_are_swept(server: S3Server, tmp_path: Path) -> None:
    storage = _storage(server, tmp_path)
    key = f"{PREFIX}/tenants/{OWNER}/jobs/{JOB}/result/result.ply"
    server.client().create_multipart_upload(Bucket=BUCKET, Key=key)  # its process died before completing it
    # Not the service's: beside the prefix (same start, another folder), and under it outside the jobs' layout
    theirs = [f"{PREFIX}2/tenants/{OWNER}/jobs/{JOB}/result/result.ply", f"{PREFIX}/backups/b.tar"]
    for other in theirs:
        server.client().create_multipart_upload(Bucket=BUCKET, Key=other)
    old, fresh = storage.new_staging(), storage.new_staging()
    past = time.time() - 7200
    os.utime(old, (past, past))
    # moto dates every multipart upload in 2010, so the upload counts as stale here.
    assert storage.sweep_staging(3600) == 2
    assert not old.exists() and fresh.exists()
    left = server.client().list_multipart_uploads(Bucket=BUCKET, Prefix=PREFIX).get("Uploads", [])
    assert sorted(u["Key"] for u in left) == sorted(theirs)
    for upload in left:
        server.client().abort_multipart_upload(Bucket=BUCKET, Key=upload["Key"], UploadId=upload["UploadId"])


def test_a_bucket_is_reachable_when_it_answers(server: S3Server, tmp_path: Path) -> None:
    assert _storage(server, tmp_path).reachable()
    assert not _storage(server, tmp_path, bucket="no-such-bucket").reachable()
    # A worker does not start where the bucket is missing (a configuration an operator must mend); an outage, which
    # may pass, does not keep it from starting.
    assert _storage(server, tmp_path).refused() is None
    assert _storage(server, tmp_path, bucket="no-such-bucket").refused() == (
        "the bucket does not exist; create it, or check SYMGS_STORAGE"
    )
    import boto3
    from botocore.config import Config

    from service.cli.stack import free_port

    nobody = boto3.session.Session(aws_access_key_id="k", aws_secret_access_key="s", region_name="us-east-1").client(
        "s3", endpoint_url=f"http://127.0.0.1:{free_port()}", config=Config(retries={"max_attempts": 1})
    )
    assert S3Storage(BUCKET, PREFIX, cache=tmp_path, client=nobody).refused() is None


def test_hostile_object_names_never_leave_the_workspace(server: S3Server, tmp_path: Path) -> None:
    job = "f" * 32
    server.client().put_object(Bucket=BUCKET, Key=f"{PREFIX}/tenants/{OWNER}/jobs/{job}/upload/../../escape", Body=b"x")
    storage = _storage(server, tmp_path / "cache")
    with pytest.raises(StorageError, match="refusing object name"):
        with storage.workspace(owner=OWNER, job_id=job):
            pass
    assert not list((tmp_path / "cache" / "jobs").iterdir()) and not (tmp_path / "escape").exists()
    storage.delete(owner=OWNER, job_id=job)


def test_a_missing_bucket_is_a_storage_error(server: S3Server, tmp_path: Path) -> None:
    storage = _storage(server, tmp_path, bucket="no-such-bucket")
    with pytest.raises(StorageError, match="object storage: writing result.symgs"):
        storage.write_artifact(owner=OWNER, job_id=JOB, name="result.symgs", data=b"x")
