"""A job's event stream: the state and progress events its record's changes append (``event``), and reading them
back from a position, as the API relays them to a client (``follow``)."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator

import redis.asyncio as aioredis

from api_schemas import TERMINAL_STATES, JobEvent

from .keys import events_key, job_key

EVENTS_MAXLEN = 5000  # progress events kept per job; state events are few
_WAIT_MS = 10_000  # block this long for new events before checking that the job still exists
_BATCH = 200


def event(kind: str, state: str, h: dict[str, str], now: float) -> dict[str, str]:
    event = JobEvent(
        kind=kind,
        state=state,
        stage=h.get("stage") or None,
        level=int(h["level"]) if h.get("level") else None,
        progress=float(h.get("progress") or 0),
        message=h.get("message", ""),
        eta_s=float(h["eta_s"]) if h.get("eta_s") else None,
        time=now,
    )
    return {"data": event.model_dump_json()}


async def follow(r: aioredis.Redis, job_id: str, after: str) -> AsyncIterator[dict]:
    """SSE messages (``id``, ``event``, ``data``) of a job's stream after id ``after``, ending with the event of a
    final state, or when the job is deleted."""
    key = events_key(job_id)
    while True:
        entries = await r.xrange(key, min=f"({after}", count=_BATCH)
        for entry_id, fields in entries:
            after = entry_id
            data = fields["data"]
            event = json.loads(data)
            yield {"id": entry_id, "event": event["kind"], "data": data}
            if event["kind"] == "state" and event["state"] in TERMINAL_STATES:
                return
        if entries:
            continue
        state = await r.hget(job_key(job_id), "state")
        if state is None:
            return  # deleted
        if state in TERMINAL_STATES:
            # Its final event was sent before `after` (a replay from past the end), or has just been added.
            if not await r.xrange(key, min=f"({after}", count=1):
                return
            continue
        await r.xread({key: after}, count=1, block=_WAIT_MS)
