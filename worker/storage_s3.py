"""Job files in an S3-compatible bucket: ``SYMGS_STORAGE=s3://bucket/prefix``.

The client is boto3's, configured by the standard AWS settings (``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``,
``AWS_DEFAULT_REGION``, ``AWS_ENDPOINT_URL`` for MinIO and other S3-compatible servers, or the AWS config files).
Files larger than one part go up and down as multipart transfers, streamed from and to disk. Nothing is shared on
disk between processes: the API receives an upload into its own local cache and sends it to the bucket; a worker
copies a job's inputs and checkpoints into its own cache, sends each new checkpoint back as the job advances (so
another worker can resume it), and removes its copy when the run ends.
"""

from __future__ import annotations

import io
import logging
import os
import re
import shutil
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path, PurePosixPath
from typing import Any

from .storage import (
    CHUNK_BYTES,
    Artifact,
    Storage,
    StorageError,
    Workspace,
    check_artifact,
    is_artifact,
    job_key,
    sweep_folders,
)

log = logging.getLogger(__name__)
_URL = re.compile(r"^s3://(?P<bucket>[a-z0-9][a-z0-9.-]{1,61}[a-z0-9])(?:/(?P<prefix>.*))?$")
PART_BYTES = 8 << 20  # multipart threshold and part size (S3's minimum part is 5 MiB)
TRANSFERS = 8  # files moved at once when a job's folder goes up or down
_TOUCH_EVERY_S = 60.0  # a workspace in use is marked fresh this often, so a sweep never takes it
# Characters of a key that DeleteObjects' XML body cannot carry as they are: those outside XML 1.0's Char production,
# and the control characters it admits but a parser may change (a carriage return reads back as a line feed).
_NOT_IN_XML = re.compile("[^\n\u0020-\ud7ff\ue000-\ufffd\U00010000-\U0010ffff]")


def parse_url(url: str) -> tuple[str, str]:
    """``s3://bucket/some/prefix`` -> (bucket, "some/prefix"); ValueError for anything else."""
    match = _URL.match(url)
    if match is None:
        raise ValueError(f"expected s3://bucket/prefix with a valid bucket name, got {url!r}")
    prefix = (match["prefix"] or "").strip("/")
    if prefix and any(part in ("", ".", "..") for part in prefix.split("/")):
        raise ValueError(f"the prefix of {url!r} has an empty, '.' or '..' segment")
    return match["bucket"], prefix


def make_client() -> Any:  # noqa: ANN401 - botocore's generated S3 client class
    """An S3 client from the standard AWS settings. A custom endpoint (MinIO, moto, ...) is addressed path-style:
    such servers rarely resolve bucket names as host names."""
    import boto3
    from botocore.config import Config

    custom = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL")
    config = Config(
        # A server that hangs must not hold an API request or a worker's sweep for minutes (botocore's defaults: 60 s
        # a read, five tries): a request fails within about half a minute, and the API answers 503.
        connect_timeout=5, read_timeout=10,
        retries={"mode": "standard", "max_attempts": 3},
        max_pool_connections=32,
        s3={"addressing_style": "path"} if custom else None,
    )
    return boto3.session.Session().client("s3", config=config)


# Answers of a server that will not take this process's credentials: no retry mends them, an operator must.
_REFUSED_CREDENTIALS = {"InvalidAccessKeyId", "SignatureDoesNotMatch", "ExpiredToken", "InvalidToken",
                        "TokenRefreshRequired"}  # fmt: skip
_REFUSED_ACCESS = {"AccessDenied", "AllAccessDisabled", "AccountProblem", "403"}  # "403": a HEAD's bodiless answer


