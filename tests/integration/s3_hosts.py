"""The service on s3:// storage with each process as on a host of its own: Redis, an S3 server process (moto), and
the API and workers each in a folder with its own HOME and TMPDIR, so they share no disk. Short leases and sweeps, so
that a lost worker's job is taken over within seconds."""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

from service.cli.stack import Child, LocalStack
from tests.integration.conftest import KEY_A, KEY_B
from tests.s3_server import BUCKET, REGION, S3Server, start_s3_server

PREFIX = "service"
FAST_RECOVERY = {"SYMGS_LEASE_SECONDS": "3", "SYMGS_MAINTENANCE_SECONDS": "1", "SYMGS_PEER_SECONDS": "0"}


def host_folder(root: Path, name: str) -> tuple[Path, dict[str, str]]:
    """A folder ``root/name`` to run a process from, with its own HOME and TMPDIR inside: what the process writes for
    itself stays there, as on a host of its own."""
    home, tmp = root / name / "home", root / name / "tmp"
    home.mkdir(parents=True, exist_ok=True)
    tmp.mkdir(exist_ok=True)
    return root / name, {"HOME": str(home), "TMPDIR": str(tmp)}


@dataclass
class S3Service:
    stack: LocalStack
    server: S3Server
    root: Path  # the hosts' folders

    def start_worker(self, name: str, env: dict[str, str] | None = None) -> Child:
        folder, host_env = host_folder(self.root, name)
        return self.stack.start_worker("cpu", env={**host_env, **(env or {})}, cwd=folder)

    def start_api(self, name: str, env: dict[str, str] | None = None) -> str:
        """Start an API process on a host of its own; its URL."""
        folder, host_env = host_folder(self.root, name)
        self.stack.start_api(env={**host_env, **(env or {})}, cwd=folder)
        return self.stack.api_url

    def job_prefix(self, owner: str, job_id: str) -> str:
        return f"{PREFIX}/tenants/{owner}/jobs/{job_id}/"

    def unfinished_uploads(self, client: Any, prefix: str) -> list[str]:  # noqa: ANN401 - botocore's S3 client
        pages = client.get_paginator("list_multipart_uploads").paginate(Bucket=BUCKET, Prefix=prefix)
        return sorted(upload["Key"] for page in pages for upload in page.get("Uploads", ()))


@contextmanager
def s3_service(tmp_root: Path, env: dict[str, str] | None = None) -> Iterator[S3Service]:
    """Redis and an S3 server, nothing else yet: each test module starts the API and the workers it needs."""
    stack = LocalStack(env={"SYMGS_API_KEYS": f"{KEY_A},{KEY_B}", **FAST_RECOVERY, **(env or {})},
                       storage=f"s3://{BUCKET}/{PREFIX}")  # fmt: skip
    try:
        stack.start_redis()
        server = start_s3_server(stack.root)
        stack.children.append(server.child)
        stack.env.update(server.env())
        yield S3Service(stack, server, tmp_root)
    finally:
        stack.cleanup()


def enforce_credentials(server: S3Server) -> tuple[dict[str, str], dict[str, str]]:
    """Make the S3 server check every request's signature, as a real one does, against two access keys made here
    through its IAM API: the AWS settings of each. The first may use S3 and delete the second, so a test can revoke
    a key a running process holds. moto accepts any credentials until its count of unauthenticated requests is
    reset to 0 (its ``/moto-api/reset-auth``, the server-mode form of ``INITIAL_NO_AUTH_ACTION_COUNT``)."""
    import boto3

    iam = boto3.client("iam", endpoint_url=server.endpoint, region_name=REGION,
                       aws_access_key_id="setup", aws_secret_access_key="setup")  # fmt: skip
    keys = []
    for user, actions in (("symgs", ["s3:*", "iam:DeleteAccessKey"]), ("revocable", ["s3:*"])):
        iam.create_user(UserName=user)
        policy = {"Version": "2012-10-17", "Statement": [{"Effect": "Allow", "Action": actions, "Resource": "*"}]}
        iam.put_user_policy(UserName=user, PolicyName="s3", PolicyDocument=json.dumps(policy))
        key = iam.create_access_key(UserName=user)["AccessKey"]
        keys.append({"AWS_ACCESS_KEY_ID": key["AccessKeyId"], "AWS_SECRET_ACCESS_KEY": key["SecretAccessKey"]})
    httpx.post(f"{server.endpoint}/moto-api/reset-auth", content=b"0", timeout=10).raise_for_status()
    return keys[0], keys[1]


def revoke(server: S3Server, credentials: dict[str, str], revocable: dict[str, str]) -> None:
    """Delete the access key ``revocable`` (of ``enforce_credentials``), as an operator rotating keys would."""
    import boto3

    iam = boto3.client("iam", endpoint_url=server.endpoint, region_name=REGION,
                       aws_access_key_id=credentials["AWS_ACCESS_KEY_ID"],
                       aws_secret_access_key=credentials["AWS_SECRET_ACCESS_KEY"])  # fmt: skip
    iam.delete_access_key(UserName="revocable", AccessKeyId=revocable["AWS_ACCESS_KEY_ID"])


def s3_client(server: S3Server, credentials: dict[str, str]) -> Any:  # noqa: ANN401 - botocore's S3 client
    import boto3

    return boto3.session.Session(
        aws_access_key_id=credentials["AWS_ACCESS_KEY_ID"],
        aws_secret_access_key=credentials["AWS_SECRET_ACCESS_KEY"],
        region_name=REGION,
    ).client("s3", endpoint_url=server.endpoint)
