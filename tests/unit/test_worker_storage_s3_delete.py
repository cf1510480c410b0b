"""Deleting a job on S3 storage leaves none of its bytes: its objects, and the parts of a file that a worker killed
mid-upload began and never completed (no listing of objects shows them, and the bucket keeps them until they are
aborted). The uploads of other jobs stay."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.s3_server import BUCKET, S3Server, start_s3_server
from worker.storage_s3 import S3Storage

OWNER = "0f1e2d3c4b5a69788796a5b4"
JOB, OTHER = "0123456789abcdef0123456789abcdef", "fedcba9876543210fedcba9876543210"


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Server]:
    running = start_s3_server(tmp_path_factory.mktemp("s3"))
    yield running
    running.child.stop()


def _begin_upload(storage: S3Storage, job_id: str, name: str) -> None:
    """What a worker killed while a result went up in parts leaves: an upload begun, a part sent, never completed."""
    key = storage.key(OWNER, job_id, "result", name)
    upload = storage.client.create_multipart_upload(Bucket=BUCKET, Key=key)
    storage.client.upload_part(Bucket=BUCKET, Key=key, UploadId=upload["UploadId"], PartNumber=1, Body=b"p" * 1024)


def _unfinished(storage: S3Storage) -> list[str]:
    return sorted(u["Key"] for u in storage.client.list_multipart_uploads(Bucket=BUCKET).get("Uploads", ()))


def test_deleting_a_job_aborts_its_unfinished_uploads_and_no_other_jobs(server: S3Server, tmp_path: Path) -> None:
    storage = S3Storage(BUCKET, "deploy", cache=tmp_path, client=server.client())
    storage.write_artifact(owner=OWNER, job_id=JOB, name="result.symgs", data=b"archive")
    _begin_upload(storage, JOB, "result.ply")
    _begin_upload(storage, JOB, "result.glb")
    _begin_upload(storage, OTHER, "result.ply")

    storage.delete(owner=OWNER, job_id=JOB)

    assert server.keys(storage.key(OWNER, JOB)) == []
    assert _unfinished(storage) == [storage.key(OWNER, OTHER, "result", "result.ply")]
    storage.delete(owner=OWNER, job_id=JOB)  # nothing left: nothing to do
    storage.delete(owner=OWNER, job_id=OTHER)
    assert _unfinished(storage) == []


def test_a_job_whose_keys_xml_cannot_carry_is_deleted_whole(server: S3Server, tmp_path: Path) -> None:
    """Names stored before names were checked at upload: DeleteObjects carries keys raw in XML, which a control
    character or a non-character breaks (the request fails, on every try) and a carriage return changes (another
    key is deleted, and the object stays). Such keys go one by one; the rest in a batch."""
    storage = S3Storage(BUCKET, "deploy", cache=tmp_path, client=server.client())
    names = ["a\x01b.txt", "a\x1bb.txt", "a\ufffeb.txt", "a\rb.txt", "a\tb.txt", "plain.png"]
    for name in names:
        key = storage.key(OWNER, JOB, "upload", "images", "notes", name)
        storage.client.put_object(Bucket=BUCKET, Key=key, Body=b"x")
    storage.write_artifact(owner=OWNER, job_id=OTHER, name="result.symgs", data=b"other")

    storage.delete(owner=OWNER, job_id=JOB)

    assert server.keys(storage.key(OWNER, JOB)) == []
    assert server.keys(storage.key(OWNER, OTHER)) == [storage.key(OWNER, OTHER, "result", "result.symgs")]
    storage.delete(owner=OWNER, job_id=OTHER)
