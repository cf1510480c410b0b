"""A standalone S3 server for tests: moto in server mode, as a child process, with one bucket."""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

from service.cli.stack import Child, free_port, spawn, wait_until

BUCKET = "symgs-test"
CREDENTIALS = {"AWS_ACCESS_KEY_ID": "symgs-test-key", "AWS_SECRET_ACCESS_KEY": "symgs-test-secret"}
REGION = "us-east-1"


@dataclass
class S3Server:
    child: Child
    endpoint: str  # as the test process reaches it

    def env(self, endpoint: str | None = None) -> dict[str, str]:
        """The standard AWS settings a process needs to use this server (reached at ``endpoint``)."""
        return {**CREDENTIALS, "AWS_DEFAULT_REGION": REGION, "AWS_ENDPOINT_URL": endpoint or self.endpoint}

    def client(self) -> Any:  # noqa: ANN401 - botocore's S3 client
        import boto3

        session = boto3.session.Session(
            aws_access_key_id=CREDENTIALS["AWS_ACCESS_KEY_ID"],
            aws_secret_access_key=CREDENTIALS["AWS_SECRET_ACCESS_KEY"],
            region_name=REGION,
        )
        return session.client("s3", endpoint_url=self.endpoint)

    def keys(self, prefix: str = "") -> list[str]:
        pages = self.client().get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix=prefix)
        return sorted(obj["Key"] for page in pages for obj in page.get("Contents", ()))


def start_s3_server(
    logs: Path, *, bind: str = "127.0.0.1", host: str | None = None, wrap: list[str] | None = None
) -> S3Server:
    """Start the server on a free port of ``bind`` (reached at ``host``) and create ``BUCKET``."""
    port = free_port()
    argv = [sys.executable, "-m", "moto.server", "-H", bind, "-p", str(port)]
    child = spawn("s3", argv, env=os.environ.copy(), logs=logs, wrap=wrap)
    server = S3Server(child, f"http://{host or bind}:{port}")
    try:
        wait_until(child, lambda: httpx.get(server.endpoint, timeout=2).status_code == 200, 30, "serve S3")
        server.client().create_bucket(Bucket=BUCKET)
    except BaseException:
        child.stop()
        raise
    return server
