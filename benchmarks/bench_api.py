"""Service benchmark: API latency under concurrent clients, job throughput with 1 and 2 CPU workers, and the time
from submission to a worker starting the job. Everything runs locally (redis-server, uvicorn, Celery workers).

    .venv/bin/python benchmarks/bench_api.py [--clients 50] [--requests 10] [--jobs 6] [--json out.json]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import httpx

from service.cli.stack import LocalStack
from service.client import SymgsClient

# The pipeline alone: no peers' formats in the job's charts, even where splat-transform is installed.
WORKERS = {"SYMGS_PEER_SECONDS": "0"}
TINY = {"iterations": 20, "train_views": 4, "fit_views": 2, "eval_views": 2, "resolution": 64, "eval_resolution": 64,
        "max_levels": 1, "device": "cpu"}


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


async def _latency(url: str, key: str | None, scene: bytes, clients: int, requests: int) -> dict:
    post_ms: list[float] = []
    get_ms: list[float] = []
    ids: list[str] = []
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    headers = {"Authorization": f"Bearer {key}"} if key else {}
    async with httpx.AsyncClient(base_url=url, headers=headers, limits=limits, timeout=120) as client:

        async def one_client(posting: bool) -> None:
            for _ in range(requests):
                t0 = time.perf_counter()
                if posting:
                    files, data = {"scene": ("s.ply", scene)}, {"params": json.dumps(TINY)}
                    r = await client.post("/v1/jobs", files=files, data=data)
                    post_ms.append(1000 * (time.perf_counter() - t0))
                    assert r.status_code == 202, r.text
                    ids.append(r.json()["id"])
                else:
                    r = await client.get(f"/v1/jobs/{ids[len(get_ms) % len(ids)]}")
                    get_ms.append(1000 * (time.perf_counter() - t0))
                    assert r.status_code == 200, r.text

        t0 = time.perf_counter()
        await asyncio.gather(*(one_client(True) for _ in range(clients)))
        post_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        await asyncio.gather(*(one_client(False) for _ in range(clients)))
        get_s = time.perf_counter() - t0
    return {
        "clients": clients,
        "scene_bytes": len(scene),
        "post": {"n": len(post_ms), "p50_ms": percentile(post_ms, 0.5), "p99_ms": percentile(post_ms, 0.99),
                 "per_s": len(post_ms) / post_s},
        "get": {"n": len(get_ms), "p50_ms": percentile(get_ms, 0.5), "p99_ms": percentile(get_ms, 0.99),
                "per_s": len(get_ms) / get_s},
    }  # fmt: skip


def _throughput(scene: Path, workers: int, jobs: int) -> dict:
    with LocalStack(env=WORKERS) as stack:
        for _ in range(workers - 1):
            stack.start_worker("cpu")
        with SymgsClient(stack.api_url, stack.api_key) as client:
            # Warm-up: the first job in each worker pays for importing torch.
            warm = [client.submit(scene, params=TINY).id for _ in range(workers)]
            for job_id in warm:
                client.wait(job_id)
            t0 = time.perf_counter()
            ids = [client.submit(scene, params=TINY).id for _ in range(jobs)]
            finals = [client.wait(job_id) for job_id in ids]
            elapsed = time.perf_counter() - t0
    assert all(j.state == "succeeded" for j in finals), [j.error for j in finals]
    return {"workers": workers, "jobs": jobs, "seconds": elapsed, "jobs_per_min": 60 * jobs / elapsed}


def _start_delay(scene: Path, samples: int) -> dict:
    """Submission (created_at) to the worker starting the job (started_at), one job at a time on an idle worker."""
    delays = []
    with LocalStack(env=WORKERS) as stack, SymgsClient(stack.api_url, stack.api_key) as client:
        client.wait(client.submit(scene, params=TINY).id)  # warm-up
        for _ in range(samples):
            job = client.wait(client.submit(scene, params={**TINY, "iterations": 0}).id)
            delays.append(1000 * (job.started_at - job.created_at))
    return {"samples": samples, "p50_ms": statistics.median(delays), "max_ms": max(delays)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument("--requests", type=int, default=10, help="requests per client and per endpoint")
    parser.add_argument("--jobs", type=int, default=6, help="jobs per throughput run")
    parser.add_argument("--samples", type=int, default=5, help="jobs timed for the start delay")
    parser.add_argument("--gaussians", type=int, default=2000)
    parser.add_argument("--json", type=Path, help="write the figures here too")
    args = parser.parse_args()

    from symgs_core.export import save_scene
    from symgs_core.synthetic import synthetic_scene

    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp) / "scene.ply"
        save_scene(synthetic_scene("global", n=args.gaussians, seed=3, sh_degree=1).scene, scene)
        stack = LocalStack()  # no worker: the submitted jobs stay queued and cost no CPU during the measurement
        try:
            stack.start_redis()
            stack.start_api()
            posted = _latency(stack.api_url, stack.api_key, scene.read_bytes(), args.clients, args.requests)
            latency = asyncio.run(posted)
        finally:
            stack.cleanup()
        delay = _start_delay(scene, args.samples)
        throughput = [_throughput(scene, workers, args.jobs) for workers in (1, 2)]

    scene_kb = latency["scene_bytes"] / 1000
    print("| what | figure |")
    print("| --- | --- |")
    for name, label in (("post", f"`POST /v1/jobs` ({scene_kb:.0f} kB multipart upload, header checks, store, queue)"),
                        ("get", "`GET /v1/jobs/{id}`")):  # fmt: skip
        f = latency[name]
        print(f"| {label}, {latency['clients']} concurrent clients, {f['n']} requests | p50 {f['p50_ms']:,.0f} ms, "
              f"p99 {f['p99_ms']:,.0f} ms, {f['per_s']:.0f} requests/s |")  # fmt: skip
    print(f"| submission to a worker starting the job (`started_at - created_at`, idle worker, {delay['samples']} "
          f"jobs) | median {delay['p50_ms']:.0f} ms, max {delay['max_ms']:.0f} ms |")  # fmt: skip
    for t in throughput:
        print(f"| job throughput, {t['workers']} CPU worker(s) ({t['jobs']} jobs after a warm-up job each) | "
              f"{t['seconds']:.1f} s, {t['jobs_per_min']:.1f} jobs/min |")  # fmt: skip

    figures = {"latency": latency, "start_delay": delay, "throughput": throughput}
    if args.json is not None:
        args.json.write_text(json.dumps(figures, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