def _refusal(exc: BaseException) -> str | None:
    """Why the server refused this process, in words an operator can act on; None for an outage or a missing object.
    Looks through the wrapping of boto3's managed transfers (S3UploadFailedError keeps the ClientError as context)."""
    from botocore.exceptions import ClientError, NoCredentialsError, PartialCredentialsError

    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, NoCredentialsError | PartialCredentialsError):
            return "this process has no complete credentials; set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY"
        if isinstance(seen, ClientError):
            code = str(seen.response.get("Error", {}).get("Code", ""))
            if code in _REFUSED_CREDENTIALS:
                return f"the storage refused the credentials ({code}); check AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY"
            if code in _REFUSED_ACCESS:
                return f"the storage refused access ({code}): wrong credentials, or no permission on the bucket"
            if code == "NoSuchBucket":
                return "the bucket does not exist; create it, or check SYMGS_STORAGE"
            return None
        seen = seen.__cause__ or seen.__context__
    return None


@contextmanager
def _s3_errors(what: str) -> Iterator[None]:
    from boto3.exceptions import Boto3Error
    from botocore.exceptions import BotoCoreError, ClientError

    try:
        yield
    except (BotoCoreError, ClientError, Boto3Error) as exc:
        refused = _refusal(exc)
        raise StorageError(f"object storage: {what}: {refused + ': ' if refused else ''}{exc}") from exc


def _missing(exc: BaseException | None) -> bool:
    from botocore.exceptions import ClientError

    gone = ("NoSuchKey", "NoSuchUpload", "404")
    return isinstance(exc, ClientError) and exc.response.get("Error", {}).get("Code") in gone


def _local(folder: Path, relative: str) -> Path:
    """Where an object named ``relative`` (below a job's prefix) goes in a local folder; never outside it."""
    parts = PurePosixPath(relative).parts
    if not parts or any(p in ("", ".", "..") for p in parts) or relative.startswith("/"):
        raise StorageError(f"object storage: refusing object name {relative!r}")
    return folder.joinpath(*parts)


def _stream(body: Any) -> Iterator[bytes]:  # noqa: ANN401 - botocore StreamingBody
    try:
        yield from body.iter_chunks(CHUNK_BYTES)
    finally:
        body.close()


