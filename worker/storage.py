"""Files of jobs: uploads, checkpoints and results, behind one interface with two backends.

``DirectoryStorage`` keeps them in a folder that the API and every worker mount; ``S3Storage``
(``storage_s3.py``) in an S3-compatible bucket, so that API and workers share no disk. Both use one layout, under
the folder or the bucket's prefix::

    tenants/<owner>/jobs/<id>/upload/        scene.ply and images/ (the extracted dataset), as accepted
    tenants/<owner>/jobs/<id>/checkpoints/   per-level checkpoints of the pipeline; a rerun resumes from them
    tenants/<owner>/jobs/<id>/result/        result.symgs, report.json, charts/<name>.png, and result<extension>
                                             for each export format (``symgs_core.export.formats``)

``<owner>`` is the digest of the API key that created the job (``anonymous`` without keys). An upload is received
into a local staging folder (under the directory, or the process's cache for S3) and becomes the job's ``upload/``
once checked. Results are written under fixed names, whole or not at all, so a rerun overwrites and a reader never
sees half a file.
"""

from __future__ import annotations

import os
import re
import shutil
import time
import uuid
from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from symgs_core.export.formats import EXPORTS

_EXPORTED = "|".join(re.escape(fmt.artifact) for fmt in EXPORTS)
_ARTIFACT = re.compile(rf"^(result\.symgs|{_EXPORTED}|report\.json|charts/[A-Za-z0-9_-]{{1,64}}\.png)$")
_JOB_ID = re.compile(r"^[0-9a-f]{32}$")
_OWNER = re.compile(r"^[0-9a-z_-]{1,64}$")
CHUNK_BYTES = 1 << 20  # read size when a result is streamed to a client
# Stored names (a dataset's files, below a job's upload/images/) become object keys and file names as they are: S3
# keys are at most 1024 bytes, whole, prefix and job folder included; a file name, 255 bytes on the disks caches use.
MAX_NAME_BYTES = 512
MAX_PART_BYTES = 255


class StorageError(OSError):
    """The storage backend failed or is unreachable (the API answers 503)."""


@contextmanager
def disk_errors() -> Iterator[None]:
    """A failing disk (full, read-only, unmounted, a folder where a file belongs) raised as StorageError, as the S3
    backend raises its failures, so that the API answers 503 and not an unexplained 500."""
    try:
        yield
    except StorageError:
        raise
    except OSError as exc:
        raise StorageError(f"{type(exc).__name__}: {exc}") from exc


def check_job_id(job_id: str) -> str:
    if not _JOB_ID.match(job_id):
        raise ValueError(f"job ids are 32 lowercase hex digits, got {job_id!r}")
    return job_id


def check_owner(owner: str) -> str:
    if not _OWNER.match(owner):
        raise ValueError(f"owner ids are 1 to 64 of [0-9a-z_-], got {owner!r}")
    return owner


def check_artifact(name: str) -> str:
    if not _ARTIFACT.match(name):
        raise ValueError(f"unknown artifact name {name!r}")
    return name


def stored_name_problem(name: str) -> str | None:
    """Why ``name`` (a path below a job's folder, parts split by "/") may not name a stored file; None when it may.

    The one rule for every name a client chooses: printable characters only, none of the control characters, format
    characters, surrogates or non-characters that ``str.isprintable`` leaves out (S3 carries a key raw in the XML of
    DeleteObjects, which XML parsers refuse, or read back changed: a carriage return comes back a line feed), and a
    bounded length."""
    parts = name.split("/")
    if any(part in ("", ".", "..") for part in parts):
        return "has an empty, '.' or '..' folder"
    if not name.isprintable():
        bad = next(c for c in name if not c.isprintable())
        return f"holds the character U+{ord(bad):04X}, which is not printable"
    if len(name.encode()) > MAX_NAME_BYTES:
        return f"is longer than {MAX_NAME_BYTES} bytes"
    if any(len(part.encode()) > MAX_PART_BYTES for part in parts):
        return f"has a folder or file name longer than {MAX_PART_BYTES} bytes"
    return None


def is_artifact(name: str) -> bool:
    return _ARTIFACT.match(name) is not None


def job_key(owner: str, job_id: str) -> str:
    """The job's folder relative to the storage root: ``tenants/<owner>/jobs/<id>``."""
    return f"tenants/{check_owner(owner)}/jobs/{check_job_id(job_id)}"


@dataclass
class Artifact:
    """A result file opened for reading: its size, and its bytes in chunks (the source is closed at the end)."""

    size: int
    chunks: Iterator[bytes]


class Workspace(AbstractContextManager):
    """A job's local folder for the worker to compute in: ``folder/upload`` holds the inputs and
    ``folder/checkpoints`` the pipeline's checkpoints; ``save_checkpoints`` makes new ones durable."""

    folder: Path

    def save_checkpoints(self) -> None:
        """Store checkpoints written since the last call where another worker would find them; cheap when
        nothing changed, so it may be called on every progress event."""

    def __exit__(self, *exc: object) -> None:
        return None


