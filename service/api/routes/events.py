"""``GET /v1/jobs/{id}/events``: a job's state and progress events as Server-Sent Events, replayable."""

from __future__ import annotations

import logging
import re
from collections.abc import AsyncIterator
from typing import Annotated

import redis.asyncio as aioredis
from fastapi import APIRouter, Header, Request
from redis import RedisError
from sse_starlette import EventSourceResponse

from worker.gateway import follow_events

from ..auth import OwnerDep
from ..deps import StoreDep
from ..errors import ApiError, error_responses
from ..job_view import owned_record

router = APIRouter(prefix="/v1/jobs", tags=["events"])
log = logging.getLogger(__name__)
_STREAM_ID = re.compile(r"^(\d{1,20})-(\d{1,20})$")
_ID_PART_MAX = 2**64 - 1  # each half of a Redis stream id is an unsigned 64-bit integer


async def job_events(r: aioredis.Redis, job_id: str, after: str) -> AsyncIterator[dict]:
    """SSE messages of a job's stream after id ``after``, ending with the event of a final state. Should Redis go
    away, the stream ends early: the client resumes with the last id it received, as SSE clients do."""
    try:
        async for message in follow_events(r, job_id, after):
            yield message
    except RedisError as exc:
        log.warning("events of job %s: the job store went away (%s); ending the stream", job_id, type(exc).__name__)


def _is_stream_id(text: str) -> bool:
    """Whether ``text`` is a Redis stream id with ids after it (Redis refuses to read after the largest one)."""
    match = _STREAM_ID.match(text)
    if match is None:
        return False
    ms, seq = (int(part) for part in match.groups())
    return ms <= _ID_PART_MAX and seq <= _ID_PART_MAX and (ms, seq) != (_ID_PART_MAX, _ID_PART_MAX)


@router.get(
    "/{job_id}/events",
    summary="Follow a job's progress (Server-Sent Events)",
    description="Each message has `event` (`state` or `progress`), `id` (its position in the job's event stream) "
    "and `data` (a JobEvent as JSON). The stream starts from the job's first event, or after `Last-Event-ID`, and "
    "ends after the event of a final state (succeeded, failed, cancelled).",
    response_class=EventSourceResponse,
    responses={
        200: {
            "description": "an event stream of JobEvent messages",
            "content": {
                "text/event-stream": {
                    "schema": {"type": "string"},
                    "example": 'id: 1767225600000-0\nevent: state\ndata: {"kind": "state", "state": "queued", '
                    '"stage": null, "level": null, "progress": 0.0, "message": "", "time": 1767225600.0}\n\n',
                }
            },
        },
        **error_responses(401, 404, 422, 503),
    },
)
def get_events(
    job_id: str,
    request: Request,
    owner: OwnerDep,
    store: StoreDep,
    last_event_id: Annotated[str | None, Header(description="resume after this event id")] = None,
) -> EventSourceResponse:
    owned_record(store, owner, job_id)
    after = last_event_id or "0-0"
    if not _is_stream_id(after):
        message = f"Last-Event-ID must be a stream id like 1767225600000-0, got {after[:40]!r}"
        raise ApiError(422, "bad_last_event_id", message)
    return EventSourceResponse(job_events(request.app.state.aredis, job_id, after), ping=15)
