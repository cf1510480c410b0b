"""The command-line client against the real service: submit (following progress), status, fetch."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import httpx

from service.cli.stack import SYMGS
from symgs_core.config import DEFAULT_PRESET
from tests.integration.conftest import KEY_A, TINY


def symgs(stack, *args: str, timeout: float = 180) -> subprocess.CompletedProcess:  # noqa: ANN001
    argv = [*SYMGS, *args, "--server", stack.api_url, "--api-key", KEY_A]
    return subprocess.run(argv, capture_output=True, text=True, timeout=timeout)


def test_status_and_fetch(stack, done_job: dict, api_a: httpx.Client, tmp_path: Path) -> None:  # noqa: ANN001
    shown = symgs(stack, "status", done_job["id"], "--json")
    assert shown.returncode == 0, shown.stderr
    assert json.loads(shown.stdout) == api_a.get(f"/v1/jobs/{done_job['id']}").json()

    fetched = symgs(stack, "fetch", done_job["id"], "-o", str(tmp_path))
    assert fetched.returncode == 0, fetched.stderr
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file()) == sorted(
        done_job["artifacts"]
    )
    assert (tmp_path / "result.symgs").read_bytes() == api_a.get(f"/v1/jobs/{done_job['id']}/result").content

    missing = symgs(stack, "status", "0" * 32)
    assert missing.returncode == 2 and "not_found" in missing.stderr


def test_submit_follows_progress_and_downloads(stack, scene_path: Path, api_a: httpx.Client, tmp_path: Path) -> None:  # noqa: ANN001
    run = symgs(stack, "submit", str(scene_path), "--params", json.dumps(TINY), "-o", str(tmp_path))
    assert run.returncode == 0, run.stdout + run.stderr
    job_id = run.stdout.split("job ", 1)[1].split()[0]
    job = api_a.get(f"/v1/jobs/{job_id}").json()
    assert job["state"] == "succeeded"
    assert job["params"] == {**{k: None for k in job["params"]}, "preset": DEFAULT_PRESET, **TINY}
    assert (tmp_path / scene_path.stem / "result.symgs").read_bytes() == api_a.get(f"/v1/jobs/{job_id}/result").content

    queued = symgs(stack, "submit", str(scene_path), "--no-wait", "--params", json.dumps({**TINY, "iterations": 5000}))
    assert queued.returncode == 0, queued.stderr
    other = queued.stdout.split("job ", 1)[1].split()[0]
    assert api_a.post(f"/v1/jobs/{other}:cancel").status_code in (200, 202)

    bad = symgs(stack, "submit", str(scene_path), "--params", '{"iterations": -1}')
    assert bad.returncode == 2 and "bad_params" in bad.stderr
