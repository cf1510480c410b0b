"""Workers on other hosts. Redis, the S3 server and the API run on one host; two workers on two others (network
namespaces joined by veth pairs, made and removed here), each reaching Redis and S3 over its own link, from its own
folder with its own HOME and TMPDIR: they share no disk with the API or with each other. Two identical jobs run at
once; the host of one job's worker is unplugged and its processes killed mid-job. That job finishes on the other
worker with a result byte-identical to the job that ran uninterrupted."""

from __future__ import annotations

import os
from contextlib import ExitStack
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from service.api.auth import owner_of
from service.cli.stack import Child, LocalStack
from tests.integration.conftest import KEY_A, TINY, client_for, finished, submit, wait_for
from tests.integration.netns import NetworkUnavailable, private_network
from tests.integration.s3_hosts import host_folder
from tests.s3_server import BUCKET, start_s3_server
from worker.store import JobStore, P

PREFIX = "multihost"


def _worker_running(stack: LocalStack, job_id: str) -> Child:
    """The worker whose pool process holds the job's lease (its token is host:pid:delivery)."""
    store = JobStore.from_url(stack.redis_url)
    try:
        token = store.r.get(f"{P}job:{job_id}:lease")
    finally:
        store.r.close()
    assert token is not None, f"job {job_id} has no lease"
    group = os.getpgid(int(token.split(":")[1]))
    (worker,) = [w for w in stack.workers if w.popen.pid == group]
    return worker


def test_a_job_survives_the_loss_of_its_worker_host(tmp_path: Path, scene_path: Path) -> None:
    with ExitStack() as cleanup:
        try:
            net = cleanup.enter_context(private_network(workers=2))
        except NetworkUnavailable as exc:
            pytest.skip(f"cannot make test hosts here: {exc}")
        server_host = net.wrap(net.server_namespace)
        env = {"SYMGS_API_KEYS": KEY_A, "SYMGS_LEASE_SECONDS": "3", "SYMGS_MAINTENANCE_SECONDS": "1"}
        stack = LocalStack(
            env=env, storage=f"s3://{BUCKET}/{PREFIX}", bind="0.0.0.0", host=net.server_address, wrap=server_host
        )
        cleanup.callback(stack.cleanup)  # processes end before the network goes
        stack.start_redis()
        s3 = start_s3_server(stack.root, bind="0.0.0.0", host=net.server_address, wrap=server_host)
        stack.children.append(s3.child)
        stack.env.update(s3.env())
        api_dir, api_env = host_folder(tmp_path, "api")
        stack.start_api(env=api_env, cwd=api_dir)
        redis_port, s3_port = urlsplit(stack.redis_url).port, urlsplit(s3.endpoint).port
        hosts = {}
        for host in net.workers:
            folder, host_env = host_folder(tmp_path, host.namespace)
            remote = {
                **host_env, **s3.env(f"http://{host.server_address}:{s3_port}"),
                "SYMGS_REDIS_URL": f"redis://{host.server_address}:{redis_port}/0",
            }  # fmt: skip
            worker = stack.start_worker("cpu", env=remote, cwd=folder, wrap=net.wrap(host.namespace))
            hosts[worker.popen.pid] = host

        with client_for(stack, KEY_A) as api:
            steady, doomed = (submit(api, scene_path, TINY).json()["id"] for _ in range(2))
            wait_for(api, doomed, lambda j: j["state"] == "running" and j["stage"] == "levels", timeout=60)
            victim = _worker_running(stack, doomed)
            net.unplug(hosts[victim.popen.pid])
            victim.kill()
            stack.workers.remove(victim)

            done = wait_for(api, doomed, finished, timeout=120)
            assert done["state"] == "succeeded" and done["attempts"] == 2, done
            reference = wait_for(api, steady, finished, timeout=120)
            assert reference["state"] == "succeeded" and reference["attempts"] == 1, reference
            for artifact in ("result", "result.ply"):
                got = api.get(f"/v1/jobs/{doomed}/{artifact}")
                assert got.status_code == 200
                assert got.content == api.get(f"/v1/jobs/{steady}/{artifact}").content, artifact

        prefix = f"{PREFIX}/tenants/{owner_of(KEY_A)}/jobs/{doomed}/"
        keys = {key.removeprefix(prefix) for key in s3.keys(prefix)}
        assert {"upload/scene.ply", "checkpoints/levels.pt", "result/result.symgs"} <= keys
