"""Where the job store keeps what, in Redis. Keys (prefix ``symgs:``)::

    job:<id>                 hash: the job record (``records.JobRecord``)
    job:<id>:events          stream: state and progress events, relayed by the API as SSE (``events``)
    job:<id>:cancel          flag: a client asked to cancel; the running task polls it (``records``)
    job:<id>:lease           token of the worker running the job, kept alive by its heartbeat (``leases``)
    job:<id>:resent          flag: a sweep sent the queued job's message again (maintenance.recover_dropped)
    job:<id>:requeue:<n>     flag: a reaper re-queued attempt n (``leases``)
    jobs                     zset id -> created_at (all jobs)
    jobs:state:<state>       zset id -> created_at
    jobs:finished            zset id -> finished_at (for expiry)
    jobs:quarantine          zset id -> time of the next try: expired jobs whose files would not delete
    owner:<o>:jobs, owner:<o>:state:<state>   zset id -> created_at (listing per API key)
    abandoned                set owner/id: files of jobs never recorded, for the sweep to delete
    idem:<o>:<key hash>      id of the job created with that Idempotency-Key, and its request's fingerprint
    workers:<mode>           zset worker name -> last heartbeat (``heartbeats``)
    metrics:durations        hash: histogram of job durations (bucket counters, sum, count) (``metrics``)
"""

from __future__ import annotations

P = "symgs:"


def job_key(job_id: str) -> str:
    return f"{P}job:{job_id}"


def events_key(job_id: str) -> str:
    return f"{P}job:{job_id}:events"