class S3Storage(Storage):
    def __init__(self, bucket: str, prefix: str, *, cache: Path, client: Any = None, part_bytes: int = PART_BYTES):  # noqa: ANN401
        from boto3.s3.transfer import TransferConfig

        self.bucket, self.prefix = bucket, prefix.strip("/")
        self.cache = Path(cache)
        self.client = client if client is not None else make_client()
        self.transfer = TransferConfig(multipart_threshold=part_bytes, multipart_chunksize=part_bytes)
        self._unready: str | None = None  # why the last readiness check failed

    @classmethod
    def from_url(cls, url: str, *, cache: Path) -> S3Storage:
        bucket, prefix = parse_url(url)
        return cls(bucket, prefix, cache=cache)

    def key_root(self) -> str:
        """The start of every key the service writes: ``<prefix>/tenants/`` (``tenants/`` without a prefix)."""
        return "/".join(p for p in (self.prefix, "tenants") if p) + "/"

    def key(self, owner: str, job_id: str, *parts: str) -> str:
        return "/".join(p for p in (self.prefix, job_key(owner, job_id), *parts) if p)

    def _list(self, prefix: str) -> Iterator[dict]:
        with _s3_errors(f"listing {prefix}"):
            for page in self.client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=prefix):
                yield from page.get("Contents", ())

    def _each(self, fn: Callable[[Any], None], items: Iterable[Any]) -> None:
        """Run ``fn`` on every item, several at once; the first failure is raised once all have ended."""
        with ThreadPoolExecutor(TRANSFERS) as pool:
            for future in [pool.submit(fn, item) for item in items]:
                future.result()

    def upload_folder(self, folder: Path, prefix: str) -> None:
        def put(path: Path) -> None:
            with _s3_errors(f"uploading {path.name}"):
                key = f"{prefix}/{path.relative_to(folder).as_posix()}"
                self.client.upload_file(str(path), self.bucket, key, Config=self.transfer)

        self._each(put, (p for p in folder.rglob("*") if p.is_file() and not p.is_symlink()))

    def download_folder(self, prefix: str, folder: Path) -> None:
        def get(obj: dict) -> None:
            target = _local(folder, obj["Key"][len(prefix) + 1 :])
            target.parent.mkdir(parents=True, exist_ok=True)
            with _s3_errors(f"downloading {obj['Key']}"):
                self.client.download_file(self.bucket, obj["Key"], str(target), Config=self.transfer)

        self._each(get, list(self._list(prefix + "/")))

    # -- the API ----------------------------------------------------------------------------------------------

    def new_staging(self) -> Path:
        path = self.cache / "staging" / uuid.uuid4().hex
        path.mkdir(parents=True)
        return path

    def adopt(self, staging: Path, *, owner: str, job_id: str) -> None:
        try:  # what is written before a failure, the caller deletes (or has the sweep delete)
            self.upload_folder(staging, self.key(owner, job_id, "upload"))
        finally:
            shutil.rmtree(staging, ignore_errors=True)

    def open_artifact(self, *, owner: str, job_id: str, name: str) -> Artifact | None:
        return self._open(self.key(owner, job_id, "result", check_artifact(name)), name)

    def open_upload(self, *, owner: str, job_id: str) -> Artifact | None:
        return self._open(self.key(owner, job_id, "upload", "scene.ply"), "the uploaded scene")

    def _open(self, key: str, name: str) -> Artifact | None:
        try:
            with _s3_errors(f"reading {name}"):
                got = self.client.get_object(Bucket=self.bucket, Key=key)
        except StorageError as exc:
            if _missing(exc.__cause__):
                return None
            raise
        return Artifact(int(got["ContentLength"]), _stream(got["Body"]))

    def artifact_names(self, *, owner: str, job_id: str) -> list[str]:
        prefix = self.key(owner, job_id, "result") + "/"
        names = (obj["Key"][len(prefix) :] for obj in self._list(prefix))
        return sorted(n for n in names if is_artifact(n))

    # -- the workers ------------------------------------------------------------------------------------------

    def workspace(self, *, owner: str, job_id: str) -> Workspace:
        return _S3Workspace(self, owner, job_id)

    def write_artifact(self, *, owner: str, job_id: str, name: str, data: bytes) -> None:
        key = self.key(owner, job_id, "result", check_artifact(name))
        with _s3_errors(f"writing {name}"):
            self.client.upload_fileobj(io.BytesIO(data), self.bucket, key, Config=self.transfer)

    # -- both -------------------------------------------------------------------------------------------------

    def delete(self, *, owner: str, job_id: str) -> None:
        prefix = self.key(owner, job_id) + "/"
        keys = [obj["Key"] for obj in self._list(prefix)]
        # DeleteObjects carries its keys raw in an XML body: a key XML cannot hold (stored before names were checked
        # at upload) fails the whole request, or one with a carriage return reads back as another key and stays.
        # Those go one by one, in the request's path.
        batch = [{"Key": key} for key in keys if not _NOT_IN_XML.search(key)]
        for start in range(0, len(batch), 1000):  # DeleteObjects takes at most 1000 keys
            with _s3_errors(f"deleting job {job_id}"):
                self.client.delete_objects(Bucket=self.bucket, Delete={"Objects": batch[start : start + 1000]})
        for key in (key for key in keys if _NOT_IN_XML.search(key)):
            with _s3_errors(f"deleting job {job_id}"):
                self.client.delete_object(Bucket=self.bucket, Key=key)
        # A worker killed while a file went up in parts leaves those parts, which no listing of objects shows: a
        # deleted job must keep none of its bytes, nor wait for the sweep of stale uploads hours later.
        for upload in self._unfinished(prefix):
            self._abort(upload)

    def _unfinished(self, prefix: str) -> list[dict]:
        """Multipart uploads under ``prefix`` that were begun and never completed nor aborted."""
        with _s3_errors("listing unfinished uploads"):
            pages = self.client.get_paginator("list_multipart_uploads").paginate(Bucket=self.bucket, Prefix=prefix)
            return [upload for page in pages for upload in page.get("Uploads", ())]

    def _abort(self, upload: dict) -> None:
        try:
            with _s3_errors("aborting an unfinished upload"):
                self.client.abort_multipart_upload(Bucket=self.bucket, Key=upload["Key"], UploadId=upload["UploadId"])
        except StorageError as exc:
            if not _missing(exc.__cause__):  # NoSuchUpload: another process aborted or completed it meanwhile
                raise

    def _probe(self) -> StorageError | None:
        """What a one-key listing of the service's objects fails with, None when it answers. A listing, not a HEAD:
        its refusal names its reason (a HEAD's answer has no body), and the service lists."""
        try:
            with _s3_errors("checking the bucket"):
                self.client.list_objects_v2(Bucket=self.bucket, Prefix=self.key_root(), MaxKeys=1)
        except StorageError as exc:
            return exc
        return None

    def reachable(self) -> bool:
        if (failed := self._probe()) is not None:
            if str(failed) != self._unready:  # probed every few seconds: a line when the reason changes, not each time
                log.error("storage not ready: %s", failed)
            self._unready = str(failed)
            return False
        if self._unready is not None:
            log.warning("storage ready again")
        self._unready = None
        return True

    def refused(self) -> str | None:
        failed = self._probe()
        return None if failed is None else _refusal(failed)

    def sweep_staging(self, older_than_s: float) -> int:
        """Local folders of dead processes, and multipart uploads that a dead process never completed (a bucket
        keeps, and bills, their parts until they are aborted)."""
        removed = sweep_folders(self.cache / "staging", older_than_s) + sweep_folders(self.cache / "jobs", older_than_s)
        cutoff = datetime.fromtimestamp(time.time() - older_than_s, UTC)
        # the service's own uploads only: under the prefix as a folder, in the jobs' layout
        stale = [upload for upload in self._unfinished(self.key_root()) if upload["Initiated"] < cutoff]
        for upload in stale:
            self._abort(upload)
        return removed + len(stale)


