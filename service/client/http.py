"""HTTP client of the SymGS API, for batch use and the command line."""

from __future__ import annotations

import json
import os
import re
import time
import uuid
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import httpx

from api_schemas import TERMINAL_STATES, Job, JobEvent, JobPage
from symgs_core.files import whole_file

T = TypeVar("T")
# Result file name -> its path under /v1/jobs/{id}/ (charts/<name>.png keep theirs).
_DOWNLOAD_PATHS = {"result.symgs": "result", "report.json": "report"}
_MAX_ARTIFACT_NAME = 255
_DRIVE = re.compile(r"^[A-Za-z]:")  # C:x is a path of its own on Windows
# How long wait() and submit() keep trying while the API is out of reach or answers 503 (its Redis restarting, a
# redeploy): long enough to ride out a restart, short enough that a server gone for good is reported.
PATIENCE_S = 120.0
# Pauses between those tries where the API names none (Retry-After): doubling from the first up to the last.
_FIRST_PAUSE_S, _LAST_PAUSE_S = 0.5, 5.0


class ApiClientError(Exception):
    """An error answer of the API: HTTP status, machine-readable code and message, and the seconds it asked the
    client to wait before trying again (its Retry-After), if it said."""

    def __init__(self, status: int, code: str, message: str, retry_after: float | None = None) -> None:
        super().__init__(f"{status} {code}: {message}")
        self.status, self.code, self.message, self.retry_after = status, code, message, retry_after


@dataclass(frozen=True)
class Event:
    id: str
    event: JobEvent


class UnsafeArtifactName(ValueError):
    """The server listed a result file whose name would be written outside the folder asked for (an absolute path,
    a ``..``, a backslash or a control character): nothing of the job is written."""

    def __init__(self, name: str, folder: Path) -> None:
        super().__init__(
            f"the server listed a result file named {name[:120]!r}, which would be written outside {folder}; "
            "nothing was downloaded"
        )
        self.name = name


def artifact_path(folder: Path, name: str) -> Path:
    """Where the result file ``name`` goes under ``folder``; UnsafeArtifactName for any name that could leave it.
    The server's word is not trusted: over plain http anyone in the middle could put words in its mouth."""
    parts = name.split("/")
    if (
        not 0 < len(name) <= _MAX_ARTIFACT_NAME
        or not name.isprintable()
        or "\\" in name
        or _DRIVE.match(name)
        or any(part in ("", ".", "..") for part in parts)
    ):
        raise UnsafeArtifactName(name, folder)
    return folder.joinpath(*parts)


def _raise_for(response: httpx.Response) -> None:
    if response.is_success:
        return
    try:
        error = response.json()["error"]
        code, message = error["code"], error["message"]
    except (ValueError, KeyError, TypeError):
        code, message = "http_error", response.text[:200]
    raise ApiClientError(response.status_code, code, message, _retry_after(response))


def _retry_after(response: httpx.Response) -> float | None:
    try:
        return max(0.0, float(response.headers["Retry-After"]))
    except (KeyError, ValueError):  # absent, or an HTTP date: the client's own pauses will do
        return None


