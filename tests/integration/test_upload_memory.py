"""A large upload goes to storage as it arrives: the API process's resident memory does not grow with it."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from service.api.auth import owner_of
from service.cli.stack import LocalStack
from tests.upload_stream import upload
from worker.storage import DirectoryStorage

SCENE_BYTES = 200_000_000
MAX_GROWTH_MIB = 48  # a few buffers of the stream; holding the upload would take 190 MiB

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def api_only() -> Iterator[LocalStack]:
    """Redis and the API, no worker: the job stays queued, and nothing else shares the API's memory figures."""
    stack = LocalStack(env={"SYMGS_MAX_UPLOAD_BYTES": str(SCENE_BYTES + (1 << 20))})
    try:
        stack.start_redis()
        stack.start_api()
        yield stack
    finally:
        stack.cleanup()


def test_a_200_mb_upload_streams_to_storage(api_only: LocalStack) -> None:
    api = next(child for child in api_only.children if child.name == "api")
    figures = upload(api_only.api_url, api_only.api_key, api.popen.pid, SCENE_BYTES)
    assert figures["status"] == 202, figures
    job = figures["job"]
    assert job["scene"]["bytes"] == figures["scene_bytes"] and job["scene"]["gaussians"] == figures["gaussians"]
    stored = DirectoryStorage(api_only.storage).job_dir(owner_of(api_only.api_key), job["id"]) / "upload/scene.ply"
    assert stored.stat().st_size == figures["scene_bytes"]
    growth = figures["rss_peak_mib"] - figures["rss_before_mib"]
    assert growth < MAX_GROWTH_MIB, figures
