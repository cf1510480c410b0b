"""Files of jobs, shared by the API and the workers: uploads, checkpoints and results.

Layout under the root (a directory both sides mount)::

    staging/<token>/            an upload being received and checked, before it becomes a job
    jobs/<id>/upload/           scene.ply and images/ (the extracted dataset), as accepted
    jobs/<id>/checkpoints/      per-level checkpoints of the pipeline; a rerun resumes from them
    jobs/<id>/result/           result.symgs, report.json, charts/<name>.png, and result<extension> for each
                                export format (``symgs_core.export.formats``)

Results are written under fixed names, atomically (write then rename), so a rerun overwrites and a reader never
sees half a file.
"""

from __future__ import annotations

import os
import re
import shutil
import time
import uuid
from abc import ABC, abstractmethod
from pathlib import Path

from symgs_core.export.formats import EXPORTS

from .settings import Settings

_EXPORTED = "|".join(re.escape(fmt.artifact) for fmt in EXPORTS)
_ARTIFACT = re.compile(rf"^(result\.symgs|{_EXPORTED}|report\.json|charts/[A-Za-z0-9_-]{{1,64}}\.png)$")
_JOB_ID = re.compile(r"^[0-9a-f]{32}$")


def check_job_id(job_id: str) -> str:
    if not _JOB_ID.match(job_id):
        raise ValueError(f"job ids are 32 lowercase hex digits, got {job_id!r}")
    return job_id


def check_artifact(name: str) -> str:
    if not _ARTIFACT.match(name):
        raise ValueError(f"unknown artifact name {name!r}")
    return name


class Storage(ABC):
    """What the service needs from artifact storage. A backend on an object store would keep the same names and
    stage files locally for the worker (``job_dir``) and for the API (``artifact_path``)."""

    @abstractmethod
    def new_staging(self) -> Path:
        """An empty local folder to receive one upload into."""

    @abstractmethod
    def adopt(self, staging: Path, job_id: str) -> None:
        """Make a checked staging folder the job's ``upload/``."""

    @abstractmethod
    def discard(self, staging: Path) -> None:
        """Remove a staging folder whose upload was refused."""

    @abstractmethod
    def job_dir(self, job_id: str) -> Path:
        """The local folder of a job (``upload/``, ``checkpoints/``, ``result/``) for the worker to compute in."""

    def upload_path(self, job_id: str) -> Path | None:
        """A local path of the scene as uploaded (``upload/scene.ply``), or None when it does not exist."""
        path = self.job_dir(job_id) / "upload" / "scene.ply"
        return path if path.is_file() else None

    @abstractmethod
    def write_artifact(self, job_id: str, name: str, data: bytes) -> None:
        """Write a result file atomically; a rerun overwrites it."""

    @abstractmethod
    def artifact_path(self, job_id: str, name: str) -> Path | None:
        """A local path of a result file to serve, or None when it does not exist."""

    @abstractmethod
    def artifact_names(self, job_id: str) -> list[str]:
        """Names of the result files present, sorted."""

    @abstractmethod
    def delete(self, job_id: str) -> None:
        """Remove every file of a job; nothing happens when there is none."""

    @abstractmethod
    def sweep_staging(self, older_than_s: float) -> int:
        """Remove staging folders left behind (an API process died mid-upload); returns how many."""


class DirectoryStorage(Storage):
    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root).resolve()  # folders are made on first write

    def new_staging(self) -> Path:
        path = self.root / "staging" / uuid.uuid4().hex
        path.mkdir(parents=True)
        return path

    def adopt(self, staging: Path, job_id: str) -> None:
        job = self.job_dir(job_id)
        job.mkdir(parents=True, exist_ok=True)
        os.replace(staging, job / "upload")

    def discard(self, staging: Path) -> None:
        shutil.rmtree(staging, ignore_errors=True)

    def job_dir(self, job_id: str) -> Path:
        return self.root / "jobs" / check_job_id(job_id)

    def write_artifact(self, job_id: str, name: str, data: bytes) -> None:
        path = self.job_dir(job_id) / "result" / check_artifact(name)
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(f".{path.name}.{uuid.uuid4().hex}.part")
        partial.write_bytes(data)
        os.replace(partial, path)

    def artifact_path(self, job_id: str, name: str) -> Path | None:
        path = self.job_dir(job_id) / "result" / check_artifact(name)
        return path if path.is_file() else None

    def artifact_names(self, job_id: str) -> list[str]:
        result = self.job_dir(job_id) / "result"
        if not result.is_dir():
            return []
        names = (p.relative_to(result).as_posix() for p in result.rglob("*") if p.is_file())
        return sorted(n for n in names if _ARTIFACT.match(n))

    def delete(self, job_id: str) -> None:
        shutil.rmtree(self.job_dir(job_id), ignore_errors=True)

    def sweep_staging(self, older_than_s: float) -> int:
        cutoff = time.time() - older_than_s
        removed = 0
        staging = self.root / "staging"
        for path in staging.iterdir() if staging.is_dir() else ():
            try:
                if path.stat().st_mtime < cutoff:
                    shutil.rmtree(path, ignore_errors=True)
                    removed += 1
            except FileNotFoundError:  # removed by another sweeper meanwhile
                continue
        return removed


def storage_from_settings(settings: Settings) -> Storage:
    return DirectoryStorage(settings.storage)
