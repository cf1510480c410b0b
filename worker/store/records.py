"""Job records: the hash of each job, the indexes that list them (by state, by owner, finished, set aside), their
cancel flags, and the checked state changes, each appending its event to the job's stream (``events``).

State changes are checked transactions, so concurrent writers (a worker, the API cancelling, a reaper) cannot
move a job out of a final state or run it twice.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from typing import Any

import redis

from api_schemas import JOB_STATES, TERMINAL_STATES, JobParams

from .events import EVENTS_MAXLEN, event
from .keys import P, events_key, job_key

STATES = JOB_STATES
_ALLOWED = {  # to-state -> from-states
    "queued": {"running"},  # a reaper re-queues a job whose worker was lost
    "running": {"queued"},
    "succeeded": {"running"},
    "failed": {"queued", "running"},
    "cancelled": {"queued", "running"},
}


@dataclass
class JobRecord:
    """A job as stored. ``scene``/``images``/``mirrors``/``metrics`` hold the dicts of the api_schemas models."""

    id: str
    owner: str
    params: JobParams
    queue: str
    scene: dict[str, Any]
    images: dict[str, Any] | None = None
    images_root: str | None = None  # dataset folder inside upload/images
    state: str = "queued"
    stage: str | None = None
    level: int | None = None
    progress: float = 0.0
    message: str = ""
    eta_s: float | None = None  # of a running job; a state change clears it
    mirrors: list[dict[str, Any]] = field(default_factory=list)
    metrics: dict[str, Any] | None = None
    artifacts: list[str] = field(default_factory=list)
    error_code: str | None = None
    error_message: str | None = None
    attempts: int = 0
    cancel_requested: bool = False
    delete_requested: bool = False
    created_at: float = 0.0
    started_at: float | None = None
    finished_at: float | None = None
    updated_at: float = 0.0

    _JSON = ("params", "scene", "images", "mirrors", "metrics", "artifacts")

    def to_hash(self) -> dict[str, str]:
        values = {name: getattr(self, name) for name in self.__dataclass_fields__ if name != "params"}
        return {**_hash_fields(values), "params": self.params.model_dump_json()}

    @classmethod
    def from_hash(cls, h: dict[str, str]) -> JobRecord:
        def opt(name: str, cast: Any) -> Any:
            value = h.get(name, "")
            return None if value == "" else cast(value)

        return cls(
            id=h["id"],
            owner=h["owner"],
            params=JobParams.model_validate_json(h["params"]),
            queue=h["queue"],
            scene=json.loads(h["scene"]),
            images=json.loads(h.get("images") or "null"),
            images_root=opt("images_root", str),
            state=h["state"],
            stage=opt("stage", str),
            level=opt("level", int),
            progress=float(h.get("progress") or 0),
            message=h.get("message", ""),
            eta_s=opt("eta_s", float),
            mirrors=json.loads(h.get("mirrors") or "[]"),
            metrics=json.loads(h.get("metrics") or "null"),
            artifacts=json.loads(h.get("artifacts") or "[]"),
            error_code=opt("error_code", str),
            error_message=opt("error_message", str),
            attempts=int(h.get("attempts") or 0),
            cancel_requested=h.get("cancel_requested") == "1",
            delete_requested=h.get("delete_requested") == "1",
            created_at=float(h["created_at"]),
            started_at=opt("started_at", float),
            finished_at=opt("finished_at", float),
            updated_at=float(h["updated_at"]),
        )

    @property
    def finished(self) -> bool:
        return self.state in TERMINAL_STATES


def _hash_fields(fields: dict[str, Any]) -> dict[str, str]:
    out = {}
    for name, value in fields.items():
        if name in JobRecord._JSON:
            out[name] = json.dumps(value)
        elif isinstance(value, bool):
            out[name] = "1" if value else "0"
        else:
            out[name] = "" if value is None else str(value)
    return out


class Records:
    """The job records, and the indexes and flags kept beside them."""

    def __init__(self, client: redis.Redis) -> None:
        self.r = client

    def create(self, record: JobRecord) -> None:
        now = time.time()
        record.created_at = record.updated_at = now
        h = record.to_hash()
        with self.r.pipeline(transaction=True) as p:
            p.hset(job_key(record.id), mapping=h)
            p.zadd(f"{P}jobs", {record.id: now})
            p.zadd(f"{P}jobs:state:{record.state}", {record.id: now})
            p.zadd(f"{P}owner:{record.owner}:jobs", {record.id: now})
            p.zadd(f"{P}owner:{record.owner}:state:{record.state}", {record.id: now})
            p.xadd(events_key(record.id), event("state", record.state, h, now))
            p.execute()

    def get(self, job_id: str) -> JobRecord | None:
        h = self.r.hgetall(job_key(job_id))
        return JobRecord.from_hash(h) if h else None

    def get_owned(self, job_id: str, owner: str) -> JobRecord | None:
        """The job, or None when it does not exist or belongs to another owner (the API answers 404 to both)."""
        record = self.get(job_id)
        return record if record is not None and record.owner == owner else None

    def list_owned(self, owner: str, *, state: str | None, offset: int, limit: int) -> tuple[list[JobRecord], int]:
        """A page of an owner's jobs, newest first, and the total count."""
        key = f"{P}owner:{owner}:state:{state}" if state else f"{P}owner:{owner}:jobs"
        with self.r.pipeline(transaction=False) as p:
            p.zcard(key)
            p.zrevrange(key, offset, offset + limit - 1)
            total, ids = p.execute()
        with self.r.pipeline(transaction=False) as p:
            for job_id in ids:
                p.hgetall(job_key(job_id))
            hashes = p.execute()
        return [JobRecord.from_hash(h) for h in hashes if h], int(total)

    def transition(self, job_id: str, to: str, **fields: Any) -> JobRecord | None:
        """Move a job to state ``to`` if its current state allows it, setting ``fields`` too; appends a state
        event. Returns the updated record, or None when the job is gone or in a state that cannot move to ``to``."""
        key = job_key(job_id)

        def attempt(p: redis.client.Pipeline) -> dict[str, str] | None:
            h = p.hgetall(key)
            if not h or h["state"] not in _ALLOWED[to]:
                return None
            now = time.time()
            update = _hash_fields({"eta_s": None, **fields, "state": to, "updated_at": now})
            if to in TERMINAL_STATES:
                update["finished_at"] = str(now)
            merged = {**h, **update}
            created = float(h["created_at"])
            p.multi()
            p.hset(key, mapping=update)
            p.zrem(f"{P}jobs:state:{h['state']}", job_id)
            p.zrem(f"{P}owner:{h['owner']}:state:{h['state']}", job_id)
            p.zadd(f"{P}jobs:state:{to}", {job_id: created})
            p.zadd(f"{P}owner:{h['owner']}:state:{to}", {job_id: created})
            if to in TERMINAL_STATES:
                p.zadd(f"{P}jobs:finished", {job_id: now})
            p.xadd(events_key(job_id), event("state", to, merged, now))
            return merged

        merged = self.r.transaction(attempt, key, value_from_callable=True)
        return JobRecord.from_hash(merged) if merged else None

    def update(self, job_id: str, **fields: Any) -> None:
        """Set fields of a job record that are not its state (mirrors, metrics, attempts, ...)."""
        self.r.hset(job_key(job_id), mapping=_hash_fields({**fields, "updated_at": time.time()}))

    def progress(
        self, job_id: str, *, stage: str, level: int | None, fraction: float, message: str, eta_s: float | None = None
    ) -> None:
        """Record a progress report of a running job and append it to the job's event stream."""
        now = time.time()
        fields = {"stage": stage, "level": level, "progress": fraction, "message": message, "eta_s": eta_s}
        h = _hash_fields({**fields, "updated_at": now})
        with self.r.pipeline(transaction=True) as p:
            p.hset(job_key(job_id), mapping=h)
            p.xadd(events_key(job_id), event("progress", "running", h, now), maxlen=EVENTS_MAXLEN, approximate=True)
            p.execute()

    def delete(self, job_id: str) -> None:
        """Forget a job: its record, events, flags and index entries (its files are the storage's)."""
        h = self.r.hgetall(job_key(job_id))
        with self.r.pipeline(transaction=True) as p:
            p.delete(job_key(job_id), events_key(job_id), f"{P}job:{job_id}:cancel", f"{P}job:{job_id}:lease")
            p.zrem(f"{P}jobs", job_id)
            p.zrem(f"{P}jobs:finished", job_id)
            p.zrem(f"{P}jobs:quarantine", job_id)
            for state in STATES:
                p.zrem(f"{P}jobs:state:{state}", job_id)
            if h:
                p.zrem(f"{P}owner:{h['owner']}:jobs", job_id)
                for state in STATES:
                    p.zrem(f"{P}owner:{h['owner']}:state:{state}", job_id)
            p.execute()

    def ids_in_state(self, state: str) -> list[str]:
        return list(self.r.zrange(f"{P}jobs:state:{state}", 0, -1))

    def finished_before(self, cutoff: float) -> list[str]:
        return list(self.r.zrangebyscore(f"{P}jobs:finished", "-inf", cutoff))

    def quarantine(self, job_id: str, until: float) -> None:
        """Set an expired job whose files would not delete aside until ``until``, out of the expiry queue, whose
        oldest jobs come first: retried then, it keeps no other job from expiring meanwhile."""
        with self.r.pipeline(transaction=True) as p:
            p.zrem(f"{P}jobs:finished", job_id)
            p.zadd(f"{P}jobs:quarantine", {job_id: until})
            p.execute()

    def quarantined_until(self, cutoff: float) -> list[str]:
        """Jobs set aside by ``quarantine`` whose time to be tried again is ``cutoff`` or earlier."""
        return list(self.r.zrangebyscore(f"{P}jobs:quarantine", "-inf", cutoff))

    def count_by_state(self) -> dict[str, int]:
        with self.r.pipeline(transaction=False) as p:
            for state in STATES:
                p.zcard(f"{P}jobs:state:{state}")
            return dict(zip(STATES, map(int, p.execute()), strict=True))

    def abandon(self, owner: str, job_id: str) -> None:
        """Files of a job that was never recorded, which the storage could not delete yet: the sweep tries again."""
        self.r.sadd(f"{P}abandoned", f"{owner}/{job_id}")

    def abandoned(self) -> list[tuple[str, str]]:
        return [(owner, job_id) for owner, _, job_id in (m.partition("/") for m in self.r.smembers(f"{P}abandoned"))]

    def forget_abandoned(self, owner: str, job_id: str) -> None:
        self.r.srem(f"{P}abandoned", f"{owner}/{job_id}")

    def request_cancel(self, job_id: str, ttl_s: int) -> None:
        with self.r.pipeline(transaction=True) as p:
            p.set(f"{P}job:{job_id}:cancel", "1", ex=ttl_s)
            p.hset(job_key(job_id), mapping={"cancel_requested": "1", "updated_at": str(time.time())})
            p.execute()

    def cancel_requested(self, job_id: str) -> bool:
        return bool(self.r.exists(f"{P}job:{job_id}:cancel"))