class _S3Workspace(Workspace):
    def __init__(self, storage: S3Storage, owner: str, job_id: str) -> None:
        self.storage, self.prefix = storage, storage.key(owner, job_id)
        self.folder = storage.cache / "jobs" / f"{job_id}-{uuid.uuid4().hex[:8]}"
        self._pushed: dict[str, tuple[int, int]] = {}  # checkpoint name -> (mtime_ns, size) in the bucket
        self._touched = 0.0

    def __enter__(self) -> _S3Workspace:
        self.folder.mkdir(parents=True)
        try:
            for part in ("upload", "checkpoints"):
                self.storage.download_folder(f"{self.prefix}/{part}", self.folder / part)
        except BaseException:
            shutil.rmtree(self.folder, ignore_errors=True)
            raise
        self._pushed = {path.name: _stamp(path) for path in self._checkpoints()}
        self._touched = time.monotonic()
        return self

    def _checkpoints(self) -> list[Path]:
        folder = self.folder / "checkpoints"
        return [p for p in folder.iterdir() if p.is_file()] if folder.is_dir() else []

    def save_checkpoints(self) -> None:
        for path in self._checkpoints():
            stamp = _stamp(path)
            if self._pushed.get(path.name) != stamp:
                with _s3_errors(f"saving checkpoint {path.name}"):
                    key = f"{self.prefix}/checkpoints/{path.name}"
                    self.storage.client.upload_file(str(path), self.storage.bucket, key, Config=self.storage.transfer)
                self._pushed[path.name] = stamp
        if time.monotonic() - self._touched > _TOUCH_EVERY_S:
            os.utime(self.folder)
            self._touched = time.monotonic()

    def __exit__(self, *exc: object) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)


def _stamp(path: Path) -> tuple[int, int]:
    st = path.stat()
    return st.st_mtime_ns, st.st_size
