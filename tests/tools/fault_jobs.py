"""Jobs through worker kills and Redis restarts: how many accepted jobs end without their result.

A local stack (``service.cli.stack.LocalStack``: Redis with its append-only file synced on every write, the
API, CPU workers) runs ``--jobs`` small jobs, all of the same scene and parameters, submitted one every ``--pace``
seconds by a client that retries with an Idempotency-Key whenever the API answers 503 or cannot be reached.
Meanwhile, every ``--every`` seconds, one fault in turn: a worker and its pool killed with SIGKILL (a replacement
started), or Redis stopped, with SIGKILL or SIGTERM alternately, and started again. When the planned faults are done
and every job has finished, it counts:

    lost        accepted, then never finished, or gone from the store
    failed      finished as failed (by error code: ``worker_lost`` after ``SYMGS_MAX_ATTEMPTS`` runs, ...)
    succeeded   and how many distinct results they hold (the same job must give the same bytes however often it was
                interrupted)

    .venv/bin/python tests/tools/fault_jobs.py --jobs 100 --workers 2 --kills 10 --restarts 10 --every 8 --pace 1.5
"""

from __future__ import annotations

import argparse
import hashlib
import json
import random
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import httpx

from service.cli.stack import LocalStack

KEY = "fault-key-5d1e"
PARAMS = {"iterations": 20, "train_views": 4, "fit_views": 2, "eval_views": 2, "resolution": 64, "eval_resolution": 64,
          "max_levels": 1, "device": "cpu"}  # fmt: skip
FINISHED = ("succeeded", "failed", "cancelled")


@dataclass
class Outcome:
    accepted: dict[int, str] = field(default_factory=dict)  # submission number -> job id
    submit_retries: int = 0
    faults: list[str] = field(default_factory=list)
    states: dict[str, dict] = field(default_factory=dict)  # job id -> the job as last read
    results: Counter = field(default_factory=Counter)  # sha256 of result.symgs -> jobs
    seconds: float = 0.0

    @property
    def lost(self) -> list[str]:
        return [i for i in self.accepted.values() if self.states.get(i, {}).get("state") not in FINISHED]

    def summary(self) -> dict:
        finals = [self.states[i] for i in self.accepted.values() if i in self.states]
        failed = Counter(j["error"]["code"] for j in finals if j["state"] == "failed")
        return {
            "jobs": len(self.accepted), "succeeded": sum(j["state"] == "succeeded" for j in finals),
            "failed": dict(failed), "lost": len(self.lost), "distinct_results": len(self.results),
            "attempts": dict(Counter(j["attempts"] for j in finals)), "faults": Counter(self.faults),
            "submit_retries": self.submit_retries, "seconds": round(self.seconds, 1),
        }  # fmt: skip


def _client(stack: LocalStack) -> httpx.Client:
    return httpx.Client(base_url=stack.api_url, headers={"Authorization": f"Bearer {KEY}"}, timeout=30)


def _submit_all(
    stack: LocalStack, scene: bytes, jobs: int, pace: float, outcome: Outcome, stop: threading.Event
) -> None:
    """Submit a job every ``pace`` seconds, retrying each with its Idempotency-Key until the API accepts it."""
    with _client(stack) as api:
        for number in range(jobs):
            stop.wait(pace if number else 0)
            while not stop.is_set():
                try:
                    response = api.post(
                        "/v1/jobs", files={"scene": ("scene.ply", scene)}, data={"params": json.dumps(PARAMS)},
                        headers={"Idempotency-Key": f"fault-{number}"},
                    )  # fmt: skip
                except httpx.TransportError:
                    response = None
                if response is not None and response.status_code in (200, 202):
                    outcome.accepted[number] = response.json()["id"]
                    break
                if response is not None and response.status_code not in (502, 503, 504):
                    raise RuntimeError(f"submission {number}: {response.status_code} {response.text[:300]}")
                outcome.submit_retries += 1
                time.sleep(0.5)


def _poll(api: httpx.Client, outcome: Outcome) -> bool:
    """Read every unfinished job; True when all accepted jobs have finished. Outages just mean: ask again later."""
    for job_id in list(outcome.accepted.values()):
        if outcome.states.get(job_id, {}).get("state") in FINISHED:
            continue
        try:
            response = api.get(f"/v1/jobs/{job_id}")
        except httpx.TransportError:
            return False
        if response.status_code == 200:
            outcome.states[job_id] = response.json()
        elif response.status_code == 404:
            outcome.states[job_id] = {"state": "gone", "id": job_id}
    return all(outcome.states.get(i, {}).get("state") in FINISHED for i in outcome.accepted.values())


def plan(kills: int, restarts: int) -> list[str]:
    """Worker kills and Redis restarts, alternating while both last."""
    return [kind for i in range(max(kills, restarts)) for kind, count in (("kill", kills), ("restart", restarts))
            if i < count]  # fmt: skip


