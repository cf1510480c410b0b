"""`symgs demo` on a machine with only Python: no redis-server on PATH and no SYMGS_REDIS_URL. It starts the
embedded Valkey server, gives the API a generated key, and runs a job to its end."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

from service.cli.stack import SYMGS


def test_demo_runs_to_its_end_without_redis_server(tmp_path: Path) -> None:
    from symgs_core.pipeline import decompress

    bare = tmp_path / "bin"  # a PATH with nothing on it: the demo finds no redis-server
    bare.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith("SYMGS_")}
    env["PATH"] = str(bare)
    out = tmp_path / "results"
    done = subprocess.run(
        [*SYMGS, "demo", "-o", str(out), "--gaussians", "1000"], env=env, cwd=tmp_path, capture_output=True, text=True,
        timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    assert "(valkey-server)" in done.stdout and "succeeded" in done.stdout
    assert len(decompress((out / "result.symgs").read_bytes())) > 0
    assert {"result.ply", "result.spz", "report.json"} <= {p.name for p in out.iterdir()}
