"""Secure by default: `symgs serve` refuses to start without API keys unless told to run open, and then warns."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import httpx

from service.cli.stack import SYMGS, free_port, spawn, wait_until


def _env(**settings: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("SYMGS_")}
    # Nothing listens there: /healthz answers without Redis.
    return {**env, "SYMGS_REDIS_URL": "redis://127.0.0.1:1/0", **settings}


def test_serve_without_api_keys_refuses_to_start(tmp_path: Path) -> None:
    argv = [*SYMGS, "serve", "--port", str(free_port())]
    done = subprocess.run(argv, env=_env(SYMGS_API_KEYS=""), cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done
    assert "SYMGS_API_KEYS" in done.stderr and "SYMGS_AUTH=none" in done.stderr

    both = subprocess.run(argv, env=_env(SYMGS_API_KEYS="k1", SYMGS_AUTH="none"), capture_output=True, text=True,
                          timeout=60)  # fmt: skip
    assert both.returncode == 2 and "unset one of them" in both.stderr, both


def test_serve_open_when_told_so_answers_and_warns(tmp_path: Path) -> None:
    port = free_port()
    child = spawn(
        "api", [*SYMGS, "serve", "--port", str(port)], env=_env(SYMGS_API_KEYS="", SYMGS_AUTH="none"), logs=tmp_path,
        cwd=tmp_path,
    )  # fmt: skip
    try:
        url = f"http://127.0.0.1:{port}"
        wait_until(child, lambda: httpx.get(f"{url}/healthz", timeout=2).status_code == 200, 30, "serve")
        assert httpx.get(f"{url}/healthz").json() == {"status": "ok"}
    finally:
        child.stop()
    assert "authentication is OFF (SYMGS_AUTH=none)" in child.log.read_text()