class Storage(ABC):
    """What the API and the workers need from artifact storage. Job methods take the owner and the job id."""

    @abstractmethod
    def new_staging(self) -> Path:
        """An empty local folder to receive one upload into."""

    @abstractmethod
    def adopt(self, staging: Path, *, owner: str, job_id: str) -> None:
        """Make a checked staging folder the job's ``upload/`` (the staging folder is gone afterwards). Should it fail
        part way, what it wrote stays: the caller deletes the job's files."""

    def discard(self, staging: Path) -> None:
        """Remove a staging folder whose upload was refused."""
        shutil.rmtree(staging, ignore_errors=True)

    @abstractmethod
    def workspace(self, *, owner: str, job_id: str) -> Workspace:
        """The job's local folder, with its upload and checkpoints, for the worker (a context manager)."""

    @abstractmethod
    def open_upload(self, *, owner: str, job_id: str) -> Artifact | None:
        """The scene as uploaded (``upload/scene.ply``), opened for reading; None when the job has none."""

    @abstractmethod
    def write_artifact(self, *, owner: str, job_id: str, name: str, data: bytes) -> None:
        """Write a result file whole; a rerun overwrites it."""

    @abstractmethod
    def open_artifact(self, *, owner: str, job_id: str, name: str) -> Artifact | None:
        """A result file to stream to a client, or None when it does not exist."""

    @abstractmethod
    def artifact_names(self, *, owner: str, job_id: str) -> list[str]:
        """Names of the result files present, sorted."""

    @abstractmethod
    def delete(self, *, owner: str, job_id: str) -> None:
        """Remove every file of a job; nothing happens when there is none."""

    @abstractmethod
    def sweep_staging(self, older_than_s: float) -> int:
        """Remove what dead processes left behind (uploads never adopted, local copies of jobs); how many."""

    @abstractmethod
    def reachable(self) -> bool:
        """Whether files can be written now (the API's readiness): the folder, or the bucket, answers."""

    @abstractmethod
    def refused(self) -> str | None:
        """Why this process may not use the storage at all, in words an operator can act on (credentials refused,
        no permission, no such bucket); None when it may, or when only an outage stops it now."""


def read_chunks(f: BinaryIO) -> Iterator[bytes]:
    with f:
        while chunk := f.read(CHUNK_BYTES):
            yield chunk


def open_file(path: Path) -> Artifact | None:
    """``path`` opened for streaming, or None when it does not exist. Opened here, before a response starts, so
    that a file that cannot be read is a 503 and not a 200 cut short."""
    with disk_errors():
        try:
            f = open(path, "rb")  # noqa: SIM115 - closed by read_chunks
        except FileNotFoundError:
            return None
        try:
            size = os.fstat(f.fileno()).st_size
        except OSError:
            f.close()
            raise
    return Artifact(size, read_chunks(f))


def sweep_folders(parent: Path, older_than_s: float) -> int:
    """Remove the subfolders of ``parent`` last modified more than ``older_than_s`` ago; how many."""
    cutoff = time.time() - older_than_s
    removed = 0
    for path in parent.iterdir() if parent.is_dir() else ():
        try:
            if path.stat().st_mtime < cutoff:
                shutil.rmtree(path, ignore_errors=True)
                removed += 1
        except FileNotFoundError:  # removed by another sweeper meanwhile
            continue
    return removed


class _DirectoryWorkspace(Workspace):
    def __init__(self, folder: Path) -> None:
        self.folder = folder


class DirectoryStorage(Storage):
    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root).resolve()  # folders are made on first write

    def job_dir(self, owner: str, job_id: str) -> Path:
        return self.root / job_key(owner, job_id)

    def new_staging(self) -> Path:
        path = self.root / "staging" / uuid.uuid4().hex
        with disk_errors():
            path.mkdir(parents=True)
        return path

    def adopt(self, staging: Path, *, owner: str, job_id: str) -> None:
        job = self.job_dir(owner, job_id)
        with disk_errors():
            job.mkdir(parents=True, exist_ok=True)
            os.replace(staging, job / "upload")

    def workspace(self, *, owner: str, job_id: str) -> Workspace:
        return _DirectoryWorkspace(self.job_dir(owner, job_id))

    def write_artifact(self, *, owner: str, job_id: str, name: str, data: bytes) -> None:
        path = self.job_dir(owner, job_id) / "result" / check_artifact(name)
        partial = path.with_name(f".{path.name}.{uuid.uuid4().hex}.part")
        with disk_errors():
            path.parent.mkdir(parents=True, exist_ok=True)
            partial.write_bytes(data)
            os.replace(partial, path)

    def open_artifact(self, *, owner: str, job_id: str, name: str) -> Artifact | None:
        return open_file(self.job_dir(owner, job_id) / "result" / check_artifact(name))

    def open_upload(self, *, owner: str, job_id: str) -> Artifact | None:
        return open_file(self.job_dir(owner, job_id) / "upload" / "scene.ply")

    def artifact_names(self, *, owner: str, job_id: str) -> list[str]:
        result = self.job_dir(owner, job_id) / "result"
        if not result.is_dir():
            return []
        names = (p.relative_to(result).as_posix() for p in result.rglob("*") if p.is_file())
        return sorted(n for n in names if is_artifact(n))

    def delete(self, *, owner: str, job_id: str) -> None:
        shutil.rmtree(self.job_dir(owner, job_id), ignore_errors=True)

    def sweep_staging(self, older_than_s: float) -> int:
        return sweep_folders(self.root / "staging", older_than_s)

    def reachable(self) -> bool:
        # folders are made on first write: the nearest one that exists must take them
        existing = next(p for p in (self.root, *self.root.parents) if p.exists())
        return existing.is_dir() and os.access(existing, os.W_OK | os.X_OK)

    def refused(self) -> str | None:
        return None if self.reachable() else "this process cannot write the storage folder"
