"""Directory storage: the tenant/job layout, fixed names, atomic overwrite, deletion, and nothing outside a job's
folder."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from worker.storage import DirectoryStorage, StorageError

JOB = "0123456789abcdef0123456789abcdef"
OWNER = "0f1e2d3c4b5a69788796a5b4"


def _read(storage: DirectoryStorage, name: str, owner: str = OWNER) -> bytes | None:
    artifact = storage.open_artifact(owner=owner, job_id=JOB, name=name)
    if artifact is None:
        return None
    data = b"".join(artifact.chunks)
    assert len(data) == artifact.size
    return data


def test_upload_is_adopted_and_results_overwrite(tmp_path: Path) -> None:
    storage = DirectoryStorage(tmp_path)
    staging = storage.new_staging()
    (staging / "scene.ply").write_bytes(b"ply")
    storage.adopt(staging, owner=OWNER, job_id=JOB)
    job = tmp_path / "tenants" / OWNER / "jobs" / JOB
    assert not staging.exists() and (job / "upload" / "scene.ply").read_bytes() == b"ply"
    with storage.workspace(owner=OWNER, job_id=JOB) as work:
        assert (work.folder / "upload" / "scene.ply").read_bytes() == b"ply"
        work.save_checkpoints()

    assert _read(storage, "result.symgs") is None and storage.artifact_names(owner=OWNER, job_id=JOB) == []
    storage.write_artifact(owner=OWNER, job_id=JOB, name="result.symgs", data=b"first")
    storage.write_artifact(owner=OWNER, job_id=JOB, name="result.symgs", data=b"second")
    storage.write_artifact(owner=OWNER, job_id=JOB, name="charts/rate_distortion.png", data=b"png")
    assert _read(storage, "result.symgs") == b"second"
    assert _read(storage, "result.symgs", owner="anonymous") is None  # another tenant's folder
    assert storage.artifact_names(owner=OWNER, job_id=JOB) == ["charts/rate_distortion.png", "result.symgs"]
    assert not [p for p in (job / "result").rglob("*.part")]

    storage.delete(owner=OWNER, job_id=JOB)
    assert not job.exists()
    storage.delete(owner=OWNER, job_id=JOB)  # nothing left: no error


def test_a_folder_storage_is_reachable_where_its_folders_can_be_made(tmp_path: Path) -> None:
    assert DirectoryStorage(tmp_path / "not" / "yet").reachable()  # made on first write
    (tmp_path / "afile").write_bytes(b"")
    assert not DirectoryStorage(tmp_path / "afile" / "below").reachable()
    # A worker checks this before it takes jobs, and does not start where it would fail every one.
    assert DirectoryStorage(tmp_path / "not" / "yet").refused() is None
    assert DirectoryStorage(tmp_path / "afile" / "below").refused() == "this process cannot write the storage folder"


def test_a_failing_disk_is_a_storage_error(tmp_path: Path) -> None:
    """A disk that cannot take or give a file (full, read-only, a folder where a file belongs) fails as StorageError,
    which the API answers with 503 storage_unavailable, and a file is opened before any byte of it is sent."""
    storage = DirectoryStorage(tmp_path)
    (tmp_path / "staging").write_bytes(b"")  # a file where the staging folder belongs
    with pytest.raises(StorageError):
        storage.new_staging()
    result = tmp_path / "tenants" / OWNER / "jobs" / JOB / "result"
    (result / "report.json").mkdir(parents=True)
    with pytest.raises(StorageError):
        storage.open_artifact(owner=OWNER, job_id=JOB, name="report.json")
    with pytest.raises(StorageError):
        storage.write_artifact(owner=OWNER, job_id=JOB, name="report.json", data=b"{}")
    (result / "charts").write_bytes(b"")  # a file where a folder belongs
    with pytest.raises(StorageError):
        storage.write_artifact(owner=OWNER, job_id=JOB, name="charts/a.png", data=b"png")


@pytest.mark.parametrize("name", ["../x", "result.symgs/../../x", "charts/../../a.png", "charts/a b.png", "other"])
def test_unknown_artifact_names_are_refused(tmp_path: Path, name: str) -> None:
    with pytest.raises(ValueError, match="artifact"):
        DirectoryStorage(tmp_path).write_artifact(owner=OWNER, job_id=JOB, name=name, data=b"x")


@pytest.mark.parametrize("job_id", ["../../etc", "ABCDEF0123456789abcdef0123456789", "abc", ""])
def test_job_ids_are_checked(tmp_path: Path, job_id: str) -> None:
    with pytest.raises(ValueError, match="32 lowercase hex"):
        DirectoryStorage(tmp_path).workspace(owner=OWNER, job_id=job_id)


@pytest.mark.parametrize("owner", ["..", "a/b", "", "A" * 65, "Anonymous"])
def test_owner_ids_are_checked(tmp_path: Path, owner: str) -> None:
    with pytest.raises(ValueError, match="owner ids"):
        DirectoryStorage(tmp_path).delete(owner=owner, job_id=JOB)


def test_stale_staging_is_swept(tmp_path: Path) -> None:
    storage = DirectoryStorage(tmp_path)
    old, fresh = storage.new_staging(), storage.new_staging()
    past = time.time() - 7200
    os.utime(old, (past, past))
    assert storage.sweep_staging(3600) == 1
    assert not old.exists() and fresh.exists()