class _Patience:
    """The retries of one wait() or submit(): the pause before the next try, and whether to try again at all."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.reset()

    def reset(self) -> None:
        """The API answered: the next outage gets the whole patience again."""
        self.failing_since: float | None = None
        self.backoff = _FIRST_PAUSE_S

    def pause_before_retry(self, retry_after: float | None) -> bool:
        """Sleep before the next try (the API's Retry-After where it sent one); False once patience has run out."""
        now = time.monotonic()
        if self.failing_since is None:
            self.failing_since = now
        left = self.failing_since + self.seconds - now
        if left <= 0:
            return False
        time.sleep(min(retry_after if retry_after is not None else self.backoff, left))
        self.backoff = min(2 * self.backoff, _LAST_PAUSE_S)
        return True


def _try_again(patience: _Patience, exc: Exception) -> bool:
    """After a dropped connection, an API out of reach or a 503: pause (as its Retry-After asks, where it sent one)
    and say to try again, unless patience has run out. Any other error is the answer."""
    if isinstance(exc, httpx.TransportError):
        return patience.pause_before_retry(None)
    if isinstance(exc, ApiClientError) and exc.status == 503:
        return patience.pause_before_retry(exc.retry_after)
    return False


def _files(folder: Path) -> Iterator[Path]:
    """The regular files under ``folder``, through symbolic links (a dataset's photographs are often linked in from
    elsewhere), but never into a folder that holds the link: its files are listed already."""

    def walk(directory: Path, ancestors: frozenset[tuple[int, int]]) -> Iterator[Path]:
        stat = directory.stat()
        here = (stat.st_dev, stat.st_ino)
        if here in ancestors:
            return
        for path in directory.iterdir():
            if path.is_dir():
                yield from walk(path, ancestors | {here})
            elif path.is_file():
                yield path

    return walk(folder, frozenset())


def zip_folder(folder: str | os.PathLike[str], dest: str | os.PathLike[str]) -> Path:
    """Zip a dataset folder (the archive holds the folder itself, by name) for the ``images`` upload; files and folders
    that are symbolic links are stored as what they point to, under the link's name."""
    folder, dest = Path(folder), Path(dest)
    if not folder.is_dir():
        raise ValueError(f"{folder} is not a folder")
    with zipfile.ZipFile(dest, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for path in sorted(_files(folder)):
            zf.write(path, (Path(folder.name) / path.relative_to(folder)).as_posix())
    return dest


class SymgsClient:
    def __init__(
        self, base_url: str, api_key: str | None = None, *, timeout: float = 300.0, patience: float = PATIENCE_S
    ) -> None:
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.http = httpx.Client(base_url=base_url.rstrip("/"), headers=headers, timeout=timeout)
        self.patience = patience

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> SymgsClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def submit(
        self,
        scene: str | os.PathLike[str],
        *,
        images: str | os.PathLike[str] | None = None,
        params: dict[str, Any] | None = None,
        idempotency_key: str | None = None,
    ) -> Job:
        """Upload a scene (and a zip/tar of its dataset) and return the queued job.

        A dropped connection or a 503 is tried again as ``wait`` does. Every try carries one Idempotency-Key (the
        caller's, or one made here), so a retry whose first try did reach the API gets that job back, not a second.
        """
        headers = {"Idempotency-Key": idempotency_key or uuid.uuid4().hex}
        data = {"params": json.dumps(params)} if params else None

        def post() -> Job:
            with open(scene, "rb") as scene_file:
                files: dict[str, Any] = {"scene": (Path(scene).name, scene_file, "application/octet-stream")}
                if images is None:
                    response = self.http.post("/v1/jobs", files=files, data=data, headers=headers)
                else:
                    with open(images, "rb") as images_file:
                        files["images"] = (Path(images).name, images_file, "application/octet-stream")
                        response = self.http.post("/v1/jobs", files=files, data=data, headers=headers)
            _raise_for(response)
            return Job.model_validate(response.json())

        return self._patiently(post)

    def _patiently(self, attempt: Callable[[], T]) -> T:
        """``attempt()``'s answer, trying again after a dropped connection or a 503 (``_try_again``)."""
        patience = _Patience(self.patience)
        while True:
            try:
                return attempt()
            except (httpx.TransportError, ApiClientError) as exc:
                if not _try_again(patience, exc):
                    raise

    def job(self, job_id: str) -> Job:
        response = self.http.get(f"/v1/jobs/{job_id}")
        _raise_for(response)
        return Job.model_validate(response.json())

    def jobs(self, *, state: str | None = None, offset: int = 0, limit: int = 20) -> JobPage:
        query: dict[str, Any] = {"offset": offset, "limit": limit}
        if state is not None:
            query["state"] = state
        response = self.http.get("/v1/jobs", params=query)
        _raise_for(response)
        return JobPage.model_validate(response.json())

    def cancel(self, job_id: str) -> Job:
        response = self.http.post(f"/v1/jobs/{job_id}:cancel")
        _raise_for(response)
        return Job.model_validate(response.json())

    def delete(self, job_id: str) -> None:
        _raise_for(self.http.delete(f"/v1/jobs/{job_id}"))

    def events(self, job_id: str, *, last_event_id: str | None = None) -> Iterator[Event]:
        """The job's events from the start (or after ``last_event_id``) until its final state."""
        headers = {"Last-Event-ID": last_event_id} if last_event_id else {}
        with self.http.stream("GET", f"/v1/jobs/{job_id}/events", headers=headers, timeout=None) as response:
            if not response.is_success:
                response.read()
                _raise_for(response)
            fields: dict[str, str] = {}
            for line in response.iter_lines():
                if line == "":
                    if "data" in fields:
                        yield Event(fields.get("id", ""), JobEvent.model_validate_json(fields["data"]))
                    fields = {}
                elif not line.startswith(":"):
                    name, _, value = line.partition(":")
                    fields[name] = value[1:] if value.startswith(" ") else value

    def wait(self, job_id: str, on_event: Callable[[JobEvent], None] | None = None) -> Job:
        """Follow the job's events until it finishes (reconnecting after where it left off); the final job.

        A dropped connection, an API out of reach or one answering 503 is tried again, after the API's Retry-After
        where it sends one, until ``patience`` seconds pass without an answer; then the last error is raised."""
        last: str | None = None
        patience = _Patience(self.patience)
        while True:
            try:
                for item in self.events(job_id, last_event_id=last):
                    patience.reset()
                    last = item.id
                    if on_event is not None:
                        on_event(item.event)
                job = self.job(job_id)
            except (httpx.TransportError, ApiClientError) as exc:
                if _try_again(patience, exc):
                    continue  # resume after the last event seen
                raise
            patience.reset()
            if job.state in TERMINAL_STATES:
                return job

    def download(self, job_id: str, name: str, dest: str | os.PathLike[str]) -> Path:
        """Save a result file (result.symgs, result.ply, result.spz, report.json, charts/<name>.png) to ``dest``,
        whole or not at all: it is written under a temporary name, and a download cut short (or answered 503) is
        tried again from the start, as ``submit`` tries again."""
        path = _DOWNLOAD_PATHS.get(name, name)
        dest = Path(dest)

        def get() -> Path:
            with self.http.stream("GET", f"/v1/jobs/{job_id}/{path}") as response:
                if not response.is_success:
                    response.read()
                    _raise_for(response)
                with whole_file(dest) as out:
                    for chunk in response.iter_bytes(1 << 20):
                        out.write(chunk)
            return dest

        return self._patiently(get)

    def fetch(self, job_id: str, folder: str | os.PathLike[str]) -> list[Path]:
        """Save every result file of a finished job into ``folder``; returns the paths written. Every name the
        server lists is checked first (``artifact_path``): one that would leave ``folder`` stops the whole fetch."""
        job = self._patiently(lambda: self.job(job_id))
        folder = Path(folder)
        targets = [(name, artifact_path(folder, name)) for name in job.artifacts]
        return [self.download(job_id, name, path) for name, path in targets]
