"""Directory storage: fixed names, atomic overwrite, deletion, and nothing outside a job's folder."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from worker.storage import DirectoryStorage

JOB = "0123456789abcdef0123456789abcdef"


def test_upload_is_adopted_and_results_overwrite(tmp_path: Path) -> None:
    storage = DirectoryStorage(tmp_path)
    staging = storage.new_staging()
    (staging / "scene.ply").write_bytes(b"ply")
    storage.adopt(staging, JOB)
    assert not staging.exists() and (storage.job_dir(JOB) / "upload" / "scene.ply").read_bytes() == b"ply"

    assert storage.artifact_path(JOB, "result.symgs") is None and storage.artifact_names(JOB) == []
    storage.write_artifact(JOB, "result.symgs", b"first")
    storage.write_artifact(JOB, "result.symgs", b"second")
    storage.write_artifact(JOB, "charts/rate_distortion.png", b"png")
    assert storage.artifact_path(JOB, "result.symgs").read_bytes() == b"second"
    assert storage.artifact_names(JOB) == ["charts/rate_distortion.png", "result.symgs"]
    assert not [p for p in (storage.job_dir(JOB) / "result").rglob("*.part")]

    storage.delete(JOB)
    assert not storage.job_dir(JOB).exists()
    storage.delete(JOB)  # nothing left: no error


@pytest.mark.parametrize("name", ["../x", "result.symgs/../../x", "charts/../../a.png", "charts/a b.png", "other"])
def test_unknown_artifact_names_are_refused(tmp_path: Path, name: str) -> None:
    with pytest.raises(ValueError, match="artifact"):
        DirectoryStorage(tmp_path).write_artifact(JOB, name, b"x")


@pytest.mark.parametrize("job_id", ["../../etc", "ABCDEF0123456789abcdef0123456789", "abc", ""])
def test_job_ids_are_checked(tmp_path: Path, job_id: str) -> None:
    with pytest.raises(ValueError, match="32 lowercase hex"):
        DirectoryStorage(tmp_path).job_dir(job_id)


def test_stale_staging_is_swept(tmp_path: Path) -> None:
    storage = DirectoryStorage(tmp_path)
    old, fresh = storage.new_staging(), storage.new_staging()
    past = time.time() - 7200
    os.utime(old, (past, past))
    assert storage.sweep_staging(3600) == 1
    assert not old.exists() and fresh.exists()