def _fault(stack: LocalStack, kind: str, done: list[str], rng: random.Random) -> str:
    """Cause one fault of ``kind``; Redis restarts alternate between SIGKILL and SIGTERM (``done``: faults so far)."""
    if kind == "kill":
        victim = rng.choice(stack.workers)
        victim.kill()
        stack.workers.remove(victim)
        stack.start_worker("cpu")
        return "worker killed"
    crash = sum(fault.startswith("redis") for fault in done) % 2 == 0
    stack.stop_redis(kill=crash)
    time.sleep(rng.uniform(0.2, 1.5))  # down for a moment; jobs' leases outlive it
    stack.start_redis()
    return "redis killed and restarted" if crash else "redis stopped and restarted"


def run(stack: LocalStack, scene: bytes, *, jobs: int, kills: int, restarts: int, every: float, pace: float,
        timeout: float, seed: int = 0) -> Outcome:  # fmt: skip
    """Submit ``jobs`` jobs, one every ``pace`` seconds, to a started ``stack`` while a fault happens every
    ``every`` seconds; returns what became of them."""
    rng, outcome, stop = random.Random(seed), Outcome(), threading.Event()
    started = time.monotonic()
    submitter = threading.Thread(target=_submit_all, args=(stack, scene, jobs, pace, outcome, stop), daemon=True)
    submitter.start()
    faults, next_fault = plan(kills, restarts), started + every
    with _client(stack) as api:
        while time.monotonic() - started < timeout:
            if faults and time.monotonic() >= next_fault:
                outcome.faults.append(_fault(stack, faults.pop(0), outcome.faults, rng))
                next_fault = time.monotonic() + every
            if _poll(api, outcome) and not submitter.is_alive() and not faults:
                break
            time.sleep(0.5)
        stop.set()
        submitter.join(timeout=30)
        outcome.seconds = time.monotonic() - started
        for job_id in outcome.accepted.values():
            if outcome.states.get(job_id, {}).get("state") == "succeeded":
                outcome.results[hashlib.sha256(api.get(f"/v1/jobs/{job_id}/result").content).hexdigest()] += 1
    return outcome


def scene_bytes(n: int = 2000) -> bytes:
    from symgs_core.ply import ply_bytes
    from symgs_core.synthetic import synthetic_scene

    return ply_bytes(synthetic_scene("global", n=n, seed=3, sh_degree=1).scene)


def fault_stack(workers: int, lease_s: float) -> LocalStack:
    env = {"SYMGS_API_KEYS": KEY, "SYMGS_LEASE_SECONDS": str(lease_s), "SYMGS_MAINTENANCE_SECONDS": "1"}
    return LocalStack(env=env, durable_redis=True).start(workers=workers)


def table(outcome: Outcome, args: argparse.Namespace) -> str:
    """The outcome as a Markdown table, then each failed job's error (its code and message, as the API gives them)."""
    s = outcome.summary()
    failed = sum(s["failed"].values())
    codes = ", ".join(f"`{code}` {n}" for code, n in sorted(s["failed"].items()))
    runs = ", ".join(f"{k} run{'s' if k != 1 else ''}: {n}" for k, n in sorted(s["attempts"].items()))
    faults = ", ".join(f"{kind} {n}" for kind, n in sorted(s["faults"].items()))
    lines = [
        "| jobs | succeeded | failed | lost (never finished) | distinct results | runs per job | submissions refused "
        "(503) and retried | faults | wall |",
        "|---:|---:|---:|---:|---:|---|---:|---|---:|",
        f"| {s['jobs']} | {s['succeeded']} | {failed}{f' ({codes})' if codes else ''} | **{s['lost']}** | "
        f"{s['distinct_results']} | {runs} | {s['submit_retries']} | {faults} | {s['seconds']:.0f} s |",
        "",
        f"{args.jobs} jobs, {args.workers} workers, a fault every {args.every:g} s, leases of {args.lease:g} s.",
    ]
    for job in outcome.states.values():
        if job.get("state") == "failed":
            error = job.get("error") or {}
            lines.append(f"Job {job.get('id')} failed after {job.get('attempts')} run(s): {error.get('code')}: "
                         f"{str(error.get('message'))[:300]}")  # fmt: skip
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=100)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--kills", type=int, default=10)
    parser.add_argument("--restarts", type=int, default=10)
    parser.add_argument("--every", type=float, default=8.0, help="seconds between faults")
    parser.add_argument("--pace", type=float, default=1.5, help="seconds between submissions")
    parser.add_argument("--lease", type=float, default=5.0, help="SYMGS_LEASE_SECONDS of the stack")
    parser.add_argument("--timeout", type=float, default=3600.0)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    stack = fault_stack(args.workers, args.lease)
    try:
        outcome = run(stack, scene_bytes(), jobs=args.jobs, kills=args.kills, restarts=args.restarts,
                      every=args.every, pace=args.pace, timeout=args.timeout)  # fmt: skip
    finally:
        stack.cleanup()
    summary = outcome.summary()
    print(table(outcome, args))
    if args.json is not None:
        args.json.write_text(json.dumps({**summary, "lost_ids": outcome.lost}, indent=1))


if __name__ == "__main__":
    main()
