"""The local stack's servers on ports drawn free: one whose port was taken in the meantime (by another stack started
beside it, as test processes run side by side) starts again on another, and is never mistaken for the server that
holds its port."""

from __future__ import annotations

import os
import socket
from collections.abc import Iterator

import httpx
import pytest
import redis

from service.cli import stack as stack_module
from service.cli.stack import LocalStack, embedded_redis_server, listens


def test_a_listening_socket_is_told_by_its_process() -> None:
    with socket.socket() as server, socket.socket() as bound:
        server.bind(("127.0.0.1", 0))
        server.listen()
        bound.bind(("127.0.0.1", 0))  # bound, not listening
        port, other = server.getsockname()[1], bound.getsockname()[1]
        assert listens(os.getpid(), port)
        assert not listens(os.getpid(), other)
        assert not listens(os.getppid(), port)


@pytest.fixture
def first() -> Iterator[LocalStack]:
    running = LocalStack(redis_binary=embedded_redis_server())
    try:
        running.start_redis()
        running.start_api()
        yield running
    finally:
        running.cleanup()


def port_of(url: str) -> int:
    return int(url.rsplit(":", 1)[1].split("/")[0])


def test_a_server_whose_port_another_stack_took_starts_again_on_another(
    first: LocalStack, monkeypatch: pytest.MonkeyPatch
) -> None:
    taken = [port_of(first.redis_url), port_of(first.api_url)]
    drawn: list[int] = []
    free_port = stack_module.free_port

    def draw() -> int:  # the other stack's port first, as a collision would give it
        port = taken.pop(0) if len(drawn) in (0, 2) else free_port()
        drawn.append(port)
        return port

    monkeypatch.setattr(stack_module, "free_port", draw)
    second = LocalStack(redis_binary=embedded_redis_server())
    try:
        second.start_redis()
        second.start_api()
        assert drawn[0] == port_of(first.redis_url) and port_of(second.redis_url) == drawn[1] != drawn[0]
        assert drawn[2] == port_of(first.api_url) and port_of(second.api_url) == drawn[3] != drawn[2]
        # Each stack reaches its own servers: Redis by the folder it keeps its data in, the API by its own key.
        for running in (first, second):
            client = redis.Redis.from_url(running.redis_url)
            assert client.config_get("dir")["dir"] == os.path.realpath(running.root / "redis")
            client.close()
        key = {"Authorization": f"Bearer {second.api_key}"}
        assert httpx.get(f"{second.api_url}/v1/jobs", headers=key, timeout=10).status_code == 200
        assert httpx.get(f"{first.api_url}/v1/jobs", headers=key, timeout=10).status_code == 401
        assert [c.name for c in second.children if c.alive()] == ["redis", "api"]
    finally:
        second.cleanup()

