"""The same scene with the same parameters gives a byte-identical archive by every door: Python, CLI and HTTP."""

from __future__ import annotations

import subprocess
from pathlib import Path

import httpx

from service.cli.stack import SYMGS
from symgs_core.config import CompressConfig
from symgs_core.pipeline import compress
from tests.integration.conftest import TINY, finished, submit, wait_for


def test_python_cli_and_http_write_the_same_archive(
    stack, scene_path: Path, api_a: httpx.Client, tmp_path: Path  # noqa: ANN001
) -> None:
    settings = {k: v for k, v in TINY.items() if k != "device"}  # no preset named: every door's default

    job = submit(api_a, scene_path, TINY).json()
    done = wait_for(api_a, job["id"], finished, timeout=300)
    assert done["state"] == "succeeded", done
    over_http = api_a.get(f"/v1/jobs/{job['id']}/result").content

    flags = [f"--{name.replace('_', '-')}={value}" for name, value in settings.items()]
    out = tmp_path / "cli.symgs"
    run = subprocess.run([*SYMGS, "compress", str(scene_path), "-o", str(out), "--device", "cpu", "--quiet", *flags],
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert run.returncode == 0, run.stderr
    by_cli = out.read_bytes()

    in_python = compress(scene_path, config=CompressConfig.for_preset(**settings, device="cpu")).archive

    assert over_http == by_cli == in_python
    assert done["params"]["preset"] == CompressConfig.for_preset().preset
