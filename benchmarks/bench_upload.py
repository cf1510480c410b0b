"""Upload memory: the API's resident memory while it receives a large scene, streamed by the client.

Starts redis-server and the API (``symgs serve``, one process; no worker, so the job stays queued), then posts
``POST /v1/jobs`` with a body that the client generates as it sends it: the multipart envelope around a valid PLY
header of an SH-3 scene whose Gaussians fill ``--gigabytes`` (all zero bytes). The API's resident set is sampled from
``/proc`` every 20 ms during the upload; ``VmHWM`` gives its peak over its whole life. ``--s3`` puts the storage on a
standalone S3 server (moto), so the upload goes on from the staging folder to the bucket as a multipart transfer.

    .venv/bin/python benchmarks/bench_upload.py --gigabytes 2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.cli.stack import LocalStack  # noqa: E402
from tests.upload_stream import upload  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gigabytes", type=float, default=2.0, help="scene bytes, in 10^9")
    parser.add_argument("--s3", action="store_true", help="storage on a standalone S3 server (moto)")
    args = parser.parse_args()
    scene_bytes = int(args.gigabytes * 1e9)
    limits = {"SYMGS_MAX_UPLOAD_BYTES": str(scene_bytes + (1 << 20)), "SYMGS_MAX_GAUSSIANS": str(scene_bytes // 200)}
    stack = LocalStack(env=limits)
    try:
        stack.start_redis()
        if args.s3:
            from tests.s3_server import BUCKET, start_s3_server

            server = start_s3_server(stack.root)
            stack.children.append(server.child)
            stack.env.update(server.env())
            stack.storage = f"s3://{BUCKET}/bench"
        stack.start_api()
        api = next(c for c in stack.children if c.name == "api")
        figures = upload(stack.api_url, stack.api_key, api.popen.pid, scene_bytes, {"device": "cpu"})
    finally:
        stack.cleanup()
    job = figures.pop("job")
    if figures["status"] != 202:
        sys.exit(f"upload refused: {figures['status']} {job}")
    storage = "S3 (moto server)" if args.s3 else "directory"
    print("| upload bytes | Gaussians (SH 3) | storage | seconds | MB/s | API RSS before (MiB) | peak sampled (MiB) | "
          "VmHWM (MiB) | job |")  # fmt: skip
    print("|---:|---:|---|---:|---:|---:|---:|---:|---|")
    print(f"| {figures['body_bytes']:,} | {figures['gaussians']:,} | {storage} | {figures['seconds']:.1f} | "
          f"{figures['mb_per_s']:.0f} | {figures['rss_before_mib']:.0f} | {figures['rss_peak_mib']:.0f} | "
          f"{figures['hwm_mib']:.0f} | {job['state']} |")  # fmt: skip

if __name__ == "__main__":
    main()
