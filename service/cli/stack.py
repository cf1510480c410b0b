"""A whole service on one machine, as child processes: redis-server, the API and workers.

Used by ``symgs demo``, the integration tests and the service benchmark. Every process runs in its own process
group, so stopping one also stops the Celery pool processes it forked.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import redis

from worker.store import JobStore

# The `symgs` command as this interpreter runs it (works without the console script on PATH; unlike `-m service.cli`
# it keeps one `service.cli` module, whose CliError the handlers raise).
SYMGS = [sys.executable, "-c", "import sys; from service.cli import main; sys.exit(main())"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class StackError(RuntimeError):
    """A process of the local stack did not start; the message ends with the tail of its log."""


@dataclass
class Child:
    name: str
    popen: subprocess.Popen
    log: Path

    def alive(self) -> bool:
        return self.popen.poll() is None

    def signal_group(self, sig: int) -> None:
        try:
            os.killpg(self.popen.pid, sig)
        except ProcessLookupError:
            pass

    def stop(self, timeout: float = 10.0) -> None:
        """SIGTERM (a worker finishes its job first, up to ``timeout``), then SIGKILL, for the whole group."""
        if self.alive():
            self.signal_group(signal.SIGTERM)
            try:
                self.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                pass
        self.signal_group(signal.SIGKILL)  # pool processes left behind
        self.popen.wait()

    def kill(self) -> None:
        """SIGKILL the process and its pool at once: a machine lost mid-job."""
        self.signal_group(signal.SIGKILL)
        self.popen.wait()

    def tail(self, lines: int = 30) -> str:
        try:
            return "\n".join(self.log.read_text(errors="replace").splitlines()[-lines:])
        except FileNotFoundError:
            return ""


def _spawn(name: str, argv: list[str], env: dict[str, str], logs: Path) -> Child:
    log = logs / f"{name}.log"
    with open(log, "ab") as out:
        popen = subprocess.Popen(
            argv, env=env, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True
        )
    return Child(name, popen, log)


def _wait(child: Child, ready, timeout: float, what: str) -> None:  # noqa: ANN001 - ready: () -> bool
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not child.alive():
            raise StackError(f"{child.name} exited with status {child.popen.returncode}:\n{child.tail()}")
        try:
            if ready():
                return
        except (OSError, redis.RedisError, httpx.HTTPError):
            pass
        time.sleep(0.1)
    child.stop()
    raise StackError(f"{child.name} did not {what} within {timeout:.0f} s:\n{child.tail()}")


@dataclass
class LocalStack:
    """redis-server, the API and workers on free ports, with storage in a temporary folder.

    ``env`` holds extra ``SYMGS_*`` settings for every process (API keys, limits, lease length, ...). With
    ``durable_redis`` Redis logs every write to its append-only file before answering, so a restart, even after
    SIGKILL, comes back with every job and queued message."""

    env: dict[str, str] = field(default_factory=dict)
    durable_redis: bool = False
    root: Path = field(default_factory=lambda: Path(tempfile.mkdtemp(prefix="symgs-stack-")))
    children: list[Child] = field(default_factory=list)
    workers: list[Child] = field(default_factory=list)
    api_url: str = ""
    redis_url: str = ""

    def child_env(self) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("SYMGS_")}
        env.update(
            SYMGS_REDIS_URL=self.redis_url, SYMGS_STORAGE=str(self.root / "storage"), PYTHONUNBUFFERED="1", **self.env
        )
        return env

    def start_redis(self, timeout: float = 20) -> None:
        """Start redis-server: on a free port the first time, on the same port again after ``stop_redis``."""
        binary = shutil.which("redis-server")
        if binary is None:
            raise StackError("redis-server is not installed (apt-get install redis-server)")
        port = int(self.redis_url.rsplit(":", 1)[1].split("/")[0]) if self.redis_url else free_port()
        data = self.root / "redis"
        data.mkdir(parents=True, exist_ok=True)
        aof = ["--appendonly", "yes", "--appendfsync", "always"] if self.durable_redis else ["--appendonly", "no"]
        argv = [binary, "--port", str(port), "--bind", "127.0.0.1", "--dir", str(data), "--save", "", *aof,
                "--loglevel", "warning"]  # fmt: skip
        child = _spawn("redis", argv, os.environ.copy(), self.root)
        self.children.insert(0, child)  # stopped last
        self.redis_url = f"redis://127.0.0.1:{port}/0"
        client = redis.Redis.from_url(self.redis_url)
        _wait(child, client.ping, timeout, "answer PING")
        client.close()

    def stop_redis(self, *, kill: bool = False) -> None:
        """Stop redis-server (SIGKILL with ``kill``: a crash); ``start_redis`` brings it back on the same port."""
        for child in [c for c in self.children if c.name == "redis"]:
            if kill:
                child.kill()
            else:
                child.stop(timeout=10)
            self.children.remove(child)

    def start_api(self, timeout: float = 30) -> None:
        port = free_port()
        argv = [*SYMGS, "serve", "--host", "127.0.0.1", "--port", str(port)]
        child = _spawn("api", argv, self.child_env(), self.root)
        self.children.append(child)
        self.api_url = f"http://127.0.0.1:{port}"
        _wait(child, lambda: httpx.get(f"{self.api_url}/healthz", timeout=2).status_code == 200, timeout, "serve")

    def start_worker(self, mode: str = "cpu", timeout: float = 60) -> Child:
        """Start a worker and wait for its first heartbeat."""
        store = JobStore.from_url(self.redis_url)
        before = store.live_workers(mode, 3600)
        argv = [*SYMGS, "worker", "--mode", mode, "--loglevel", "INFO"]
        child = _spawn(f"worker-{mode}-{len(self.workers)}", argv, self.child_env(), self.root)
        self.children.append(child)
        self.workers.append(child)
        _wait(child, lambda: store.live_workers(mode, 3600) > before, timeout, "send a heartbeat")
        store.r.close()
        return child

    def start(self, workers: int = 1) -> LocalStack:
        try:
            self.start_redis()
            self.start_api()
            for _ in range(workers):
                self.start_worker()
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        for child in reversed(self.children):  # workers and the API before Redis
            child.stop(timeout=5 if child.name != "redis" else 2)
        self.children.clear()
        self.workers.clear()

    def cleanup(self) -> None:
        self.stop()
        shutil.rmtree(self.root, ignore_errors=True)

    def __enter__(self) -> LocalStack:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.cleanup()
